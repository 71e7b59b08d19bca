//! Where a controller's steps go on the reference cell: per zone (the tip more than 5 mm above
//! the bore's entrance, within 5 mm of it, in the bore), the moves, turns and holds it asks for,
//! how far down it asks to go, and the supervisor's refusals by reason, averaged over the
//! episodes that succeed. With the
//! camera's noise four times its data sheet's, it shows what the waits for certainty cost.
//!
//! `cargo run --release -p cell-research -- where_the_steps_go
//! CONTROLLER [NOISE] [EPISODES] [SEED]
//! [DEADBAND [FROM_MM]]` (a built-in controller or a policy file; defaults 1, 1000, 1). With
//! DEADBAND = k, a move that goes deeper once the tip is FROM_MM (default 0.2) into the bore
//! (negative: above it) loses its sideways part when that part is under k × the estimate's
//! sideways σ, keeping the steering against the learned drift: the controller waits for the
//! estimate rather than centring on its noise. 10 kept robots, as `celld eval`.

use cell_research::{arg, zone};

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::eval::{episode_seed, robot_blocks, run_episode_watched};
use assembly_cell::policy::{Controller, Decision, steered_against_drift};
use assembly_cell::sim::{AssemblyEnv, EnvOptions, Observation};
use nalgebra::Vector3;
use rayon::prelude::*;
use std::collections::BTreeMap;

/// A controller whose small sideways corrections on the way in are dropped.
struct Deadband {
    inner: Box<dyn Controller>,
    sigmas: f64,
    from_mm: f64,
}

impl Controller for Deadband {
    fn name(&self) -> &str {
        "deadband"
    }

    fn reset(&mut self, seed: u64) {
        self.inner.reset(seed)
    }

    fn act(&mut self, observation: &Observation) -> Decision {
        let mut decision = self.inner.act(observation);
        let inserted_mm = observation.insertion_mm();
        let drift = observation.estimate.drift();
        let step = &mut decision.action.translation_mm;
        // The command before the steering against the drift (to first order in the drift).
        let correction = drift * *step;
        let wanted = *step + Vector3::new(correction.x, correction.y, 0.0);
        let small = wanted.xy().norm() < self.sigmas * observation.estimate.lateral_sd_mm();
        if inserted_mm > self.from_mm && step.z < 0.0 && small {
            *step = steered_against_drift(&drift, Vector3::new(0.0, 0.0, wanted.z));
        }
        decision
    }
}

pub fn main() -> anyhow::Result<()> {
    let controller: String = arg(1, "expert".to_string())?;
    let noise_scale: f64 = arg(2, 1.0)?;
    let episodes: usize = arg(3, 1000)?;
    let seed: u64 = arg(4, 1)?;
    let deadband: f64 = arg(5, 0.0)?;
    let from_mm: f64 = arg(6, 0.2)?;
    let cell = CellConfig::reference();
    let make = cell_research::controller_factory(&controller, &cell)?;
    let options = EnvOptions {
        noise_scale,
        kept_robots: 10,
        ..EnvOptions::from_cell(&cell)
    };
    let counts: Vec<BTreeMap<String, f64>> = robot_blocks(options, episodes, seed)
        .into_par_iter()
        .flat_map_iter(|(kept, block)| {
            let mut env = AssemblyEnv::new(&cell, kept);
            let mut controller = make();
            if deadband > 0.0 {
                controller = Box::new(Deadband {
                    inner: controller,
                    sigmas: deadband,
                    from_mm,
                });
            }
            let mut successes = Vec::new();
            for index in block {
                let mut count = BTreeMap::<String, f64>::new();
                let report = run_episode_watched(
                    &mut env,
                    controller.as_mut(),
                    index,
                    episode_seed(seed, index),
                    &mut |observation, decision, result| {
                        let zone = zone(observation);
                        let action = &decision.action;
                        let kind = match (action.translation_mm.norm(), action.rotation_deg.norm())
                        {
                            (t, r) if t == 0.0 && r == 0.0 => "hold",
                            (_, r) if r > 0.0 => "turn",
                            _ => "move",
                        };
                        *count.entry(format!("{zone} {kind}")).or_default() += 1.0;
                        if action.translation_mm.z < 0.0 {
                            *count
                                .entry(format!("{zone} descent asked (mm)"))
                                .or_default() -= action.translation_mm.z;
                        }
                        if let Some(veto) = &result.veto {
                            *count
                                .entry(format!("{zone} refused: {}", veto.code()))
                                .or_default() += 1.0;
                        }
                    },
                );
                if report.succeeded() {
                    count.insert("steps".into(), report.steps as f64);
                    successes.push(count);
                }
            }
            successes
        })
        .collect();
    let mut mean = BTreeMap::<String, f64>::new();
    for count in &counts {
        for (key, value) in count {
            *mean.entry(key.clone()).or_default() += value / counts.len() as f64;
        }
    }
    println!(
        "{controller}: {} of {episodes} succeeded (noise ×{noise_scale}, seed {seed}); per success:",
        counts.len()
    );
    for (key, value) in mean {
        println!("  {key:32} {value:8.2}");
    }
    Ok(())
}
