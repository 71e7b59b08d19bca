//! How many frames a still cell needs before it may insert: the estimate's sideways σ at the
//! bore's entrance and 60 mm below it (the tip of a fully inserted shaft on the reference cell)
//! after n frames with the robot holding, averaged over 20 episodes of the twin. The supervisor
//! needs the σ at the tip below 0.05 mm / 4.57 ≈ 0.011 mm (1e-4 per move, a perfectly centred
//! estimate) before the shaft may reach the bottom (docs/estimation.md).
//!
//! `cargo run --release -p cell-research -- still_frames
//! 4` (the camera's noise × its data sheet).

use assembly_cell::config::cell::CellConfig;
use assembly_cell::geometry::Move;
use assembly_cell::geometry::belief::largest_sd;
use assembly_cell::sim::{AssemblyEnv, EnvOptions};
use nalgebra::{Matrix2x6, Matrix6};

const FRAMES: usize = 300;
const EPISODES: u64 = 20;

/// σ (mm) of the worst sideways direction of a point on the bore's axis `z_mm` below the
/// entrance, for estimate errors of covariance `c` (`δP mm, δO rad` in {M}; twist left out).
fn sideways_sd_mm(c: &Matrix6<f64>, z_mm: f64) -> f64 {
    let j = Matrix2x6::new(
        1.0, 0.0, 0.0, 0.0, -z_mm, 0.0, //
        0.0, 1.0, 0.0, z_mm, 0.0, 0.0,
    );
    largest_sd(&(j * c * j.transpose()))
}

pub fn main() {
    let noise_scale: f64 = cell_research::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(1.0);
    let cell = CellConfig::reference();
    let depth_mm = cell.bore.depth_mm;
    let options = EnvOptions {
        noise_scale,
        ..EnvOptions::from_cell(&cell)
    };
    let mut env = AssemblyEnv::new(&cell, options);
    // Per frame count: (sum of σ at the entrance, sum of σ at the depth, episodes).
    let mut sums = vec![(0.0, 0.0, 0u32); FRAMES + 1];
    for seed in 0..EPISODES {
        let mut observation = env.reset(seed).expect("the reference cell resets");
        for sum in sums.iter_mut().skip(1) {
            let c = observation.estimate.covariance();
            sum.0 += sideways_sd_mm(&c, 0.0);
            sum.1 += sideways_sd_mm(&c, depth_mm);
            sum.2 += 1;
            let result = env.step(&Move::default()).expect("a hold is a valid step");
            observation = result.observation;
            if result.done {
                break;
            }
        }
    }
    println!("noise ×{noise_scale}, {EPISODES} episodes holding still:");
    println!("frames | σ at the entrance (mm) | σ {depth_mm} mm deep (mm)");
    for n in [10, 25, 50, 100, 150, 200, 250, 300] {
        let (entrance, deep, count) = sums[n];
        if count > 0 {
            let count = f64::from(count);
            println!("{n:6} | {:.4} | {:.4}", entrance / count, deep / count);
        }
    }
}
