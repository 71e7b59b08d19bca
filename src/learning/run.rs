//! One training run, demonstrations in, policy file out, as a single function with progress and
//! cancellation: what `POST /api/training` runs in the background. The stages are those of
//! `celld train all` (behaviour cloning of both actors, the LSTM selector, then TD3 in the
//! hierarchy), with the same defaults, and any DAgger rounds after them as `celld train policy`
//! runs them; a run for any cell ends with `celld train policy`'s polishing pass ([`POLISH`]).

use super::bc::{ACROSS_CELLS_ORIENTATION_LABEL_FLOOR, BcConfig};
use super::dagger;
use super::demos::{DEFAULT_DEMONSTRATOR, DemoEpisode, Recording, check_demonstrator};
use super::pipeline::{self, step_limits};
use super::refine::step_size::StepSizeConfig;
use super::refine::{RefineConfig, Refinement};
use super::selector::SelectorConfig;
use crate::config::cell::CellConfig;
use crate::policy::file::PolicyFile;
use crate::policy::hierarchical::HierarchicalPolicy;
use crate::policy::inputs::PolicyInputs;
use crate::policy::learned::LearnedPolicy;
use crate::policy::{Actor, Controller};
use crate::sim::EnvOptions;
use crate::sim::randomise::CellRanges;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use std::collections::BTreeMap;

/// How much of the pipeline a run does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TrainingPart {
    /// Behaviour cloning and the selector: the `bc` policy, no TD3.
    Bc,
    /// Every stage, TD3 included.
    All,
}

/// Largest actor width and LSTM hidden size a run accepts.
pub const MAX_WIDTH: usize = 1024;
/// Most epochs of any one BC or LSTM stage.
pub const MAX_EPOCHS: usize = 100_000;
/// Most TD3 episodes of a run.
pub const MAX_TD3_EPISODES: usize = 1_000_000;
/// Most validation episodes.
pub const MAX_EVAL_EPISODES: usize = 100_000;
/// Most DAgger rounds of a run.
pub const MAX_DAGGER_ROUNDS: usize = 5;
/// Position actor epochs of a DAgger round by default (`celld train policy`'s).
pub const DAGGER_BC_EPOCHS: usize = 100;

/// Episodes per batch of the LSTM selector's training (not a setting of the HTTP API; `celld
/// train --lstm-batch` defaults to it).
pub const LSTM_BATCH_SIZE: usize = 8;
/// Learning rate (Adam) of the LSTM selector's training (not a setting of the HTTP API; `celld
/// train --lstm-lr` defaults to it).
pub const LSTM_LEARNING_RATE: f64 = 5e-3;

/// The polishing pass that ends a policy for any cell (`celld train policy`'s last round, and a
/// run `for_any_cell`): a few epochs from the last pass's policy at a low rate, with the
/// position actor's errors counted relative to its labels as well as the orientation actor's.
/// The first pass answers the last few hundredths of a millimetre to the seat with no move;
/// the polish teaches it that move (docs/learning-reference.md § Training in detail).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Polish {
    /// [`BcConfig::position_label_floor`].
    pub position_label_floor: f64,
    pub bc_learning_rate: f64,
    /// Epochs of the position actor.
    pub bc_epochs: usize,
    pub bc_anneal_fraction: f64,
    pub bc_anneal_factor: f64,
    pub bc_orientation_epochs: usize,
    pub lstm_learning_rate: f64,
    pub lstm_epochs: usize,
    /// TD3 episodes after the polish (`celld train policy`, and the service's default
    /// `polish_td3_episodes`), with the step-size agent (`learning::refine::step_size`) beside the
    /// actors' agents, on this many kept robots: on the approach the first pass's selector
    /// steps short of the demonstrator's full steps, and TD3 lengthens them (decision 0027).
    pub td3_episodes: usize,
    pub td3_robots: u32,
}

/// The polishing pass of `celld train policy` (the bundled `hierarchical-swift-cells` and
/// `hierarchical-cells`).
pub const POLISH: Polish = Polish {
    position_label_floor: 0.3,
    bc_learning_rate: 0.002,
    bc_epochs: 6,
    bc_anneal_fraction: 0.5,
    bc_anneal_factor: 0.25,
    bc_orientation_epochs: 100,
    lstm_learning_rate: 5e-4,
    lstm_epochs: 1,
    td3_episodes: 500,
    td3_robots: 10,
};

/// A run's settings (the defaults are `celld train all`'s, which takes them from here).
///
/// The bounds in the `schema` attributes are the ones [`TrainingSettings::check`] holds to;
/// the HTTP API's description is made from them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct TrainingSettings {
    pub part: TrainingPart,
    /// Any u64 (JSON numbers above 2^53 are read exactly).
    #[schema(minimum = 0, maximum = 18_446_744_073_709_551_615_u64)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub seed: u64,
    #[schema(minimum = 1, maximum = 1024)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub actor_width: usize,
    /// Epochs of the position actor.
    #[schema(minimum = 1, maximum = 100_000)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub bc_epochs: usize,
    /// Epochs of the orientation actor (see [`BcConfig::orientation_epochs`]).
    #[schema(minimum = 1, maximum = 100_000)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub bc_orientation_epochs: usize,
    #[schema(exclusive_minimum = 0.0)]
    pub bc_learning_rate: f64,
    /// Weight of the sideways errors of samples in the bore in the BC loss (see
    /// [`BcConfig::bore_lateral_weight`]; `hierarchical-reference` was made with 30).
    #[schema(exclusive_minimum = 0.0)]
    pub bc_bore_lateral_weight: f64,
    /// The demonstrator recorded when the run is given no stored demonstrations (one of
    /// [`super::demos::DEMONSTRATORS`]; `hierarchical-reference`'s is `expert-careful`).
    #[schema(pattern = "^(expert-state-only|expert-careful|expert-swift|expert)$")]
    pub demonstrator: String,
    /// Train a policy for cells it was not trained on: it reads cell-scaled inputs (a
    /// version 2 file), and every recorded demonstration and TD3 episode is on a cell of its
    /// own, drawn around this one over the ranges the product is specified for (the recipe of
    /// the bundled `hierarchical-swift-cells` and `hierarchical-cells`). False: the paper's
    /// absolute state, on this cell.
    pub for_any_cell: bool,
    #[schema(minimum = 1, maximum = 1024)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub lstm_hidden: usize,
    #[schema(minimum = 1, maximum = 100_000)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub lstm_epochs: usize,
    #[schema(minimum = 1, maximum = 1_000_000)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub td3_episodes: usize,
    /// TD3 episodes of the polishing pass of a run `for_any_cell`, with the step-size agent on
    /// 10 kept robots (decision 0027); `celld train policy`'s polishing round runs as many.
    #[schema(minimum = 1, maximum = 1_000_000)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub polish_td3_episodes: usize,
    /// DAgger rounds after the first pass: the last policy drives as many episodes as the run
    /// has demonstrations, `demonstrator` labels them, and they teach the actors (the selector
    /// keeps learning from the demonstrations); then the stages run again. The recommended
    /// policy has one (`celld train policy`).
    #[schema(minimum = 0, maximum = 5)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub dagger_rounds: usize,
    /// Epochs of the position actor in a DAgger round (half the first pass's on twice the
    /// episodes, in the recommended policy's recipe).
    #[schema(minimum = 1, maximum = 100_000)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub dagger_bc_epochs: usize,
    /// Validate (and keep the best policy) every this many TD3 episodes; 0: at the end only.
    #[serde(deserialize_with = "crate::integer::integer")]
    pub eval_every: usize,
    #[schema(minimum = 1, maximum = 100_000)]
    #[serde(deserialize_with = "crate::integer::integer")]
    pub eval_episodes: usize,
}

impl Default for TrainingSettings {
    fn default() -> Self {
        TrainingSettings {
            part: TrainingPart::All,
            seed: 2026,
            actor_width: 64,
            bc_epochs: BcConfig::default().epochs,
            bc_orientation_epochs: BcConfig::default().orientation_epochs,
            bc_learning_rate: 0.02,
            bc_bore_lateral_weight: BcConfig::default().bore_lateral_weight,
            demonstrator: DEFAULT_DEMONSTRATOR.to_string(),
            for_any_cell: false,
            lstm_hidden: 64,
            lstm_epochs: 60,
            td3_episodes: 500,
            polish_td3_episodes: POLISH.td3_episodes,
            dagger_rounds: 0,
            dagger_bc_epochs: DAGGER_BC_EPOCHS,
            eval_every: 50,
            eval_episodes: crate::learning::refine::VALIDATION_EPISODES,
        }
    }
}

impl TrainingSettings {
    /// Refuses settings no run can use, naming the field.
    pub fn check(&self) -> Result<(), String> {
        // The upper bounds keep a typing slip from holding the training thread for days or
        // asking for gigabytes of weights; each is far above any run we have needed.
        let counts = [
            ("actor_width", self.actor_width, MAX_WIDTH),
            ("bc_epochs", self.bc_epochs, MAX_EPOCHS),
            ("dagger_bc_epochs", self.dagger_bc_epochs, MAX_EPOCHS),
            (
                "bc_orientation_epochs",
                self.bc_orientation_epochs,
                MAX_EPOCHS,
            ),
            ("lstm_hidden", self.lstm_hidden, MAX_WIDTH),
            ("lstm_epochs", self.lstm_epochs, MAX_EPOCHS),
            ("eval_episodes", self.eval_episodes, MAX_EVAL_EPISODES),
        ];
        for (field, value, max) in counts {
            if !(1..=max).contains(&value) {
                return Err(format!("{field} = {value} is outside 1..={max}"));
            }
        }
        if self.dagger_rounds > MAX_DAGGER_ROUNDS {
            return Err(format!(
                "dagger_rounds = {} is outside 0..={MAX_DAGGER_ROUNDS}",
                self.dagger_rounds
            ));
        }
        for (field, value) in [
            ("td3_episodes", self.td3_episodes),
            ("polish_td3_episodes", self.polish_td3_episodes),
        ] {
            if !(1..=MAX_TD3_EPISODES).contains(&value) {
                return Err(format!(
                    "{field} = {value} is outside 1..={MAX_TD3_EPISODES}"
                ));
            }
        }
        for (field, value) in [
            ("bc_learning_rate", self.bc_learning_rate),
            ("bc_bore_lateral_weight", self.bc_bore_lateral_weight),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(format!("{field} = {value} must be a number > 0"));
            }
        }
        check_demonstrator(&self.demonstrator).map_err(|e| format!("demonstrator {e}"))
    }

    /// What the policy reads.
    pub fn inputs(&self) -> PolicyInputs {
        if self.for_any_cell {
            PolicyInputs::CellScaled
        } else {
            PolicyInputs::Absolute
        }
    }

    /// How the run records its demonstrations when it is named none.
    pub fn recording(&self) -> Recording {
        Recording {
            inputs: self.inputs(),
            randomise: self.for_any_cell.then(CellRanges::default),
            ..Recording::default()
        }
    }

    /// The progress units (epochs and TD3 episodes) of the whole run.
    fn units(&self) -> usize {
        let (td3, polish_td3) = if self.part == TrainingPart::All {
            (self.td3_episodes, self.polish_td3_episodes)
        } else {
            (0, 0)
        };
        let pass = self.bc_orientation_epochs + self.lstm_epochs + td3;
        let polish = if self.for_any_cell {
            POLISH.bc_epochs + POLISH.bc_orientation_epochs + POLISH.lstm_epochs + polish_td3
        } else {
            0
        };
        self.bc_epochs + pass + self.dagger_rounds * (self.dagger_bc_epochs + pass) + polish
    }
}

/// One point of a learning curve: BC and LSTM losses by epoch, TD3 returns by episode.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct CurvePoint {
    /// `bc_position`, `bc_orientation`, `lstm` or `td3`.
    pub stage: &'static str,
    pub x: usize,
    pub value: f64,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RunError {
    #[error("cancelled")]
    Cancelled,
    #[error("{0} episodes with steps; at least {MIN_EPISODES} are needed")]
    TooFewDemonstrations(usize),
    #[error("{0}")]
    Training(String),
}

/// Episodes with steps a run needs: a tenth of them is held out to check the selector.
pub const MIN_EPISODES: usize = 10;

/// Refuses demonstrations too few to learn from (episodes without steps do not count).
pub fn check_demonstrations(demos: &[DemoEpisode]) -> Result<(), RunError> {
    let with_steps = demos.iter().filter(|e| !e.steps.is_empty()).count();
    if with_steps < MIN_EPISODES {
        return Err(RunError::TooFewDemonstrations(with_steps));
    }
    Ok(())
}

/// Runs the pipeline on `demos` (a tenth held out for the selector), then its DAgger rounds,
/// then, for any cell, the polishing pass on `demos`.
/// `report` gets each curve point and the fraction done; `cancelled` is asked between epochs'
/// reports, TD3 episodes and rounds. Returns the policy file and the run's figures.
pub fn run(
    cell: &CellConfig,
    demos: Vec<DemoEpisode>,
    settings: &TrainingSettings,
    report: &mut dyn FnMut(CurvePoint, f64),
    cancelled: &dyn Fn() -> bool,
) -> Result<(PolicyFile, Value), RunError> {
    settings.check().map_err(RunError::Training)?;
    check_demonstrations(&demos)?;
    let mut progress = Progress {
        report,
        cancelled,
        done: 0,
        units: settings.units() as f64,
        points: BTreeMap::new(),
        offsets: BTreeMap::new(),
    };
    let (mut file, mut figures) = pass(
        cell,
        dagger::split(demos.clone(), 0, false),
        settings,
        Pass::First,
        &mut progress,
    )?;
    let mut rounds = Vec::new();
    for round in 1..=settings.dagger_rounds {
        progress.check()?;
        let driver =
            LearnedPolicy::hierarchical(HierarchicalPolicy::from_file(&file).map_err(failed)?)
                .with_rules(&cell.rules.in_training());
        let make = || Box::new(driver.clone()) as Box<dyn Controller>;
        let driven = dagger::rollouts(
            cell,
            EnvOptions::from_cell(cell),
            &settings.demonstrator,
            &make,
            demos.len(),
            settings.seed,
            0,
            settings.recording(),
        );
        rounds.push(json!({
            "round": round,
            "episodes": driven.len(),
            "policy_succeeded": driven.iter().filter(|e| e.succeeded).count(),
        }));
        let count = driven.len();
        let episodes = dagger::renumbered(driven.into_iter().chain(demos.clone()).collect());
        progress.next_round();
        (file, figures) = pass(
            cell,
            dagger::split(episodes, count, true),
            settings,
            Pass::Dagger,
            &mut progress,
        )?;
    }
    if settings.for_any_cell {
        progress.check()?;
        progress.next_round();
        let last = file;
        (file, figures) = pass(
            cell,
            dagger::split(demos, 0, false),
            settings,
            Pass::Polish(&last),
            &mut progress,
        )?;
        figures["polished"] = json!(true);
    }
    if !rounds.is_empty() {
        figures["dagger"] = Value::Array(rounds);
    }
    Ok((file, figures))
}

fn failed(e: impl std::fmt::Display) -> RunError {
    RunError::Training(e.to_string())
}

/// A run's progress across its passes: the fraction done, and curve points numbered on from
/// the last pass's.
struct Progress<'a> {
    report: &'a mut dyn FnMut(CurvePoint, f64),
    cancelled: &'a dyn Fn() -> bool,
    done: usize,
    units: f64,
    /// Points of each stage so far.
    points: BTreeMap<&'static str, usize>,
    /// What this pass adds to each stage's x.
    offsets: BTreeMap<&'static str, usize>,
}

impl Progress<'_> {
    fn point(&mut self, stage: &'static str, x: usize, value: f64) {
        self.done += 1;
        *self.points.entry(stage).or_default() += 1;
        let x = x + self.offsets.get(stage).copied().unwrap_or(0);
        (self.report)(
            CurvePoint { stage, x, value },
            self.done as f64 / self.units,
        );
    }

    fn next_round(&mut self) {
        self.offsets = self.points.clone();
    }

    fn check(&self) -> Result<(), RunError> {
        if (self.cancelled)() {
            Err(RunError::Cancelled)
        } else {
            Ok(())
        }
    }
}

/// Which pass of a run: they differ in the position actor's epochs, and the polish in where
/// it starts and how it learns ([`POLISH`]).
#[derive(Clone, Copy)]
enum Pass<'a> {
    First,
    Dagger,
    Polish(&'a PolicyFile),
}

/// One pass of the pipeline: both actors, the selector, and TD3 when the run's part has it.
fn pass(
    cell: &CellConfig,
    split: dagger::Split,
    settings: &TrainingSettings,
    which: Pass,
    progress: &mut Progress,
) -> Result<(PolicyFile, Value), RunError> {
    let recording = settings.recording();
    let inputs = recording.inputs;
    let limits = step_limits(cell, inputs);
    let mut bc = BcConfig {
        epochs: settings.bc_epochs,
        orientation_epochs: settings.bc_orientation_epochs,
        learning_rate: settings.bc_learning_rate,
        bore_lateral_weight: settings.bc_bore_lateral_weight,
        seed: settings.seed,
        insertion_from_pz_mm: pipeline::insertion_from_input_mm(cell, inputs),
        bore_from_pz_mm: inputs.entrance_input_mm(cell),
        inputs,
        orientation_label_floor: settings
            .for_any_cell
            .then_some(ACROSS_CELLS_ORIENTATION_LABEL_FLOOR),
        ..BcConfig::default()
    };
    let mut selector = SelectorConfig {
        hidden_size: settings.lstm_hidden,
        epochs: settings.lstm_epochs,
        batch_size: LSTM_BATCH_SIZE,
        learning_rate: LSTM_LEARNING_RATE,
        seed: settings.seed,
    };
    let start = match which {
        Pass::First => None,
        Pass::Dagger => {
            bc.epochs = settings.dagger_bc_epochs;
            None
        }
        Pass::Polish(start) => {
            bc = BcConfig {
                epochs: POLISH.bc_epochs,
                orientation_epochs: POLISH.bc_orientation_epochs,
                learning_rate: POLISH.bc_learning_rate,
                anneal_fraction: POLISH.bc_anneal_fraction,
                anneal_factor: POLISH.bc_anneal_factor,
                position_label_floor: Some(POLISH.position_label_floor),
                ..bc
            };
            selector.epochs = POLISH.lstm_epochs;
            selector.learning_rate = POLISH.lstm_learning_rate;
            Some(start)
        }
    };
    let varmap = pipeline::behaviour_clone(
        &split.train,
        &limits,
        settings.actor_width,
        &bc,
        start,
        &mut |actor, epoch, loss| {
            let stage = match actor {
                Actor::Position => "bc_position",
                Actor::Orientation => "bc_orientation",
            };
            progress.point(stage, epoch, loss);
        },
    )
    .map_err(failed)?;
    progress.check()?;

    let agreement = pipeline::train_lstm(
        &varmap,
        &split.selector,
        &split.held_out,
        &limits,
        &selector,
        start,
        &mut |epoch, loss| progress.point("lstm", epoch, loss),
    )
    .map_err(failed)?
    .held_out_agreement;
    progress.check()?;
    let mut figures = json!({"demonstrated_episodes": split.train.len() + split.held_out.len(),
                             "held_out_agreement": agreement});
    let provenance = |kind: &str| {
        BTreeMap::from([
            (
                "trained_by".to_string(),
                "celld serve /api/training".to_string(),
            ),
            ("policy_kind".to_string(), kind.to_string()),
            ("seed".to_string(), settings.seed.to_string()),
            ("cell".to_string(), cell.name.clone()),
        ])
    };
    if settings.part == TrainingPart::Bc {
        let file =
            pipeline::policy_file(&varmap, &limits, inputs, &provenance("bc")).map_err(failed)?;
        return Ok((file, figures));
    }

    let polish = matches!(which, Pass::Polish(_));
    let config = RefineConfig {
        episodes: if polish {
            settings.polish_td3_episodes
        } else {
            settings.td3_episodes
        },
        eval_every: settings.eval_every,
        eval_episodes: settings.eval_episodes,
        inputs,
        randomise: recording.randomise,
        step_size: polish.then(StepSizeConfig::default),
        ..RefineConfig::default()
    };
    let options = EnvOptions {
        kept_robots: if polish { POLISH.td3_robots } else { 0 },
        ..EnvOptions::from_cell(cell)
    };
    let mut refinement =
        Refinement::new(cell, options, varmap, config, true, settings.seed).map_err(failed)?;
    refinement.validate().map_err(failed)?;
    while refinement.episode() < config.episodes {
        progress.check()?;
        let record = refinement.train_episode().map_err(failed)?;
        progress.point("td3", record.episode, record.return_);
        let episode = refinement.episode();
        if config.eval_every > 0 && episode % config.eval_every == 0 {
            refinement.validate().map_err(failed)?;
        }
    }
    if refinement.validations().last().map(|v| v.episode) != Some(config.episodes) {
        refinement.validate().map_err(failed)?;
    }
    figures["validations"] = json!(refinement.validations());
    let (best, vars) = refinement.best();
    figures["best_validation"] = json!(best);
    let file = pipeline::policy_file(vars, &limits, inputs, &provenance("hierarchical"))
        .map_err(failed)?;
    Ok((file, figures))
}
