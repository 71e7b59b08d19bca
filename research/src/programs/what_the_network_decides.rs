//! How much of a learned hierarchical policy's moves its networks decide, and how much the
//! rules of the shield set (docs/policy-rules.md), per zone: every decision carries the
//! network's proposal beside the move made (`policy::shield::ShieldTrace`). `celld eval`
//! prints how often each rule changed a decision at all; this counts, per zone, the changes of
//! more than a tenth of the network's move.
//!
//! `cargo run --release -p cell-research -- what_the_network_decides
//! CONTROLLER [NOISE] [EPISODES]
//! [SEED]` (a bundled hierarchical policy, by default `hierarchical-swift-cells`, or a
//! hierarchical policy file; defaults 1, 1000, 1; the reference cell, 10 kept robots, as
//! `celld eval`). Per zone (the tip more than 5 mm above the entrance, within 5 mm of it, in
//! the bore), over every step with a fresh frame of every episode: the position and
//! orientation moves made, and the share of them that the rules changed by more than a tenth
//! of the network's own move (sideways, along the axis, a turn), beside the mean size of the
//! network's move and of the one made.

use cell_research::{arg, zone};

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::eval::{
    DEFAULT_KEPT_ROBOTS, episode_seed, robot_blocks, run_episode_watched,
};
use assembly_cell::policy::learned::{LearnedPolicy, LearnedPolicyFile};
use assembly_cell::policy::{Actor, Controller, Decision, bundled_policy};
use assembly_cell::sim::{AssemblyEnv, EnvOptions, Observation};
use nalgebra::{SVector, Vector1};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::Path;

/// A change by the rules counts when it is more than this share of the network's move.
const CHANGED_SHARE: f64 = 0.1;

/// Sums over the steps, by zone and then by what is counted.
type Tallies = BTreeMap<&'static str, BTreeMap<&'static str, f64>>;

/// Whether `made` differs from `net` by more than [`CHANGED_SHARE`] of `net` (any change
/// where the network asked for nothing).
fn changed<const D: usize>(net: SVector<f64, D>, made: SVector<f64, D>) -> bool {
    (made - net).norm() > CHANGED_SHARE * net.norm().max(1e-9)
}

/// The deployed policy and what its rules did.
struct Watched {
    deployed: LearnedPolicy,
    tallies: Tallies,
}

impl Watched {
    fn tally(&mut self, observation: &Observation, made: &Decision) {
        let Some(trace) = made.shield else { return };
        let t = self.tallies.entry(zone(observation)).or_default();
        let mut count = |key, value: f64| *t.entry(key).or_default() += value;
        count("steps", 1.0);
        let handed = trace.proposed_actor != made.actor;
        count("actor changed", f64::from(handed));
        if handed {
            // The proposal is the other actor's move: nothing to compare.
            return;
        }
        let net_move = trace.proposed;
        match made.actor {
            Some(Actor::Position) => {
                let (n, m) = (net_move.translation_mm, made.action.translation_mm);
                count("position", 1.0);
                count("sideways changed", f64::from(changed(n.xy(), m.xy())));
                count(
                    "along changed",
                    f64::from(changed(Vector1::new(n.z), Vector1::new(m.z))),
                );
                count("net sideways", n.xy().norm());
                count("made sideways", m.xy().norm());
                count("net along", n.z.abs());
                count("made along", m.z.abs());
            }
            Some(Actor::Orientation) => {
                let (n, m) = (net_move.rotation_deg, made.action.rotation_deg);
                count("orientation", 1.0);
                count("turn changed", f64::from(changed(n, m)));
                count("net turn", n.norm());
                count("made turn", m.norm());
            }
            None => {}
        }
    }
}

impl Controller for Watched {
    fn name(&self) -> &str {
        "watched"
    }

    fn reset(&mut self, seed: u64) {
        self.deployed.reset(seed);
    }

    fn act(&mut self, observation: &Observation) -> Decision {
        let made = self.deployed.act(observation);
        if observation.measurement_fresh {
            self.tally(observation, &made);
        }
        made
    }
}

pub fn main() -> anyhow::Result<()> {
    let controller: String = arg(1, "hierarchical-swift-cells".to_string())?;
    let noise_scale: f64 = arg(2, 1.0)?;
    let episodes: usize = arg(3, 1000)?;
    let seed: u64 = arg(4, 1)?;
    let file = match bundled_policy(&controller) {
        Some(bytes) => LearnedPolicyFile::from_bytes(bytes)?,
        None => LearnedPolicyFile::from_path(Path::new(&controller))?,
    };
    anyhow::ensure!(
        matches!(file, LearnedPolicyFile::Hierarchical(_)),
        "{controller} is not a hierarchical policy"
    );
    let deployed = LearnedPolicy::from_file(&file)?;
    let cell = CellConfig::reference();
    let options = EnvOptions {
        noise_scale,
        kept_robots: DEFAULT_KEPT_ROBOTS,
        ..EnvOptions::from_cell(&cell)
    };
    let (tallies, successes): (Tallies, usize) = robot_blocks(options, episodes, seed)
        .into_par_iter()
        .map(|(kept, block)| {
            let mut env = AssemblyEnv::new(&cell, kept);
            let mut watched = Watched {
                deployed: deployed.clone(),
                tallies: BTreeMap::new(),
            };
            let mut successes = 0;
            for index in block {
                let report = run_episode_watched(
                    &mut env,
                    &mut watched,
                    index,
                    episode_seed(seed, index),
                    &mut |_, _, _| {},
                );
                successes += usize::from(report.succeeded());
            }
            (watched.tallies, successes)
        })
        .reduce(
            || (BTreeMap::new(), 0),
            |(mut all, a), (some, b)| {
                for (zone, counts) in some {
                    let into: &mut BTreeMap<_, f64> = all.entry(zone).or_default();
                    for (key, value) in counts {
                        *into.entry(key).or_default() += value;
                    }
                }
                (all, a + b)
            },
        );
    println!(
        "{controller}: {successes} of {episodes} succeeded (noise ×{noise_scale}, seed {seed}); \
         per zone, changed = the rules moved it by more than {CHANGED_SHARE} of the network's"
    );
    for zone in ["far", "entrance", "bore"] {
        let Some(t) = tallies.get(zone) else { continue };
        let get = |key| t.get(key).copied().unwrap_or(0.0);
        let per = |key, of| {
            if get(of) > 0.0 {
                get(key) / get(of)
            } else {
                0.0
            }
        };
        println!(
            "  {zone:8} steps {:7.0}  other actor {:.3}  position {:6.0}: sideways changed {:.3} \
             (net {:.3} mm, made {:.3}), along changed {:.3} (net {:.3} mm, made {:.3})  \
             orientation {:6.0}: changed {:.3} (net {:.4}°, made {:.4}°)",
            get("steps"),
            per("actor changed", "steps"),
            get("position"),
            per("sideways changed", "position"),
            per("net sideways", "position"),
            per("made sideways", "position"),
            per("along changed", "position"),
            per("net along", "position"),
            per("made along", "position"),
            get("orientation"),
            per("turn changed", "orientation"),
            per("net turn", "orientation"),
            per("made turn", "orientation"),
        );
    }
    Ok(())
}
