use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::{self, eval};
use assembly_cell::sim::{AssemblyEnv, EnvOptions};
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).cloned().unwrap_or("expert".into());
    let index: usize = args.get(2).map(|s| s.parse().unwrap()).unwrap_or(0);
    let mut cell = CellConfig::reference();
    for kv in args.iter().skip(3) {
        match kv.as_str() {
            "nonoise" => cell.imperfections.camera_noise = false,
            "nocal" => cell.imperfections.calibration_error = false,
            "noexec" => cell.imperfections.execution_error = false,
            "nolat" => cell.imperfections.latency = false,
            _ => {}
        }
    }
    let seed = eval::episode_seed(1, index);
    let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
    let mut c = policy::builtin(&name, &cell).unwrap();
    c.reset(seed ^ 0x5EED_C0DE);
    let mut obs = env.reset(seed).unwrap();
    loop {
        let d = c.act(&obs);
        let r = env.step(&d.action).unwrap();
        let s = r.observation.state;
        let f = env.true_f_m();
        println!(
            "{:3} a=[{:7.3} {:7.3} {:7.3} | {:6.3} {:6.3} {:6.3}] P=[{:8.3} {:8.3} {:8.3}] O=[{:6.3} {:6.3} {:6.3}] true lat {:.4} depth {:8.3} tilt {:.4} arc {:.4} tf=({:.4},{:.4}) veto {:?} {:?}",
            r.observation.step,
            d.action.translation_mm.x,
            d.action.translation_mm.y,
            d.action.translation_mm.z,
            d.action.rotation_deg.x,
            d.action.rotation_deg.y,
            d.action.rotation_deg.z,
            s[6],
            s[7],
            s[8],
            s[9],
            s[10],
            s[11],
            r.true_errors.lateral_mm,
            r.true_errors.depth_error_mm,
            r.true_errors.tilt_deg,
            r.true_errors.hole_arc_mm,
            f.translation.vector.x,
            f.translation.vector.y,
            r.veto.map(|v| v.to_string()),
            r.outcome
        );
        obs = r.observation;
        if r.done {
            break;
        }
    }
}
