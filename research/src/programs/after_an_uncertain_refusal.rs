//! What a controller's next move down the bore after a refusal as uncertain is worth. After a
//! move down is refused as uncertain (the supervisor finding no share of it sure enough), the
//! controller's next move down, with the tip between 0.2 mm past the entrance and 6 mm short
//! of the seat, is made as MODE says:
//!
//! - `deployed`: as `celld eval` runs the controller (a learned policy asks the full step
//!   there, but not after a refusal for the wall until a move is made:
//!   `policy::shield::FullStepAfterUncertainty`, decision 0040);
//! - `none`: as the controller asks it (a learned policy with that rule switched off);
//! - `full`: the full step (5 mm on the reference cell) after every such refusal, also after
//!   refusals for the wall, so that the cell's cautious execution tries shares of it down to a
//!   quarter;
//! - a number of mm: no longer than that, until a move is made.
//!
//! `cargo run --release -p cell-research -- after_an_uncertain_refusal CONTROLLER MODE [NOISE
//! [EPISODES [SEEDS]]]` (built-in controllers; defaults 2, 4000, 30; SEEDS comma-separated,
//! their episodes summed). 10 kept robots, as `celld eval`. For a controller that is not a
//! learned policy `deployed` and `none` are the same.

use cell_research::arg;

use assembly_cell::collision::supervisor::VetoReason;
use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::eval::evaluate;
use assembly_cell::policy::learned::LearnedPolicy;
use assembly_cell::policy::shield::{FullStepAfterUncertainty, RuleId};
use assembly_cell::policy::{self, Controller, Decision};
use assembly_cell::sim::{EnvOptions, Observation};
use std::collections::BTreeMap;

/// How the move down after a refusal as uncertain is made.
#[derive(Debug, Clone, Copy)]
enum Mode {
    Deployed,
    AsItIs,
    FullStep,
    AtMostMm(f64),
}

impl Mode {
    fn parse(text: &str) -> anyhow::Result<Self> {
        match text {
            "deployed" => Ok(Mode::Deployed),
            "none" => Ok(Mode::AsItIs),
            "full" => Ok(Mode::FullStep),
            mm => match mm.parse::<f64>() {
                Ok(mm) if mm > 0.0 && mm.is_finite() => Ok(Mode::AtMostMm(mm)),
                _ => anyhow::bail!(
                    "unknown mode {text:?}: deployed, none, full or a length in mm above 0"
                ),
            },
        }
    }
}

struct AfterARefusal {
    inner: Box<dyn Controller>,
    mode: Mode,
    depth_mm: f64,
    step_limit_mm: f64,
    /// The last move asked went down.
    went_down: bool,
    /// A move down was refused as uncertain and no move has been made since.
    refused: bool,
}

impl Controller for AfterARefusal {
    fn name(&self) -> &str {
        "after-an-uncertain-refusal"
    }

    fn reset(&mut self, seed: u64) {
        self.inner.reset(seed);
        self.went_down = false;
        self.refused = false;
    }

    fn act(&mut self, observation: &Observation) -> Decision {
        let mut decision = self.inner.act(observation);
        let uncertain = matches!(observation.last_veto, Some(VetoReason::Uncertain { .. }));
        if uncertain && self.went_down {
            self.refused = true;
        } else if observation.measurement_fresh {
            self.refused = false;
        }
        // Where the deployed rule applies (0.2 mm in to 6 mm short of the seat here).
        let inserted_mm = observation.insertion_mm();
        let in_the_bore = FullStepAfterUncertainty::default().applies_at(
            inserted_mm,
            self.depth_mm,
            self.step_limit_mm,
        );
        let z = &mut decision.action.translation_mm.z;
        if self.refused && in_the_bore && *z < 0.0 {
            *z = match self.mode {
                Mode::Deployed | Mode::AsItIs => *z,
                Mode::FullStep => -self.step_limit_mm,
                Mode::AtMostMm(mm) => z.max(-mm),
            };
        }
        self.went_down = decision.action.translation_mm.z < 0.0;
        decision
    }
}

pub fn main() -> anyhow::Result<()> {
    let controller: String = arg(1, "hierarchical-reference".to_string())?;
    let mode_text: String = arg(2, "deployed".to_string())?;
    let noise_scale: f64 = arg(3, 2.0)?;
    let episodes: usize = arg(4, 4000)?;
    let seeds_text: String = arg(5, "30".to_string())?;
    let mode = Mode::parse(&mode_text)?;
    let seeds = cell_research::seeds(&seeds_text)?;
    let cell = CellConfig::reference();
    let make_inner: policy::ControllerFactory = match policy::bundled_policy(&controller) {
        Some(bytes) if !matches!(mode, Mode::Deployed) => {
            let bare = LearnedPolicy::from_bytes(bytes)?
                .with_name(controller.as_str())
                .without(RuleId::FullStepAfterUncertainty);
            Box::new(move || Box::new(bare.clone()))
        }
        _ => policy::builtin_factory(&controller, &cell)?,
    };
    let options = EnvOptions {
        noise_scale,
        kept_robots: 10,
        ..EnvOptions::from_cell(&cell)
    };
    let make = || {
        Box::new(AfterARefusal {
            inner: make_inner(),
            mode,
            depth_mm: cell.bore.depth_mm,
            step_limit_mm: cell.steps.position_mm,
            went_down: false,
            refused: false,
        }) as Box<dyn Controller>
    };
    let (mut successes, mut failures) = (0, BTreeMap::<String, usize>::new());
    for &seed in &seeds {
        let (summary, _) = evaluate(&cell, options, episodes, seed, &make, &|_| {});
        successes += summary.successes;
        for (reason, count) in summary.failures {
            *failures.entry(reason).or_default() += count;
        }
    }
    println!(
        "{controller}, `{mode_text}` after a refusal as uncertain (noise ×{noise_scale}, seeds \
         {seeds_text}): {successes} of {} succeeded; failures {failures:?}",
        episodes * seeds.len()
    );
    Ok(())
}
