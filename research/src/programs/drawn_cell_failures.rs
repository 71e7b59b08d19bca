//! Which drawn cells a controller fails on: runs `celld eval --controller C --randomise-cells
//! --randomise-noise-up-to NOISE --robots 400 --episodes 4000 --seed SEED` and prints every
//! episode that ended in OUTCOME with the cell it ran on (bore, radial clearance, depth, holes,
//! camera noise, calibration error, latency) and its true errors at the end.
//!
//! `cargo run --release -p cell-research -- drawn_cell_failures
//! CONTROLLER SEED [OUTCOME] [NOISE]`
//! (built-in controllers; defaults `contact` and 4).

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::{self, eval};
use assembly_cell::sim::EnvOptions;
use assembly_cell::sim::randomise::{CellRanges, cell_for};

const EPISODES: usize = 4000;
const ROBOTS: u32 = 400;

pub fn main() -> anyhow::Result<()> {
    let args: Vec<String> = cell_research::args().collect();
    let (Some(name), Some(seed)) = (args.get(1), args.get(2)) else {
        anyhow::bail!("usage: drawn_cell_failures CONTROLLER SEED [OUTCOME] [NOISE]");
    };
    let seed: u64 = seed.parse()?;
    let outcome = args.get(3).map_or("contact", String::as_str);
    let noise_up_to: f64 = args.get(4).map_or(Ok(4.0), |a| a.parse())?;
    let base = CellConfig::reference();
    let ranges = CellRanges::drawn(Some(noise_up_to))?;
    let options = EnvOptions {
        kept_robots: ROBOTS,
        ..EnvOptions::from_cell(&base)
    };
    let _known = policy::builtin_factory(name, &base)?;
    let make = |cell: &CellConfig| {
        policy::builtin_factory(name, cell).expect("a built-in controller, checked above")()
    };
    let (_, reports) =
        eval::evaluate_on_drawn_cells(&base, &ranges, options, EPISODES, seed, &make, &|_| {});
    let blocks = eval::robot_blocks(options, EPISODES, seed);
    for report in reports.iter().filter(|r| r.outcome == outcome) {
        let (kept, block) = blocks
            .iter()
            .find(|(_, block)| block.contains(&report.index))
            .expect("every episode is in a robot's block");
        let (cell, drawn) = cell_for(&base, kept, Some(&ranges), kept.robot_seed);
        let errors = &report.final_errors;
        println!(
            "episode {} ({} of its robot's) at step {}: bore Φ{:.1} mm, clearance {:.3} mm, \
             depth {:.1} mm, {} holes, noise ×{:.2}, calibration ×{:.2}, latency {:.3} s; \
             lateral {:.4} mm, {:.1} mm from seated, tilt {:.4}°",
            report.index,
            report.index - block.start + 1,
            report.steps,
            cell.bore.diameter_mm,
            cell.radial_clearance_mm(),
            cell.bore.depth_mm,
            cell.bore.holes,
            drawn.noise_scale,
            drawn.calibration_scale,
            cell.camera.latency_s,
            errors.lateral_mm,
            -errors.depth_error_mm,
            errors.tilt_deg,
        );
    }
    Ok(())
}
