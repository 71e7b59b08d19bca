//! The bundled policies hold their goals: the cross-cell policies on the deep, tight cells
//! they were not trained on (success within 0.01 of `expert`'s on the same episodes, and no
//! episode driven out of the workspace), and every hierarchical policy on the reference cell
//! (no more failures than `expert`, the fast ones in at most 40 steps) and under a camera two
//! and four times as noisy as its data sheet (the goals' floors, 0.99 and 0.62, and no step
//! back from `expert` that 2000 episodes can see). A bundled file stays
//! as it was while the code around it changes: under decisions 0044–0046 the careful
//! cross-cell file of decision 0043 came to hit the step limit in 3.5 % of episodes on
//! phi100-deep, and nothing showed it until its recipe was run again (decision 0050). On
//! these 400 episodes that file succeeds 0.965 against `expert`'s 0.9925 on phi100-deep, and
//! 0.9825 against 1.0 on c120-tight-deep-small-robot.
//!
//! The 4000-episode figures of docs/learning.md: `celld eval --controller NAME --cell FILE
//! --episodes 4000 --seed 2`, on the reference cell `--seed 21` to `24`, and under the noisy
//! camera `--noise-scale 2|4` over the seeds its tables name.

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::builtin_factory;
use assembly_cell::policy::eval::{DEFAULT_KEPT_ROBOTS, EvalSummary, evaluate};
use assembly_cell::sim::EnvOptions;
use std::path::Path;

const EPISODES: usize = 400;
const SEED: u64 = 2;
/// The reference cell's evaluation seed: the first of the seeds docs/learning.md's
/// reference-cell figures are measured on.
const REFERENCE_SEED: u64 = 21;

/// The noisy camera's evaluation: the first of the seeds of docs/learning.md's table at four
/// times the noise, on more episodes than the other checks.
const NOISY_SEED: u64 = 10;
const NOISY_EPISODES: usize = 2000;

const DEEP_TIGHT_CELLS: [&str; 3] = [
    "cells/phi100-deep.toml",
    "cells/corners/c120-tight-deep-small-robot.toml",
    "cells/corners/c250-tight-deep.toml",
];

fn evaluated(controller: &str, cell: &CellConfig, seed: u64) -> EvalSummary {
    evaluated_under_noise(controller, cell, 1.0, EPISODES, seed)
}

/// As `celld eval --noise-scale NOISE_SCALE` by default: the episodes shared among the
/// robots the cell keeps.
fn evaluated_under_noise(
    controller: &str,
    cell: &CellConfig,
    noise_scale: f64,
    episodes: usize,
    seed: u64,
) -> EvalSummary {
    let options = EnvOptions {
        kept_robots: DEFAULT_KEPT_ROBOTS,
        noise_scale,
        ..EnvOptions::from_cell(cell)
    };
    let make = builtin_factory(controller, cell).unwrap();
    let (summary, reports) = evaluate(cell, options, episodes, seed, &make, &|_| {});
    assert_eq!(reports.len(), episodes);
    summary
}

#[test]
fn the_cross_cell_policies_are_within_a_hundredth_of_expert_on_deep_tight_cells() {
    for file in DEEP_TIGHT_CELLS {
        let cell = CellConfig::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join(file)).unwrap();
        let expert = evaluated("expert", &cell, SEED);
        for policy in ["hierarchical-cells", "hierarchical-swift-cells"] {
            let learned = evaluated(policy, &cell, SEED);
            println!(
                "{file}: {policy} {} ({:?}), expert {} ({:?})",
                learned.success_rate, learned.failures, expert.success_rate, expert.failures
            );
            assert!(
                learned.success_rate >= expert.success_rate - 0.01,
                "{policy} on {file}: {} against expert's {} ({:?})",
                learned.success_rate,
                expert.success_rate,
                learned.failures
            );
            assert!(
                !learned.failures.contains_key("motion_limit"),
                "{policy} on {file}: {:?}",
                learned.failures
            );
        }
    }
}

#[test]
fn on_the_reference_cell_the_hierarchical_policies_fail_no_more_than_expert() {
    let cell = CellConfig::reference();
    let expert = evaluated("expert", &cell, REFERENCE_SEED);
    for (policy, most_steps) in [
        ("hierarchical-reference", None),
        ("hierarchical-cells", None),
        ("hierarchical-swift-reference", Some(40.0)),
        ("hierarchical-swift-cells", Some(40.0)),
    ] {
        let learned = evaluated(policy, &cell, REFERENCE_SEED);
        println!(
            "{policy}: {} in {:?} steps ({:?}), expert {} in {:?}",
            learned.successes,
            learned.avg_steps,
            learned.failures,
            expert.successes,
            expert.avg_steps
        );
        assert!(
            learned.successes >= expert.successes,
            "{policy}: {} successes against expert's {} ({:?})",
            learned.successes,
            expert.successes,
            learned.failures
        );
        if let Some(most_steps) = most_steps {
            let steps = learned.avg_steps.unwrap();
            assert!(
                steps <= most_steps,
                "{policy}: {steps} steps, more than {most_steps}"
            );
        }
    }
}

/// The goals' floors under a noisy camera, and no step back from `expert` that this seed's 2000
/// episodes can see. The leads docs/learning.md measures are a few thousandths at four times
/// the noise (over 24,000 to 72,000 episodes) and none at twice; on 2000 episodes one seed's
/// paired difference moves by about 0.005 at four times, so a policy is held within 0.01 of
/// `expert` there and to fewer steps (10–20 fewer today), and at twice within 0.001, two
/// episodes, where `expert` fails about one in 20,000.
#[test]
fn under_a_camera_two_and_four_times_as_noisy_the_hierarchical_policies_hold_their_goals() {
    let cell = CellConfig::reference();
    for (noise_scale, floor, most_behind) in [(2.0, 0.99, 0.001), (4.0, 0.62, 0.01)] {
        let expert =
            evaluated_under_noise("expert", &cell, noise_scale, NOISY_EPISODES, NOISY_SEED);
        let expert_steps = expert.avg_steps.unwrap();
        for policy in [
            "hierarchical-reference",
            "hierarchical-cells",
            "hierarchical-swift-reference",
            "hierarchical-swift-cells",
        ] {
            let learned =
                evaluated_under_noise(policy, &cell, noise_scale, NOISY_EPISODES, NOISY_SEED);
            let steps = learned.avg_steps.unwrap();
            println!(
                "noise x{noise_scale}: {policy} {} in {steps:.2} steps ({:?}), expert {} in \
                 {expert_steps:.2} ({:?})",
                learned.successes, learned.failures, expert.successes, expert.failures
            );
            assert!(
                learned.success_rate >= floor,
                "{policy} at noise x{noise_scale}: {} below {floor} ({:?})",
                learned.success_rate,
                learned.failures
            );
            assert!(
                learned.success_rate >= expert.success_rate - most_behind,
                "{policy} at noise x{noise_scale}: {} against expert's {} ({:?})",
                learned.success_rate,
                expert.success_rate,
                learned.failures
            );
            if noise_scale > 2.0 {
                assert!(
                    steps < expert_steps,
                    "{policy} at noise x{noise_scale}: {steps} steps, expert {expert_steps}"
                );
            }
        }
    }
}
