//! How often the shift watch suspects or confirms a camera shift that did not happen, on the
//! reference cell with no fault injected: in episodes of a cell holding still for a number of
//! frames, or in episodes of a controller (10 kept robots, as `celld eval`), with how many of
//! the episodes that failed were suspected at some step (docs/estimation.md §1a).
//!
//! `cargo run --release -p cell-research -- shift_watch still [NOISE] [EPISODES] [FRAMES]`
//! `cargo run --release -p cell-research -- shift_watch CONTROLLER [NOISE] [EPISODES] [SEED]`
//! (defaults: noise 1, 400 still episodes of 300 frames; 4000 episodes of a controller, seed 1).

use cell_research::arg;

use assembly_cell::config::cell::CellConfig;
use assembly_cell::geometry::Move;
use assembly_cell::policy::eval::{episode_seed, robot_blocks, run_episode_watched};
use assembly_cell::policy::{self, Controller};
use assembly_cell::sim::{AssemblyEnv, EnvOptions};
use rayon::prelude::*;

/// What one episode showed: suspected at some step, a shift confirmed, succeeded.
#[derive(Default, Clone, Copy)]
struct Seen {
    suspected: bool,
    confirmed: bool,
    succeeded: bool,
}

fn note(seen: &mut Seen, detected: Option<&str>) {
    seen.suspected |= detected == Some("camera_shift_suspected");
    seen.confirmed |= detected == Some("camera_shift");
}

fn still(cell: &CellConfig, noise_scale: f64, episodes: u64, frames: usize) -> Vec<Seen> {
    let options = EnvOptions {
        noise_scale,
        ..EnvOptions::from_cell(cell)
    };
    let mut env = AssemblyEnv::new(cell, options);
    (0..episodes)
        .map(|seed| {
            let mut seen = Seen::default();
            env.reset(seed).expect("the reference cell resets");
            for _ in 0..frames {
                let result = env.step(&Move::default()).expect("a hold is a valid step");
                note(&mut seen, result.detected);
                if result.done {
                    break;
                }
            }
            seen
        })
        .collect()
}

fn run(
    cell: &CellConfig,
    make: &policy::ControllerFactory,
    noise_scale: f64,
    episodes: usize,
    seed: u64,
) -> Vec<Seen> {
    let options = EnvOptions {
        noise_scale,
        kept_robots: 10,
        ..EnvOptions::from_cell(cell)
    };
    robot_blocks(options, episodes, seed)
        .into_par_iter()
        .flat_map_iter(|(kept, block)| {
            let mut env = AssemblyEnv::new(cell, kept);
            let mut controller: Box<dyn Controller> = make();
            block
                .into_iter()
                .map(|index| {
                    let mut seen = Seen::default();
                    let report = run_episode_watched(
                        &mut env,
                        controller.as_mut(),
                        index,
                        episode_seed(seed, index),
                        &mut |_, _, result| note(&mut seen, result.detected),
                    );
                    seen.succeeded = report.succeeded();
                    seen
                })
                .collect::<Vec<_>>()
        })
        .collect()
}

pub fn main() -> anyhow::Result<()> {
    let what: String = arg(1, "still".to_string())?;
    let noise_scale: f64 = arg(2, 1.0)?;
    let cell = CellConfig::reference();
    let seen = if what == "still" {
        let (episodes, frames) = (arg(3, 400u64)?, arg(4, 300usize)?);
        println!("noise ×{noise_scale}, {episodes} episodes holding still for {frames} frames:");
        still(&cell, noise_scale, episodes, frames)
    } else {
        let (episodes, seed) = (arg(3, 4000usize)?, arg(4, 1u64)?);
        let make = policy::builtin_factory(&what, &cell)?;
        println!("{what}, noise ×{noise_scale}, {episodes} episodes, seed {seed}:");
        run(&cell, &make, noise_scale, episodes, seed)
    };
    let count = |f: fn(&Seen) -> bool| seen.iter().filter(|s| f(s)).count();
    println!("  suspected at some step: {}", count(|s| s.suspected));
    println!("  a shift confirmed:      {}", count(|s| s.confirmed));
    if what != "still" {
        println!("  failed:                 {}", count(|s| !s.succeeded));
        println!(
            "  failed, suspected:      {}",
            count(|s| !s.succeeded && s.suspected)
        );
    }
    Ok(())
}
