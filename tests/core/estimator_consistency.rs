//! The state estimate's covariance against the twin's truth: over many episodes of the expert,
//! the normalised estimation error squared (NEES) of each of the six components of {F} in {M}
//! averages 1 when the covariance is right, whatever the camera's true noise (0.25× to 8× its
//! data sheet) and the robot's calibration error (0 to 3× the cell file's).

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::{Controller, expert::Expert};
use assembly_cell::sim::{AssemblyEnv, EnvOptions};

/// Mean NEES per component and joint (all six, correlations included) over `episodes` expert
/// episodes, and the noise scale learned at the end.
/// With `kept_robots` 1 the cell keeps its robot and starts each episode from the drift it
/// remembers (docs/estimation.md §3a).
fn mean_nees(
    noise_scale: f64,
    calibration_scale: f64,
    episodes: u64,
    kept_robots: u32,
) -> ([f64; 6], f64, f64) {
    let mut cell = CellConfig::reference();
    cell.imperfections.calibration_error_mm *= calibration_scale;
    let options = EnvOptions {
        noise_scale,
        kept_robots,
        robot_seed: 11,
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

/// The band: the joint six-component NEES averages between 0.5 and 1.2 times its dimension,
/// no component averages above 1.5 (overconfident in that axis), and the noise learned from
/// the residuals is the camera's.
fn assert_consistent(noises: &[f64], calibrations: &[f64], kept_robots: u32) {
    for &noise in noises {
        for &calibration in calibrations {
            let (nees, joint, scale) = mean_nees(noise, calibration, 60, kept_robots);
            let label = format!(
                "noise ×{noise}, calibration ×{calibration}, kept robots {kept_robots}: \
                 NEES {nees:.2?}, joint {joint:.2}"
            );
            eprintln!("{label}");
            assert!((3.0..=7.2).contains(&joint), "{label}");
            assert!(nees.iter().all(|&n| n <= 1.5), "{label}");
            assert!(
                (scale / noise - 1.0).abs() < 0.15,
                "{label}: learned ×{scale:.2}"
            );
        }
    }
}

#[test]
fn the_covariance_is_consistent_across_noise_and_calibration() {
    assert_consistent(&[0.25, 1.0, 2.0, 4.0, 8.0], &[0.0, 1.0, 3.0], 0);
}

/// Started from a remembered drift, the filter is as honest: the memory's own uncertainty is
/// carried into each episode.
#[test]
fn the_covariance_stays_consistent_when_the_robot_is_kept() {
    assert_consistent(&[1.0, 4.0], &[0.0, 1.0, 3.0], 1);
}
