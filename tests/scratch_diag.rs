use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::{Controller, expert::Expert};
use assembly_cell::sim::{AssemblyEnv, EnvOptions};

#[test]
fn diag() {
    let cell = CellConfig::reference();
    let options = EnvOptions { noise_scale: 2.0, ..EnvOptions::from_cell(&cell) };
    let mut env = AssemblyEnv::new(&cell, options);
    let mut controller = Expert::new(&cell);
    controller.reset(1);
    let mut observation = env.reset(1001).unwrap();
    for _ in 0..300 {
        let action = controller.act(&observation).action;
        let result = env.step(&action).unwrap();
        let sd = result.observation.estimate.sd();
        let s = &result.observation.state;
        eprintln!("{:3} act [{:.3} {:.3} {:.3}] P [{:.3} {:.3} {:.2}] sd lat {:.4} tilt {:.5}deg veto {:?} det {:?}",
            result.observation.step, action.translation_mm.x, action.translation_mm.y, action.translation_mm.z,
            s[6], s[7], s[8], sd.lateral_mm, sd.tilt_rad.to_degrees(),
            result.veto.map(|v| v.code()), result.detected);
        observation = result.observation;
        if result.done { eprintln!("{:?}", result.outcome); break; }
    }
}
