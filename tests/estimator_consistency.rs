//! The state estimate's covariance against the twin's truth: over many episodes of the expert,
//! the normalised estimation error squared (NEES) of each of the six components of {F} in {M}
//! averages 1 when the covariance is right, whatever the camera's true noise (0.25× to 8× its
//! data sheet) and the robot's calibration error (0 to 3× the cell file's).

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::{Controller, expert::Expert};
use assembly_cell::sim::{AssemblyEnv, EnvOptions};

/// Mean NEES per component and joint (all six, correlations included) over `episodes` expert
/// episodes, and the noise scale learned at the end.
fn mean_nees(noise_scale: f64, calibration_scale: f64, episodes: u64) -> ([f64; 6], f64, f64) {
    let mut cell = CellConfig::reference();
    cell.imperfections.calibration_error_mm *= calibration_scale;
    let options = EnvOptions {
        noise_scale,
        ..EnvOptions::from_cell(&cell)
    };
    let mut env = AssemblyEnv::new(&cell, options);
    let mut controller = Expert::new(&cell);
    let (mut sum, mut joint, mut count, mut scale) = ([0.0; 6], 0.0, 0.0, 0.0);
    for seed in 0..episodes {
        controller.reset(seed);
        let mut observation = env.reset(1000 + seed).unwrap();
        loop {
            let action = controller.act(&observation).action;
            let result = env.step(&action).unwrap();
            if result.observation.measurement_fresh {
                let truth = env.true_f_m().inverse();
                let estimate = &result.observation.estimate;
                if let (Some(nees), Some(all)) =
                    (estimate.nees(&truth), estimate.joint_nees(&truth))
                {
                    for (s, n) in sum.iter_mut().zip(nees) {
                        *s += n;
                    }
                    joint += all;
                    count += 1.0;
                    scale = result.observation.estimate.noise_scale();
                }
            }
            observation = result.observation;
            if result.done {
                break;
            }
        }
    }
    (sum.map(|s| s / count), joint / count, scale)
}

#[test]
fn the_covariance_is_consistent_across_noise_and_calibration() {
    for noise in [0.25, 1.0, 2.0, 4.0, 8.0] {
        for calibration in [0.0, 1.0, 3.0] {
            let (nees, joint, scale) = mean_nees(noise, calibration, 60);
            let label = format!(
                "noise ×{noise}, calibration ×{calibration}: NEES {nees:.2?}, joint {joint:.2}"
            );
            eprintln!("{label}");
            // The band: the joint six-component NEES averages between 0.5 and 1.2 times its
            // dimension, and no component averages above 1.5 (overconfident in that axis).
            assert!((3.0..=7.2).contains(&joint), "{label}");
            assert!(nees.iter().all(|&n| n <= 1.5), "{label}");
            // The noise it learned from the residuals is the camera's.
            assert!(
                (scale / noise - 1.0).abs() < 0.15,
                "{label}: learned ×{scale:.2}"
            );
        }
    }
}
