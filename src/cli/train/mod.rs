//! `celld train bc|lstm|td3|all`: the training pipeline over a run directory; `celld train flat`:
//! the flat TD3 baseline (one 6-DoF actor, no BC, no hierarchy) in the same kind of directory;
//! `celld train policy`: `all` and its DAgger rounds, one run directory each (`policy.rs`).
//!
//! A run directory holds each stage's output, so a stage is a checkpoint and a run resumes:
//!
//! | file | written by |
//! |---|---|
//! | `demos.jsonl` | demonstrations (recorded in the twin, after any `--dagger-policy` episodes; or copied from `--demos-file`) |
//! | `bc.safetensors`, `bc_curve.csv` | `train bc`: both actors and the normaliser |
//! | `lstm.safetensors`, `lstm_curve.csv`, `bc-policy.safetensors` | `train lstm`: + the selector |
//! | `td3_checkpoint.safetensors`, `td3_progress.json` | `train td3`, every `--checkpoint-every` episodes |
//! | `td3_curve.csv`, `td3_curve.json`, `policy.safetensors` | `train td3`: curve, best policy |
//! | `td3-flat_checkpoint.safetensors`, `td3-flat_progress.json` | `train flat`, every `--checkpoint-every` episodes |
//! | `td3-flat_curve.csv`, `td3-flat_curve.json`, `td3-flat-policy.safetensors` | `train flat`: curve, best policy |
//! | `run.json` | every stage: settings, figures, wall times |
//!
//! Every file is written with `files::write_atomically`; a checkpoint holds its progress in its
//! metadata (the progress file is a copy to read), so a run stopped at any moment resumes.
//!
//! The stages are in `imitation.rs` (demonstrations, DAgger, BC, the selector) and `refine.rs`
//! (TD3 and the flat baseline); this module checks the settings and keeps the run directory.

use crate::cli::progress::Progress;
use anyhow::{Context, Result, bail};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::files::write_atomically;
use assembly_cell::learning::bc::BcConfig;
use assembly_cell::learning::dataset::GoalScales;
use assembly_cell::learning::demos::{self, Recording};
use assembly_cell::learning::refine::step_size::StepSizeConfig;
use assembly_cell::learning::refine::{DEMO_REGULARISATION, RefineConfig};
use assembly_cell::learning::run::{self, TrainingSettings};
use assembly_cell::learning::td3::Td3Config;
use assembly_cell::policy::file::PolicyFile;
use assembly_cell::policy::hierarchical::HierarchicalPolicy;
use assembly_cell::policy::inputs::PolicyInputs;
use assembly_cell::sim::EnvOptions;
use assembly_cell::sim::randomise::CellRanges;
use candle_nn::VarMap;
use clap::{Args, Subcommand};
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

mod imitation;
mod policy;
mod refine;

#[derive(Subcommand)]
pub enum TrainCommand {
    /// Behaviour cloning of the two actors on expert demonstrations (SGD).
    Bc(TrainArgs),
    /// The LSTM selector (Adam); also writes the BC policy as bc-policy.safetensors.
    Lstm(TrainArgs),
    /// TD3 refinement of the actors in the twin, from the BC actors.
    Td3(TrainArgs),
    /// Every stage: demonstrations, bc and lstm at once, then td3.
    All(TrainArgs),
    /// The flat TD3 baseline: one 6-DoF actor from fresh weights, no BC, no hierarchy.
    Flat(TrainArgs),
    /// The recommended policy in one command: `all` on a cell of its own for every episode,
    /// then DAgger rounds; with the defaults it makes the bundled `hierarchical-swift-cells`.
    Policy(policy::PolicyArgs),
}

// The settings of a run. Defaults that the HTTP API's training also has come from
// `TrainingSettings::default()` (and `run::LSTM_BATCH_SIZE`, `run::LSTM_LEARNING_RATE`), so
// `celld train all` and `POST /api/training` train alike; the others from the stage's own
// configuration (`BcConfig`, `RefineConfig`, `Td3Config`, `GoalScales`). Why each default is
// what it is: docs/learning-reference.md. (Plain comments: a doc comment here would become the
// subcommands' help.)
#[derive(Args, Clone)]
pub struct TrainArgs {
    /// Run directory (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Continue the run in --out (skip finished stages, resume TD3).
    #[arg(long)]
    resume: bool,
    #[arg(long, default_value_t = TrainingSettings::default().seed)]
    seed: u64,
    /// Cell file (default: the bundled reference cell).
    #[arg(long)]
    cell: Option<PathBuf>,
    /// Expert episodes to record in the twin.
    #[arg(long, default_value_t = DEMONSTRATIONS)]
    demos: usize,
    /// The scripted expert that records them.
    #[arg(long, default_value_t = TrainingSettings::default().demonstrator)]
    demonstrator: String,
    /// σ (mm) of sideways noise on the demonstrator's executed moves (DART; 0: none).
    #[arg(long, default_value_t = 0.0)]
    demo_lateral_noise_mm: f64,
    /// What the policy reads: `absolute` (the paper's state; a version 1 file) or
    /// `cell-relative` (the pose from the goal and the entrance, with the cell's depth,
    /// clearance and hole pitch; a version 2 file that works on cells it was not trained on),
    /// or `cell-scaled` (the same with the tilt, and the orientation actor's tilting moves, in
    /// the cell's own unit: a deep, tight bore's small tilts read as large as the reference
    /// cell's). Every stage of a run must be given the same.
    #[arg(long, default_value = "absolute")]
    inputs: String,
    /// Run every demonstration, DAgger and TD3 episode on a cell of its own, drawn around --cell
    /// over the ranges the product is specified for (diameter 100-250 mm, clearance 0.03-0.1
    /// mm, depth 40-100 mm, 4-16 holes, robot size, camera placement and latency, camera noise
    /// 0.5-2x unless --randomise-noise-up-to, calibration error 0-3x). Needs --inputs
    /// cell-relative or cell-scaled.
    #[arg(long)]
    randomise_cells: bool,
    /// With --randomise-cells: the camera noise is drawn from 0.5 times the data sheet's up to
    /// this multiple (default 2; at most 16).
    #[arg(long, value_name = "SCALE", requires = "randomise_cells")]
    randomise_noise_up_to: Option<f64>,
    /// Robots the DAgger and TD3 episodes (and TD3's validations) are shared among, each in
    /// its own cell that remembers its drift from one episode to the next, as a cell keeps its
    /// robot (`celld eval --robots`); 0: every episode on a robot new to the cell. The
    /// demonstrations for behaviour cloning always run on robots new to the cell.
    #[arg(long, default_value_t = 0)]
    robots: u32,
    /// Read the demonstrations from this JSON Lines file instead of recording them.
    #[arg(long)]
    demos_file: Option<PathBuf>,
    /// DAgger: a policy that drives more episodes for the demonstrator to label (repeatable).
    #[arg(long)]
    dagger_policy: Vec<PathBuf>,
    /// Fine-tune this policy instead of starting from fresh weights.
    #[arg(long)]
    init_policy: Option<PathBuf>,
    /// DAgger episodes teach the actors only; the selector learns from the demonstrator's own
    /// episodes. (The demonstrator's holds on a struggling policy's states can teach a selector
    /// to hold where the demonstrator itself would have moved on.)
    #[arg(long)]
    dagger_actors_only: bool,
    /// Episodes each --dagger-policy drives.
    #[arg(long, default_value_t = DEMONSTRATIONS)]
    dagger_episodes: usize,
    /// Hidden width of each actor (D).
    #[arg(long, default_value_t = TrainingSettings::default().actor_width)]
    actor_width: usize,
    /// BC epochs of the position actor.
    #[arg(long, default_value_t = TrainingSettings::default().bc_epochs)]
    bc_epochs: usize,
    /// BC epochs of the orientation actor.
    #[arg(long, default_value_t = TrainingSettings::default().bc_orientation_epochs)]
    bc_orientation_epochs: usize,
    /// BC batch size.
    #[arg(long, default_value_t = BcConfig::default().batch_size)]
    bc_batch: usize,
    /// BC learning rate (SGD).
    #[arg(long, default_value_t = TrainingSettings::default().bc_learning_rate)]
    bc_lr: f64,
    /// Fraction of the BC epochs, at the end, run at the annealed rate (0: off).
    #[arg(long, default_value_t = BcConfig::default().anneal_fraction)]
    bc_anneal_fraction: f64,
    /// Factor of --bc-lr in the annealed epochs.
    #[arg(long, default_value_t = BcConfig::default().anneal_factor)]
    bc_anneal_factor: f64,
    /// Weight of x, y in the position actor's BC loss.
    #[arg(long, default_value_t = BcConfig::default().lateral_weight)]
    bc_lateral_weight: f64,
    /// Further weight of x, y in the BC losses with the tip in the bore (1: none).
    #[arg(long, default_value_t = TrainingSettings::default().bc_bore_lateral_weight)]
    bc_bore_lateral_weight: f64,
    /// Count each orientation label's BC error relative to the label's size, down to this size
    /// (tanh units, e.g. 0.2): small tilt corrections are then fitted as closely as large ones
    /// (default: every error counts alike).
    #[arg(long)]
    bc_orientation_label_floor: Option<f64>,
    /// The same for the position actor's labels (e.g. 0.2): the last few hundredths of a
    /// millimetre to the seat are then fitted as closely as an insertion step (default: every
    /// error counts alike).
    #[arg(long)]
    bc_position_label_floor: Option<f64>,
    /// Repeats of each insertion step in the position actor's BC samples.
    #[arg(long, default_value_t = BcConfig::default().insertion_repeat)]
    bc_insertion_repeat: usize,
    /// σ (mm) of P_x, P_y in the goal-centred input normaliser.
    #[arg(long, default_value_t = GoalScales::default().lateral_mm)]
    norm_lateral_std_mm: f64,
    /// σ (mm) of P_z in the goal-centred input normaliser.
    #[arg(long, default_value_t = GoalScales::default().depth_mm)]
    norm_depth_std_mm: f64,
    /// σ (deg) of O_x, O_y in the goal-centred input normaliser.
    #[arg(long, default_value_t = GoalScales::default().tilt_deg)]
    norm_tilt_std_deg: f64,
    /// LSTM hidden size (H).
    #[arg(long, default_value_t = TrainingSettings::default().lstm_hidden)]
    lstm_hidden: usize,
    /// LSTM epochs.
    #[arg(long, default_value_t = TrainingSettings::default().lstm_epochs)]
    lstm_epochs: usize,
    /// LSTM learning rate (Adam).
    #[arg(long, default_value_t = run::LSTM_LEARNING_RATE)]
    lstm_lr: f64,
    /// Episodes per LSTM batch.
    #[arg(long, default_value_t = run::LSTM_BATCH_SIZE)]
    lstm_batch: usize,
    /// TD3 episodes (`train td3` and `train flat`).
    #[arg(long, default_value_t = TrainingSettings::default().td3_episodes)]
    td3_episodes: usize,
    /// TD3 actor learning rate (Adam).
    #[arg(long, default_value_t = RefineConfig::default().td3.actor_learning_rate)]
    td3_actor_lr: f64,
    /// σ of TD3's exploration noise [default: 0.002 from BC actors, else 0.1].
    #[arg(long)]
    td3_noise: Option<f64>,
    /// σ of TD3's target-policy smoothing noise (tanh units), clipped at half of it
    /// [default: Table 1's 0.2, clipped at 0.1].
    #[arg(long)]
    td3_target_noise: Option<f64>,
    /// Trust region (tanh units) around the BC actors' outputs (0: plain TD3).
    #[arg(long, default_value_t = RefineConfig::default().td3.trust_region.unwrap_or(0.0))]
    td3_trust_region: f64,
    /// TD3 episodes at the start in which only the critics learn.
    #[arg(long, default_value_t = RefineConfig::default().critic_warmup_episodes)]
    td3_critic_warmup: usize,
    /// TD3 training episodes run at once on all cores, each with the policy as it stood
    /// before the first of them; the agents then learn from each in turn (1: one at a time).
    #[arg(long, default_value_t = RefineConfig::default().parallel_episodes,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1024))]
    td3_parallel_episodes: usize,
    /// Episodes of the demonstrator kept in TD3's replay (0: plain TD3 with the trust region).
    /// With any, TD3 learns beside its demonstrator: critics that also read the true pose,
    /// pre-trained on the demonstrations, and Q-filtered TD3+BC actor updates.
    #[arg(long, default_value_t = 0)]
    td3_demonstrations: usize,
    /// α of the TD3+BC actor update with --td3-demonstrations: the weight of the critic's
    /// value against imitating the demonstrator (smaller imitates more).
    #[arg(long, default_value_t = DEMO_REGULARISATION)]
    td3_demo_alpha: f64,
    /// TD3 also refines the selector's step size: a third agent moves the head's ω3 row,
    /// exploring and moving it further on the approach above the bore (the tip more than 5 mm
    /// above the entrance) than in the bore.
    #[arg(long)]
    td3_step_size: bool,
    /// With --td3-step-size: σ of the step-size agent's exploration on the approach (u = 2·s − 1).
    #[arg(long, default_value_t = StepSizeConfig::default().coarse_noise)]
    td3_step_noise: f64,
    /// With --td3-step-size: its trust region on the approach (u = 2·s − 1).
    #[arg(long, default_value_t = StepSizeConfig::default().coarse_trust_region)]
    td3_step_trust_region: f64,
    /// With --td3-step-size: its trust region elsewhere (u = 2·s − 1).
    #[arg(long, default_value_t = StepSizeConfig::default().fine_trust_region)]
    td3_step_fine_trust_region: f64,
    /// With --td3-step-size: Adam's rate for the selector's step-size row.
    #[arg(long, default_value_t = StepSizeConfig::default().learning_rate)]
    td3_step_lr: f64,
    /// With --td3-step-size: reward shaping of the step-size agent, per mm the estimated
    /// distance to the goal shrinks over a step (0: the paper's reward alone).
    #[arg(long, default_value_t = StepSizeConfig::default().progress_reward_per_mm)]
    td3_step_progress_reward: f64,
    /// Start TD3 from freshly initialised actors instead of the BC actors.
    #[arg(long)]
    no_bc_init: bool,
    /// Validate (and keep the best policy) every this many TD3 episodes.
    #[arg(long, default_value_t = TrainingSettings::default().eval_every)]
    eval_every: usize,
    /// Episodes of each validation.
    #[arg(long, default_value_t = TrainingSettings::default().eval_episodes)]
    eval_episodes: usize,
    /// Write a TD3 checkpoint every this many episodes.
    #[arg(long, default_value_t = 50)]
    checkpoint_every: usize,
    /// Hidden width of the flat baseline's actor and critics (`train flat`).
    #[arg(long, default_value_t = Td3Config::default().hidden)]
    flat_hidden: usize,
}

/// Expert episodes `celld train` records (and each DAgger round drives) by default. The HTTP
/// API records its own default number (docs/service.md).
const DEMONSTRATIONS: usize = 800;

const DEMOS: &str = "demos.jsonl";
const BC: &str = "bc.safetensors";
const LSTM: &str = "lstm.safetensors";
const BC_POLICY: &str = "bc-policy.safetensors";
const TD3_CHECKPOINT: &str = "td3_checkpoint.safetensors";
const TD3_PROGRESS: &str = "td3_progress.json";
const POLICY: &str = "policy.safetensors";
const FLAT_CHECKPOINT: &str = "td3-flat_checkpoint.safetensors";
const FLAT_PROGRESS: &str = "td3-flat_progress.json";
const FLAT_POLICY: &str = "td3-flat-policy.safetensors";

/// Reads and checks --init-policy: a hierarchical policy file of this run's sizes and the
/// cell's step limits.
fn init_policy(
    path: &Path,
    args: &TrainArgs,
    cell: &CellConfig,
    inputs: PolicyInputs,
) -> Result<PolicyFile> {
    let file =
        PolicyFile::from_path(path).with_context(|| format!("--init-policy {}", path.display()))?;
    let context = |what: String| format!("--init-policy {}: {what}", path.display());
    let theirs = file.metadata().inputs;
    if theirs != inputs {
        bail!(context(format!(
            "it reads {} inputs, this run's --inputs is {}",
            theirs.name(),
            inputs.name()
        )));
    }
    for (name, ours, theirs) in [
        ("--actor-width", args.actor_width, file.actor_width()),
        ("--lstm-hidden", args.lstm_hidden, file.hidden_size()),
    ] {
        if ours != theirs {
            bail!(context(format!(
                "its size is {theirs}, this run's {name} is {ours}"
            )));
        }
    }
    for (name, ours, theirs) in [
        ("position", cell.steps.position_mm, file.step_limit_mm()),
        (
            "orientation",
            cell.steps.orientation_deg,
            file.step_limit_deg(),
        ),
    ] {
        if ours != theirs {
            bail!(context(format!(
                "its {name} step limit is {theirs}, the cell's is {ours}"
            )));
        }
    }
    Ok(file)
}

pub fn run(command: TrainCommand) -> Result<()> {
    let (args, stages): (TrainArgs, &[Stage]) = match command {
        TrainCommand::Bc(a) => (a, &[Stage::Bc]),
        TrainCommand::Lstm(a) => (a, &[Stage::Lstm]),
        TrainCommand::Td3(a) => (a, &[Stage::Td3]),
        TrainCommand::All(a) => (a, &[Stage::BcAndLstm, Stage::Td3]),
        TrainCommand::Flat(a) => (a, &[Stage::Flat]),
        TrainCommand::Policy(a) => return policy::run(a),
    };
    let run = Run::open(args)?;
    if stages.contains(&Stage::Flat) && run.inputs != PolicyInputs::Absolute {
        bail!(
            "`train flat` trains the flat baseline on the absolute inputs only; leave out --inputs"
        );
    }
    for stage in stages {
        run.stage(*stage)?;
    }
    Ok(())
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Stage {
    Bc,
    Lstm,
    BcAndLstm,
    Td3,
    Flat,
}

/// A stage's trained weights, before they are written, with its figures for run.json.
struct Fitted {
    varmap: VarMap,
    /// How long the training took (s), not counting the wait for the other one.
    wall_s: f64,
    figures: Value,
}

struct Run {
    args: TrainArgs,
    cell: CellConfig,
    options: EnvOptions,
    /// What the policy reads (--inputs).
    inputs: PolicyInputs,
    /// The ranges drawn cells come from, with --randomise-cells.
    ranges: CellRanges,
    /// The --dagger-policy files, loaded and checked, in order.
    dagger_drivers: Vec<HierarchicalPolicy>,
    /// The --init-policy file, checked.
    init: Option<PolicyFile>,
}

impl Run {
    /// Checks every setting before any work starts.
    fn open(args: TrainArgs) -> Result<Self> {
        let cell = match &args.cell {
            Some(path) => CellConfig::load(path)?,
            None => CellConfig::reference(),
        };
        let positive = [
            ("--actor-width", args.actor_width),
            ("--bc-epochs", args.bc_epochs),
            ("--bc-orientation-epochs", args.bc_orientation_epochs),
            ("--bc-batch", args.bc_batch),
            ("--bc-insertion-repeat", args.bc_insertion_repeat),
            ("--lstm-hidden", args.lstm_hidden),
            ("--lstm-epochs", args.lstm_epochs),
            ("--lstm-batch", args.lstm_batch),
            ("--eval-episodes", args.eval_episodes),
            ("--checkpoint-every", args.checkpoint_every),
            ("--flat-hidden", args.flat_hidden),
        ];
        for (name, value) in positive {
            if value == 0 {
                bail!("{name} must be at least 1");
            }
        }
        if args.demos_file.is_none() && args.demos < 10 {
            bail!(
                "--demos must be at least 10 (a tenth is held out to check the selector), got {}",
                args.demos
            );
        }
        for (name, lr) in [
            ("--bc-lr", args.bc_lr),
            ("--lstm-lr", args.lstm_lr),
            ("--bc-lateral-weight", args.bc_lateral_weight),
            ("--bc-bore-lateral-weight", args.bc_bore_lateral_weight),
            ("--td3-actor-lr", args.td3_actor_lr),
            ("--norm-lateral-std-mm", args.norm_lateral_std_mm),
            ("--norm-depth-std-mm", args.norm_depth_std_mm),
            ("--norm-tilt-std-deg", args.norm_tilt_std_deg),
            ("--td3-step-noise", args.td3_step_noise),
            ("--td3-step-trust-region", args.td3_step_trust_region),
            (
                "--td3-step-fine-trust-region",
                args.td3_step_fine_trust_region,
            ),
            ("--td3-step-lr", args.td3_step_lr),
        ]
        .into_iter()
        .chain(args.td3_noise.map(|noise| ("--td3-noise", noise)))
        .chain(
            args.td3_target_noise
                .map(|noise| ("--td3-target-noise", noise)),
        ) {
            if !(lr.is_finite() && lr > 0.0) {
                bail!("{name} must be a finite number > 0, got {lr}");
            }
        }
        for (name, floor) in [
            (
                "--bc-orientation-label-floor",
                args.bc_orientation_label_floor,
            ),
            ("--bc-position-label-floor", args.bc_position_label_floor),
        ] {
            if let Some(floor) = floor
                && !(floor.is_finite() && floor > 0.0 && floor <= 1.0)
            {
                bail!("{name} must be in (0, 1], got {floor}");
            }
        }
        if !(args.td3_step_progress_reward.is_finite() && args.td3_step_progress_reward >= 0.0) {
            bail!(
                "--td3-step-progress-reward must be a finite number >= 0, got {}",
                args.td3_step_progress_reward
            );
        }
        if !(args.td3_trust_region.is_finite() && args.td3_trust_region >= 0.0) {
            bail!(
                "--td3-trust-region must be a finite number >= 0 (0: none), got {}",
                args.td3_trust_region
            );
        }
        if !(0.0..=1.0).contains(&args.bc_anneal_fraction) {
            bail!(
                "--bc-anneal-fraction must be between 0 and 1, got {}",
                args.bc_anneal_fraction
            );
        }
        if !(args.bc_anneal_factor > 0.0 && args.bc_anneal_factor <= 1.0) {
            bail!(
                "--bc-anneal-factor must be > 0 and at most 1, got {}",
                args.bc_anneal_factor
            );
        }
        demos::check_demonstrator(&args.demonstrator)
            .map_err(|e| anyhow::anyhow!("--demonstrator {e}"))?;
        let inputs = PolicyInputs::parse(&args.inputs).ok_or_else(|| {
            anyhow::anyhow!(
                "--inputs {}: expected one of {}",
                args.inputs,
                PolicyInputs::ALL.map(PolicyInputs::name).join(", ")
            )
        })?;
        if args.randomise_cells && !inputs.reads_the_cell() {
            bail!(
                "--randomise-cells needs --inputs cell-relative or cell-scaled: a policy that \
                 reads the absolute pose cannot tell the drawn cells apart"
            );
        }
        let ranges = CellRanges::drawn(args.randomise_noise_up_to)
            .map_err(|e| anyhow::anyhow!("--randomise-noise-up-to {e}"))?;
        if let Some(path) = &args.demos_file
            && !path.is_file()
        {
            bail!("--demos-file {}: no such file", path.display());
        }
        if !args.dagger_policy.is_empty() {
            if args.demos_file.is_some() {
                bail!("--dagger-policy records in the twin; it cannot add to --demos-file");
            }
            if args.dagger_episodes == 0 {
                bail!("--dagger-episodes must be at least 1");
            }
        }
        let dagger_drivers = args
            .dagger_policy
            .iter()
            .map(|path| {
                HierarchicalPolicy::from_path(path)
                    .with_context(|| format!("--dagger-policy {}", path.display()))
            })
            .collect::<Result<Vec<_>>>()?;
        let init = args
            .init_policy
            .as_ref()
            .map(|path| init_policy(path, &args, &cell, inputs))
            .transpose()?;
        std::fs::create_dir_all(&args.out)
            .with_context(|| format!("--out {}: cannot create", args.out.display()))?;
        let options = EnvOptions {
            kept_robots: args.robots,
            ..EnvOptions::from_cell(&cell)
        };
        Ok(Run {
            args,
            cell,
            options,
            inputs,
            ranges,
            dagger_drivers,
            init,
        })
    }

    /// The demonstrator's own episodes each run on a robot new to the cell, whatever
    /// --robots says: the episodes in which the cell learns its robot's drift show the
    /// learner more states around the demonstrator's path, and behaviour cloning from them
    /// succeeded more often (docs/learning-reference.md).
    fn demonstration_options(&self) -> EnvOptions {
        EnvOptions {
            kept_robots: 0,
            ..self.options
        }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.args.out.join(name)
    }

    /// Whether a stage whose output is `name` should run: not if it exists and --resume is on;
    /// an error if it exists without --resume.
    fn should_run(&self, name: &str) -> Result<bool> {
        if !self.path(name).exists() {
            return Ok(true);
        }
        if self.args.resume {
            eprintln!(
                "{}: already there, kept (--resume)",
                self.path(name).display()
            );
            return Ok(false);
        }
        bail!(
            "{} exists; pass --resume to continue that run, or choose another --out",
            self.path(name).display()
        )
    }

    fn needs(&self, name: &str, stage: &str) -> Result<PathBuf> {
        let path = self.path(name);
        if !path.is_file() {
            bail!(
                "{} is missing: run `celld train {stage} --out {}` first",
                path.display(),
                self.args.out.display()
            );
        }
        Ok(path)
    }

    fn stage(&self, stage: Stage) -> Result<()> {
        match stage {
            Stage::Bc => self.bc(),
            Stage::Lstm => self.lstm(),
            Stage::BcAndLstm => self.bc_and_lstm(),
            Stage::Td3 => self.td3(),
            Stage::Flat => self.flat(),
        }
    }

    /// How this run records its demonstrations and DAgger episodes.
    fn recording(&self) -> Recording {
        Recording {
            noise: demos::ExecutionNoise {
                lateral_mm: self.args.demo_lateral_noise_mm,
            },
            inputs: self.inputs,
            randomise: self.args.randomise_cells.then_some(self.ranges),
        }
    }

    fn provenance(&self, kind: &str) -> BTreeMap<String, String> {
        BTreeMap::from([
            ("policy".to_string(), kind.to_string()),
            ("seed".to_string(), self.args.seed.to_string()),
            ("cell".to_string(), self.cell.name.clone()),
            (
                "trained_by".to_string(),
                format!("celld {}", env!("CARGO_PKG_VERSION")),
            ),
        ])
    }

    /// Adds a stage's figures and wall time to run.json.
    fn note(&self, stage: &str, wall_s: f64, figures: Value) -> Result<()> {
        let path = self.path("run.json");
        let mut run: Value = match std::fs::read(&path) {
            Ok(bytes) => serde_json::from_slice(&bytes).unwrap_or_else(|_| json!({})),
            Err(_) => json!({}),
        };
        run["seed"] = json!(self.args.seed);
        run["cell"] = json!(self.cell.name);
        run[stage] = json!({"wall_s": wall_s, "figures": figures});
        write_atomically(&path, &serde_json::to_vec_pretty(&run)?)?;
        eprintln!("{stage}: {wall_s:.1} s");
        Ok(())
    }
}

fn bar(len: u64, stage: &str) -> Progress {
    let template =
        format!("{stage:>4} {{bar:30}} {{pos}}/{{len}} {{elapsed}} (eta {{eta}}) {{msg}}");
    Progress::new(len, stage, &template)
}
