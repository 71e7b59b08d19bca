//! The last steps of every episode that ended one way: runs a controller on a cell (the
//! reference cell unless CELL names a cell file) as `celld eval` does (4000 episodes a seed,
//! 10 kept robots) and, for each episode whose outcome is OUTCOME (`success` or a failure code
//! such as `uncertain` or `step_limit`), prints its last STEPS steps: the true insertion (mm),
//! sideways error (mm) and tilt (deg); the estimate's insertion, sideways offset and its σ
//! (mm) as the controller saw them; the move asked (mm); the supervisor's refusal; and the
//! step's `detected` field (docs/estimation.md §5).
//!
//! `cargo run --release -p cell-research -- failure_trace
//! CONTROLLER NOISE OUTCOME SEEDS [STEPS
//! [FAULT [CELL [CALIBRATION [ROBOTS]]]]]` (SEEDS comma-separated; STEPS default 40; FAULT a
//! fault's code, as `celld eval --fault`, or `none`; CELL a cell file or `reference`;
//! CALIBRATION the calibration error's multiple, as `celld eval --calibration-scale`, default
//! 1; ROBOTS the kept robots, as `celld eval --robots`, default 10, 0 for a new robot every
//! episode).

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::eval::{episode_seed, robot_blocks, run_episode_watched};
use assembly_cell::policy::{self, Controller, Decision};
use assembly_cell::sim::{AssemblyEnv, EnvOptions, Fault, Observation, StepResult};
use rayon::prelude::*;
use std::path::Path;

const EPISODES: usize = 4000;

/// One step as a line: the truth after it, the estimate the controller acted on, its move.
fn line(
    depth_mm: f64,
    observation: &Observation,
    decision: &Decision,
    result: &StepResult,
) -> String {
    let (asked, truth) = (decision.action.translation_mm, result.true_errors);
    format!(
        "{:3} in {:6.2} off {:.3} tilt {:.3} | est in {:6.2} off {:.3} σ {:.4} | asked ({:+.3}, {:+.3}, {:+.2}) refused {} detected {}",
        observation.step,
        truth.depth_error_mm + depth_mm,
        truth.lateral_mm,
        truth.tilt_deg,
        observation.insertion_mm(),
        observation.state[6].hypot(observation.state[7]),
        observation.estimate.lateral_sd_mm(),
        asked.x,
        asked.y,
        asked.z,
        result.veto.as_ref().map_or("-", |v| v.code()),
        result.detected.unwrap_or("-"),
    )
}

/// The episodes of one evaluation seed that ended in `wanted`, each with its last `keep` lines.
fn traces(
    cell: &CellConfig,
    make: &policy::ControllerFactory,
    options: EnvOptions,
    wanted: &str,
    seed: u64,
    keep: usize,
) -> Vec<(usize, Vec<String>)> {
    let depth_mm = cell.bore.depth_mm;
    robot_blocks(options, EPISODES, seed)
        .into_par_iter()
        .flat_map_iter(|(kept, block)| {
            let mut env = AssemblyEnv::new(cell, kept);
            let mut controller: Box<dyn Controller> = make();
            block
                .into_iter()
                .filter_map(|index| {
                    let mut lines = Vec::new();
                    let report = run_episode_watched(
                        &mut env,
                        controller.as_mut(),
                        index,
                        episode_seed(seed, index),
                        &mut |observation, decision, result| {
                            lines.push(line(depth_mm, observation, decision, result))
                        },
                    );
                    let start = lines.len().saturating_sub(keep);
                    (report.outcome == wanted).then(|| (index, lines.split_off(start)))
                })
                .collect::<Vec<_>>()
        })
        .collect()
}

pub fn main() -> anyhow::Result<()> {
    let args: Vec<String> = cell_research::args().collect();
    let usage = "usage: failure_trace CONTROLLER NOISE OUTCOME SEEDS [STEPS [FAULT [CELL [CALIBRATION [ROBOTS]]]]]";
    let (Some(name), Some(noise), Some(wanted), Some(seeds)) =
        (args.get(1), args.get(2), args.get(3), args.get(4))
    else {
        anyhow::bail!(usage);
    };
    let noise_scale: f64 = noise
        .parse()
        .map_err(|_| anyhow::anyhow!("NOISE: {noise}"))?;
    let seeds = cell_research::seeds(seeds)?;
    let keep: usize = cell_research::arg(5, 40)?;
    let fault: Option<Fault> = match args.get(6).map(String::as_str) {
        None | Some("none") => None,
        Some(code) => Some(code.parse()?),
    };
    let cell = match args.get(7).map(String::as_str) {
        None | Some("reference") => CellConfig::reference(),
        Some(path) => CellConfig::load(Path::new(path))?,
    };
    let calibration_scale: f64 = cell_research::arg(8, 1.0)?;
    let kept_robots: u32 = cell_research::arg(9, 10)?;
    let options = EnvOptions {
        noise_scale,
        calibration_scale,
        kept_robots,
        fault,
        ..EnvOptions::from_cell(&cell)
    };
    let make = policy::builtin_factory(name, &cell)?;
    for seed in seeds {
        for (index, lines) in traces(&cell, &make, options, wanted, seed, keep) {
            let fault = fault.map_or(String::new(), |f| format!(", fault {f}"));
            println!(
                "== {name} on {}, noise ×{noise_scale}, calibration ×{calibration_scale}{fault}, \
                 seed {seed}, episode {index}: {wanted}",
                cell.name
            );
            for line in lines {
                println!("{line}");
            }
        }
    }
    Ok(())
}
