//! How the cell's check of a kept robot's remembered drift does (docs/estimation.md §3a), two
//! ways:
//!
//! - `kept CONTROLLER NOISE CALIBRATION SEEDS`: runs a controller as `celld eval` does (10 kept
//!   robots, 4000 episodes a seed, the calibration error that many times the cell file's) and
//!   counts how the episodes ended, split by whether the cell named `robot_changed` in them: a
//!   kept robot is never changed here, so every such episode is a false alarm.
//! - `swapped NOISE CALIBRATION PAIRS`: for each pair of robots, `expert` runs ten episodes on
//!   one, then the robot is replaced without the cell being told, and the first episode on the
//!   new one is counted: named `robot_changed`, and how it ended.
//!
//! `cargo run --release -p cell-research -- robot_changed kept expert 1 3 1,2,3,4`
//! `cargo run --release -p cell-research -- robot_changed swapped 1 1 100`

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::eval::{episode_seed, robot_blocks, run_episode_watched};
use assembly_cell::policy::{self, Controller};
use assembly_cell::sim::{AssemblyEnv, EnvOptions};
use rayon::prelude::*;
use std::collections::BTreeMap;

const EPISODES: usize = 4000;

/// One episode: whether the cell named `robot_changed` in it, and how it ended.
fn episode(env: &mut AssemblyEnv, controller: &mut dyn Controller, seed: u64) -> (bool, String) {
    let mut changed = false;
    let report = run_episode_watched(env, controller, 0, seed, &mut |_, _, result| {
        changed |= result.detected == Some("robot_changed")
    });
    (changed, report.outcome)
}

/// Prints how many episodes ended each way, split by whether `robot_changed` was named.
fn print_tally(episodes: impl IntoIterator<Item = (bool, String)>) {
    let mut counts: BTreeMap<(bool, String), usize> = BTreeMap::new();
    for key in episodes {
        *counts.entry(key).or_default() += 1;
    }
    for ((changed, outcome), n) in counts {
        let named = if changed {
            "robot_changed"
        } else {
            "not named"
        };
        println!("{named:14} {outcome:16} {n}");
    }
}

fn kept(cell: &CellConfig, options: EnvOptions, name: &str, seeds: &[u64]) -> anyhow::Result<()> {
    let make = policy::builtin_factory(name, cell)?;
    let mut episodes: Vec<(bool, String)> = Vec::new();
    for &seed in seeds {
        episodes.par_extend(
            robot_blocks(options, EPISODES, seed)
                .into_par_iter()
                .flat_map_iter(|(kept, block)| {
                    let mut env = AssemblyEnv::new(cell, kept);
                    let mut controller = make();
                    block
                        .into_iter()
                        .map(|index| {
                            episode(&mut env, controller.as_mut(), episode_seed(seed, index))
                        })
                        .collect::<Vec<_>>()
                }),
        );
    }
    println!(
        "{name}, noise ×{}, calibration ×{}, seeds {seeds:?} ({} episodes):",
        options.noise_scale,
        options.calibration_scale,
        EPISODES * seeds.len()
    );
    print_tally(episodes);
    Ok(())
}

fn swapped(cell: &CellConfig, options: EnvOptions, pairs: u64) -> anyhow::Result<()> {
    let make = policy::builtin_factory("expert", cell)?;
    let firsts: Vec<(bool, String)> = (0..pairs)
        .into_par_iter()
        .map(|pair| {
            let kept = EnvOptions {
                kept_robots: 1,
                robot_seed: 100 + pair,
                ..options
            };
            let mut env = AssemblyEnv::new(cell, kept);
            let mut controller = make();
            for i in 0..10 {
                episode(&mut env, controller.as_mut(), episode_seed(pair, i));
            }
            env.swap_robot(500 + pair);
            episode(&mut env, controller.as_mut(), episode_seed(pair, 10))
        })
        .collect();
    println!(
        "the first episode after an unannounced swap, {pairs} pairs, noise ×{}, calibration ×{}:",
        options.noise_scale, options.calibration_scale
    );
    print_tally(firsts);
    Ok(())
}

pub fn main() -> anyhow::Result<()> {
    let usage = "usage: robot_changed kept CONTROLLER NOISE CALIBRATION SEEDS | swapped NOISE CALIBRATION PAIRS";
    let mode: String = cell_research::arg(1, String::new())?;
    let cell = CellConfig::reference();
    let with = |noise_scale, calibration_scale| EnvOptions {
        noise_scale,
        calibration_scale,
        kept_robots: 10,
        ..EnvOptions::from_cell(&cell)
    };
    match mode.as_str() {
        "kept" => {
            let name: String = cell_research::arg(2, "expert".to_string())?;
            let options = with(cell_research::arg(3, 1.0)?, cell_research::arg(4, 1.0)?);
            let seeds = cell_research::seeds(&cell_research::arg(5, "1".to_string())?)?;
            kept(&cell, options, &name, &seeds)
        }
        "swapped" => {
            let options = with(cell_research::arg(2, 1.0)?, cell_research::arg(3, 1.0)?);
            swapped(&cell, options, cell_research::arg(4, 100)?)
        }
        _ => anyhow::bail!(usage),
    }
}
