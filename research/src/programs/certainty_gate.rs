//! What `expert`'s certainty gate is worth on top of another controller. `expert` goes into the
//! bore only once the state filter's sideways σ is at most 0.009 mm, and makes each move down
//! the bore no longer than keeps that σ at most 0.013 mm; a learned policy does not see the σ.
//! With MODE:
//!
//! - `none`: the controller as `celld eval` runs it;
//! - `entrance`: a move that would take the tip into the bore while the σ is above 0.009 mm
//!   keeps its depth while the tip is 0.5 mm or more above the entrance, and goes down at most
//!   0.5 mm less the tip's height within 0.5 mm of it (so a tip 0.3 mm above may still cross);
//!   its sideways part and turn are made;
//! - `hold`: as `entrance`, but the move keeps its depth however near the entrance the tip is;
//! - `steps`: in the bore, a move down is shortened by 0.7 at a time, down to 0.5 mm, while the
//!   σ after it would be above 0.013 mm, as `expert` does;
//! - `both`: `entrance` and `steps`; `both-hold`: `hold` and `steps`;
//! - `without-standoff`: a bundled learned policy without the rule that keeps the tip at the
//!   standoff while the σ is above the cell's clearance
//!   (`policy::learned::no_nearer_than_the_standoff_mm`, decision 0043); for another
//!   controller the same as `none`.
//!
//! `cargo run --release -p cell-research -- certainty_gate
//! CONTROLLER MODE [NOISE [EPISODES [SEEDS
//! [FAULT]]]]` (built-in controllers; defaults 4, 4000, 10, none; SEEDS comma-separated; FAULT a
//! fault's code, as `celld eval --fault`). One JSON line per seed:
//! successes, average steps of the successes and the failures by reason. 10 kept robots, as
//! `celld eval`, on the reference cell.

use cell_research::arg;

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::eval::evaluate;
use assembly_cell::policy::expert::{ExpertTuning, tip_in_bore};
use assembly_cell::policy::learned::LearnedPolicy;
use assembly_cell::policy::shield::RuleId;
use assembly_cell::policy::{self, Controller, Decision};
use assembly_cell::sim::{EnvOptions, Fault, Observation};
use serde_json::json;

/// How a move into the bore is held while the estimate is unsure sideways.
#[derive(Clone, Copy)]
enum Entrance {
    /// Down at most 0.5 mm less the tip's height above the entrance.
    NearlyHold,
    /// No move down at all.
    Hold,
}

/// The controller's moves, gated by the state filter's sideways σ as `expert` gates its own.
struct Gated {
    inner: Box<dyn Controller>,
    at_the_entrance: Option<Entrance>,
    in_the_bore: bool,
    tuning: ExpertTuning,
}

impl Controller for Gated {
    fn name(&self) -> &str {
        "certainty-gated"
    }

    fn reset(&mut self, seed: u64) {
        self.inner.reset(seed);
    }

    fn act(&mut self, observation: &Observation) -> Decision {
        let mut decision = self.inner.act(observation);
        let dz = decision.action.translation_mm.z;
        if dz.is_nan() || dz >= 0.0 {
            return decision;
        }
        let estimate = &observation.estimate;
        let insertion_mm = observation.insertion_mm();
        let entering = !tip_in_bore(insertion_mm) && tip_in_bore(insertion_mm - dz);
        let unsure = estimate.lateral_sd_mm() > self.tuning.lateral_certainty_mm;
        if let (true, true, Some(entrance)) = (entering, unsure, self.at_the_entrance) {
            decision.action.translation_mm.z = match entrance {
                Entrance::NearlyHold => (-0.5 - insertion_mm).clamp(dz, 0.0),
                Entrance::Hold => 0.0,
            };
        } else if tip_in_bore(insertion_mm) && self.in_the_bore {
            let mut shortened = dz;
            while shortened.abs() > 0.5
                && estimate.lateral_sd_after_mm(shortened) > self.tuning.insertion_certainty_mm
            {
                shortened *= 0.7;
            }
            decision.action.translation_mm.z = shortened;
        }
        decision
    }
}

pub fn main() -> anyhow::Result<()> {
    let controller: String = arg(1, "hierarchical-cells".to_string())?;
    let mode: String = arg(2, "none".to_string())?;
    let noise_scale: f64 = arg(3, 4.0)?;
    let episodes: usize = arg(4, 4000)?;
    let seeds: String = arg(5, "10".to_string())?;
    let fault: Option<Fault> = cell_research::args()
        .nth(6)
        .map(|c| c.parse())
        .transpose()?;
    let (at_the_entrance, in_the_bore) = match mode.as_str() {
        "none" => (None, false),
        "entrance" => (Some(Entrance::NearlyHold), false),
        "hold" => (Some(Entrance::Hold), false),
        "steps" => (None, true),
        "both" => (Some(Entrance::NearlyHold), true),
        "both-hold" => (Some(Entrance::Hold), true),
        "without-standoff" => (None, false),
        other => {
            anyhow::bail!(
                "unknown mode {other:?}: none, entrance, hold, steps, both, both-hold or \
                 without-standoff"
            )
        }
    };
    let cell = CellConfig::reference();
    let inner: policy::ControllerFactory = match policy::bundled_policy(&controller) {
        Some(bytes) if mode == "without-standoff" => {
            let bare = LearnedPolicy::from_bytes(bytes)?
                .with_name(controller.as_str())
                .without(RuleId::StandoffWhileUnsure);
            Box::new(move || Box::new(bare.clone()))
        }
        _ => policy::builtin_factory(&controller, &cell)?,
    };
    let options = EnvOptions {
        noise_scale,
        kept_robots: 10,
        fault,
        ..EnvOptions::from_cell(&cell)
    };
    let make = || {
        Box::new(Gated {
            inner: inner(),
            at_the_entrance,
            in_the_bore,
            tuning: ExpertTuning::default(),
        }) as Box<dyn Controller>
    };
    for seed in cell_research::seeds(&seeds)? {
        let (summary, _) = evaluate(&cell, options, episodes, seed, &make, &|_| {});
        let line = json!({
            "controller": controller,
            "mode": mode,
            "noise_scale": noise_scale,
            "fault": fault.map(|f| f.code()),
            "seed": seed,
            "episodes": episodes,
            "successes": summary.successes,
            "avg_steps": summary.avg_steps,
            "failures": summary.failures,
        });
        println!("{line}");
    }
    Ok(())
}
