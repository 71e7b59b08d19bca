//! The goals `celld check` holds the bundled policies to, as data: each holds some policies,
//! on some conditions (a cell, a camera noise, episodes and a seed), to some bounds, most of
//! them against `expert` on the same episodes.

use anyhow::{Result, bail};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::eval::EvalSummary;

/// The cross-cell policies: trained on randomised cells.
pub(super) const CROSS_CELL: &[&str] = &["hierarchical-cells", "hierarchical-swift-cells"];
/// Every hierarchical policy.
pub(super) const HIERARCHICAL: &[&str] = &[
    "hierarchical-reference",
    "hierarchical-cells",
    "hierarchical-swift-reference",
    "hierarchical-swift-cells",
];
/// The fast ones, trained on `expert-swift`.
pub(super) const SWIFT: &[&str] = &["hierarchical-swift-reference", "hierarchical-swift-cells"];

/// The baseline most goals are measured against, on the same episodes.
pub(super) const BASELINE: &str = "expert";

/// The cells a goal runs on, built into the binary so the check needs no checkout.
#[derive(Clone, Copy)]
pub(super) enum Cell {
    /// cells/phi170.toml.
    Reference,
    /// A cell file's text and its path in the repository.
    File(&'static str, &'static str),
}

impl Cell {
    pub(super) fn load(self) -> Result<CellConfig> {
        match self {
            Cell::Reference => Ok(CellConfig::reference()),
            Cell::File(origin, text) => Ok(CellConfig::parse(text, origin)?),
        }
    }
}

/// Episodes and the seed they are drawn from.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub(super) struct Episodes {
    pub(super) episodes: usize,
    pub(super) seed: u64,
}

/// Where a goal's episodes run: as `celld eval --cell FILE --noise-scale NOISE --episodes N
/// --seed S` (10 kept robots, every rule).
#[derive(Clone, Copy)]
pub(super) struct Condition {
    /// Named in the goal lines.
    pub(super) name: &'static str,
    pub(super) cell: Cell,
    /// The camera's point noise × its data sheet's.
    pub(super) noise_scale: f64,
    /// The full check's episodes: the figures of
    /// docs/experiments/2026-12-07-81d9a69-where-the-policies-stand.md are measured on these seeds.
    pub(super) full: Episodes,
    /// `--smoke`'s: a seed where every goal on this condition holds with the bundled files.
    pub(super) smoke: Episodes,
}

/// A bound on a policy's evaluation.
#[derive(Clone, Copy, Debug)]
pub(super) enum Bound {
    /// Success rate at least `expert`'s less this.
    BehindExpertAtMost(f64),
    /// No fewer successes than `expert`.
    NoMoreFailuresThanExpert,
    /// Success rate at least this.
    SuccessAtLeast(f64),
    /// Average steps of the successes at most this.
    StepsAtMost(f64),
    /// Fewer average steps of the successes than `expert`.
    FewerStepsThanExpert,
    /// No episode driven out of the workspace (failure `motion_limit`).
    StaysInWorkspace,
}

impl Bound {
    pub(super) fn needs_expert(self) -> bool {
        matches!(
            self,
            Bound::BehindExpertAtMost(_)
                | Bound::NoMoreFailuresThanExpert
                | Bound::FewerStepsThanExpert
        )
    }

    /// This bound on `learned`, with `expert` on the same episodes.
    pub(super) fn judge(self, learned: &EvalSummary, expert: Option<&EvalSummary>) -> Measured {
        let expert = || expert.expect("the baseline is evaluated for a bound that needs it");
        // A policy with no success has no average steps: NaN fails every comparison.
        let steps = |s: &EvalSummary| s.avg_steps.unwrap_or(f64::NAN);
        let shown = |steps: f64| match steps.is_nan() {
            true => "- (no success)".to_string(),
            false => format!("{steps:.2}"),
        };
        let (figure, measured, relation, bound, text) = match self {
            Bound::BehindExpertAtMost(most) => {
                let expert = expert().success_rate;
                let bound = expert - most;
                let text = format!(
                    "success {:.4} ≥ {bound:.4} (expert {expert:.4} − {most})",
                    learned.success_rate
                );
                ("success_rate", learned.success_rate, ">=", bound, text)
            }
            Bound::NoMoreFailuresThanExpert => {
                let expert = expert().successes as f64;
                let text = format!(
                    "successes {} ≥ expert's {expert} of {}",
                    learned.successes, learned.episodes
                );
                ("successes", learned.successes as f64, ">=", expert, text)
            }
            Bound::SuccessAtLeast(floor) => {
                let text = format!("success {:.4} ≥ {floor}", learned.success_rate);
                ("success_rate", learned.success_rate, ">=", floor, text)
            }
            Bound::StepsAtMost(most) => {
                let text = format!("steps {} ≤ {most}", shown(steps(learned)));
                ("avg_steps", steps(learned), "<=", most, text)
            }
            Bound::FewerStepsThanExpert => {
                let expert = steps(expert());
                let text = format!(
                    "steps {} < expert's {}",
                    shown(steps(learned)),
                    shown(expert)
                );
                ("avg_steps", steps(learned), "<", expert, text)
            }
            Bound::StaysInWorkspace => {
                let out = learned.failures.get("motion_limit").copied().unwrap_or(0);
                let text = format!("out of workspace {out} = 0");
                ("motion_limit", out as f64, "<=", 0.0, text)
            }
        };
        let held = match relation {
            ">=" => measured >= bound,
            "<=" => measured <= bound,
            _ => measured < bound,
        };
        Measured {
            figure,
            measured,
            relation,
            bound,
            text,
            held,
        }
    }
}

/// One bound measured.
pub(super) struct Measured {
    pub(super) figure: &'static str,
    pub(super) measured: f64,
    pub(super) relation: &'static str,
    pub(super) bound: f64,
    /// The figure against its bound, for the goal's line.
    pub(super) text: String,
    pub(super) held: bool,
}

/// A goal: every one of `policies` on every one of `conditions` holds every one of `bounds`.
pub(super) struct Goal {
    pub(super) name: &'static str,
    pub(super) conditions: &'static [Condition],
    pub(super) policies: &'static [&'static str],
    pub(super) bounds: &'static [Bound],
}

const fn deep_tight(name: &'static str, origin: &'static str, text: &'static str) -> Condition {
    Condition {
        name,
        cell: Cell::File(origin, text),
        noise_scale: 1.0,
        full: Episodes {
            episodes: 400,
            seed: 2,
        },
        smoke: Episodes {
            episodes: 20,
            seed: 2,
        },
    }
}

/// The deep, tight cells none of the policies was trained on.
const DEEP_TIGHT: &[Condition] = &[
    deep_tight(
        "phi100-deep",
        "cells/phi100-deep.toml",
        include_str!("../../../cells/phi100-deep.toml"),
    ),
    deep_tight(
        "c120-tight-deep-small-robot",
        "cells/corners/c120-tight-deep-small-robot.toml",
        include_str!("../../../cells/corners/c120-tight-deep-small-robot.toml"),
    ),
    deep_tight(
        "c250-tight-deep",
        "cells/corners/c250-tight-deep.toml",
        include_str!("../../../cells/corners/c250-tight-deep.toml"),
    ),
];

/// The reference cell, on the first of the seeds of the reference-cell figures of
/// docs/experiments/2026-12-07-81d9a69-where-the-policies-stand.md.
const REFERENCE: &[Condition] = &[Condition {
    name: "phi170",
    cell: Cell::Reference,
    noise_scale: 1.0,
    full: Episodes {
        episodes: 400,
        seed: 21,
    },
    smoke: Episodes {
        episodes: 20,
        seed: 21,
    },
}];

/// The reference cell under a camera `noise_scale` times as noisy, on the first of the seeds
/// of the table at four times the noise in
/// docs/experiments/2026-12-07-81d9a69-where-the-policies-stand.md, on more episodes.
const fn noisy(name: &'static str, noise_scale: f64, smoke: Episodes) -> Condition {
    Condition {
        name,
        cell: Cell::Reference,
        noise_scale,
        full: Episodes {
            episodes: 2000,
            seed: 10,
        },
        smoke,
    }
}

/// Every goal `celld check` checks.
///
/// Under the noisy camera, the leads
/// docs/experiments/2026-12-07-81d9a69-where-the-policies-stand.md measures are a few thousandths
/// at four times the noise (over 24,000 to 72,000 episodes) and none at twice; on 2000 episodes one
/// seed's paired difference moves by about 0.005 at four times, so a policy is held within
/// 0.01 of `expert` there and to fewer steps (10–20 fewer today), and at twice within 0.001,
/// two episodes, where `expert` fails about one in 20,000.
pub(super) const GOALS: &[Goal] = &[
    Goal {
        name: "deep-tight",
        conditions: DEEP_TIGHT,
        policies: CROSS_CELL,
        bounds: &[Bound::BehindExpertAtMost(0.01), Bound::StaysInWorkspace],
    },
    Goal {
        name: "reference",
        conditions: REFERENCE,
        policies: HIERARCHICAL,
        bounds: &[Bound::NoMoreFailuresThanExpert],
    },
    Goal {
        name: "reference-fast",
        conditions: REFERENCE,
        policies: SWIFT,
        bounds: &[Bound::StepsAtMost(40.0)],
    },
    Goal {
        name: "noise-x2",
        conditions: &[noisy(
            "phi170 noise x2",
            2.0,
            Episodes {
                episodes: 40,
                seed: 10,
            },
        )],
        policies: HIERARCHICAL,
        bounds: &[
            Bound::SuccessAtLeast(0.99),
            Bound::BehindExpertAtMost(0.001),
        ],
    },
    Goal {
        name: "noise-x4",
        // Fewer than 60 episodes leave each of the 10 robots too few to learn its drift
        // from: on 40 every policy succeeds 0.475.
        conditions: &[noisy(
            "phi170 noise x4",
            4.0,
            Episodes {
                episodes: 60,
                seed: 11,
            },
        )],
        policies: HIERARCHICAL,
        bounds: &[
            Bound::SuccessAtLeast(0.62),
            Bound::BehindExpertAtMost(0.01),
            Bound::FewerStepsThanExpert,
        ],
    },
];

/// What `--only` leaves of the goals: each goal with the policies it checks.
pub(super) fn selected(only: &[String]) -> Result<Vec<(&'static Goal, Vec<&'static str>)>> {
    let is_goal = |name: &str| GOALS.iter().any(|g| g.name == name);
    let is_policy = |name: &str| GOALS.iter().any(|g| g.policies.contains(&name));
    if let Some(unknown) = only.iter().find(|n| !is_goal(n) && !is_policy(n)) {
        let goals: Vec<_> = GOALS.iter().map(|g| g.name).collect();
        bail!(
            "--only {unknown}: not a goal ({}) nor a policy the goals check ({})",
            goals.join(", "),
            HIERARCHICAL.join(", ")
        );
    }
    let goals: Vec<&str> = only
        .iter()
        .map(String::as_str)
        .filter(|n| is_goal(n))
        .collect();
    let policies: Vec<&str> = only
        .iter()
        .map(String::as_str)
        .filter(|n| is_policy(n))
        .collect();
    let chosen: Vec<_> = GOALS
        .iter()
        .filter(|g| goals.is_empty() || goals.contains(&g.name))
        .map(|g| {
            let kept = g.policies.iter().copied();
            let kept = kept.filter(|p| policies.is_empty() || policies.contains(p));
            (g, kept.collect::<Vec<_>>())
        })
        .filter(|(_, policies)| !policies.is_empty())
        .collect();
    if chosen.is_empty() {
        bail!("--only {}: no goal checks those policies", only.join(","));
    }
    Ok(chosen)
}

#[cfg(test)]
mod tests {
    use super::*;
    use assembly_cell::policy::eval::DEFAULT_KEPT_ROBOTS;
    use std::collections::BTreeMap;

    fn summary(successes: usize, episodes: usize, avg_steps: Option<f64>) -> EvalSummary {
        EvalSummary {
            controller: "c".into(),
            cell: "phi170".into(),
            episodes,
            seed: 1,
            init_pos_mm: 50.0,
            init_ori_deg: 1.0,
            noise_scale: 1.0,
            calibration_scale: 1.0,
            fault: None,
            kept_robots: DEFAULT_KEPT_ROBOTS,
            successes,
            success_rate: successes as f64 / episodes as f64,
            avg_steps,
            avg_steps_all: 0.0,
            avg_reward: 0.0,
            avg_vetoes: 0.0,
            failures: BTreeMap::new(),
            rules: None,
            drawn_cells: None,
            wall_s: 0.0,
        }
    }

    #[test]
    fn each_bound_holds_on_its_side_and_misses_on_the_other() {
        // Hand-computed: expert 397 of 400 (0.9925); within 0.01 is 0.9825 or more.
        let expert = summary(397, 400, Some(30.0));
        let cases = [
            (
                Bound::BehindExpertAtMost(0.01),
                summary(394, 400, Some(1.0)),
                true,
            ),
            (
                Bound::BehindExpertAtMost(0.01),
                summary(392, 400, Some(1.0)),
                false,
            ),
            (
                Bound::NoMoreFailuresThanExpert,
                summary(397, 400, None),
                true,
            ),
            (
                Bound::NoMoreFailuresThanExpert,
                summary(396, 400, None),
                false,
            ),
            (Bound::SuccessAtLeast(0.62), summary(31, 50, None), true),
            (Bound::SuccessAtLeast(0.62), summary(30, 50, None), false),
            (Bound::StepsAtMost(40.0), summary(1, 1, Some(40.0)), true),
            (Bound::StepsAtMost(40.0), summary(1, 1, Some(40.5)), false),
            (Bound::StepsAtMost(40.0), summary(0, 1, None), false),
            (Bound::FewerStepsThanExpert, summary(1, 1, Some(29.9)), true),
            (
                Bound::FewerStepsThanExpert,
                summary(1, 1, Some(30.0)),
                false,
            ),
            (Bound::StaysInWorkspace, summary(1, 2, None), true),
        ];
        for (bound, learned, held) in cases {
            let measured = bound.judge(&learned, Some(&expert));
            assert_eq!(measured.held, held, "{bound:?}: {}", measured.text);
        }
        let mut out = summary(1, 2, None);
        out.failures.insert("motion_limit".into(), 1);
        let measured = Bound::StaysInWorkspace.judge(&out, None);
        assert!(!measured.held);
        assert_eq!(measured.text, "out of workspace 1 = 0");
        let none = Bound::StepsAtMost(40.0).judge(&summary(0, 3, None), None);
        assert_eq!(none.text, "steps - (no success) ≤ 40");
    }

    #[test]
    fn only_picks_goals_and_policies_and_refuses_other_names() {
        let names = |only: &[&str]| -> Vec<(&str, Vec<&str>)> {
            let only: Vec<String> = only.iter().map(|s| s.to_string()).collect();
            let chosen = selected(&only).unwrap();
            chosen.into_iter().map(|(g, p)| (g.name, p)).collect()
        };
        assert_eq!(names(&[]).len(), GOALS.len());
        assert_eq!(
            names(&["reference-fast"]),
            [("reference-fast", SWIFT.to_vec())]
        );
        assert_eq!(
            names(&["hierarchical-cells"]),
            ["deep-tight", "reference", "noise-x2", "noise-x4"]
                .map(|g| (g, vec!["hierarchical-cells"]))
        );
        assert_eq!(
            names(&["noise-x4", "hierarchical-swift-cells"]),
            [("noise-x4", vec!["hierarchical-swift-cells"])]
        );
        let err = |only: &[&str]| {
            let only: Vec<String> = only.iter().map(|s| s.to_string()).collect();
            selected(&only).err().unwrap().to_string()
        };
        assert!(err(&["expert"]).contains("--only expert: not a goal"));
        assert!(err(&["reference-fast", "hierarchical-cells"]).contains("no goal checks those"));
    }

    /// Evaluations are kept by condition name: a name stands for one cell and camera, and
    /// the smoke check runs fewer episodes than the full one.
    #[test]
    fn a_condition_name_is_one_cell_and_noise_and_the_smoke_runs_fewer_episodes() {
        let conditions: Vec<&Condition> = GOALS.iter().flat_map(|g| g.conditions).collect();
        for a in &conditions {
            assert!(a.smoke.episodes < a.full.episodes, "{}", a.name);
            a.cell.load().unwrap();
            for b in conditions.iter().filter(|b| b.name == a.name) {
                let origin = |c: &Condition| match c.cell {
                    Cell::Reference => "reference",
                    Cell::File(origin, _) => origin,
                };
                assert_eq!(origin(a), origin(b), "{}", a.name);
                assert_eq!(a.noise_scale, b.noise_scale, "{}", a.name);
                assert!(a.full == b.full && a.smoke == b.smoke, "{}", a.name);
            }
        }
    }
}
