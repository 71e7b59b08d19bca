//! `celld train policy`: the recommended policy in one command. It runs `train all` once on the
//! demonstrator's episodes, then `--dagger-rounds` (default none) more times, each with the last
//! round's policy driving DAgger episodes that teach the actors only, then a polishing round
//! that fine-tunes the last policy with small moves weighed as closely as large ones. With the
//! defaults it learns from `expert-swift` and makes the recipe of
//! `policies/swift-cells.safetensors` (controller `hierarchical-swift-cells`, decision 0048);
//! `-- --demonstrator expert-careful` makes that of `hierarchical-cells`.
//!
//! The recipe is written as `train all` flags ([`RECIPE`], [`DAGGER_ROUND`]) and parsed into the
//! same settings, so each round is exactly the `train all` command that `run.json` and the docs
//! name, and any of its flags can be changed after `--`.

use super::{POLICY, Run, Stage, TrainArgs};
use anyhow::{Context, Result, bail};
use assembly_cell::files::write_atomically;
use assembly_cell::learning::run::POLISH;
use clap::{Args, Parser};
use std::path::{Path, PathBuf};

/// Every round's `train all` flags: the swift demonstrator (decision 0048), sideways errors in the bore
/// weighted 30 in the BC loss, cell-scaled inputs (the tilt in each cell's own unit), a cell of
/// its own for every episode, the
/// orientation actor's errors relative to its labels down to 0.2, one TD3 episode (TD3 on the
/// actors does not improve on BC; the polishing round runs TD3 on the step size), and 1600
/// demonstrations with the position actor's epochs halved (as many updates, on twice the
/// states).
const RECIPE: &[&str] = &[
    "--demonstrator",
    "expert-swift",
    "--bc-bore-lateral-weight",
    "30",
    "--inputs",
    "cell-scaled",
    "--randomise-cells",
    "--bc-orientation-label-floor",
    "0.2",
    "--td3-episodes",
    "1",
    "--demos",
    "1600",
    "--bc-epochs",
    "100",
];

/// The further flag of a DAgger round (before `--dagger-policy`): its episodes teach the actors
/// only.
const DAGGER_ROUND: &[&str] = &["--dagger-actors-only"];

/// The further flags of the polishing round (before `--init-policy`), from [`POLISH`]: 6
/// epochs from the last round's policy at a tenth of the first pass's rate, the position
/// actor's errors relative to its labels down to 0.3 as well as the orientation actor's, and
/// one epoch of the selector at a tenth of its rate. The first pass answers the last few
/// hundredths of a millimetre to the seat with no move; the polish teaches it that move. From
/// scratch, the same weighting left a shallow Φ250 cell at 0.45 (docs/learning-reference.md § Why the
/// defaults are what they are).
fn polish_flags() -> Vec<String> {
    [
        (
            "--bc-position-label-floor",
            POLISH.position_label_floor.to_string(),
        ),
        ("--bc-lr", POLISH.bc_learning_rate.to_string()),
        ("--bc-epochs", POLISH.bc_epochs.to_string()),
        (
            "--bc-anneal-fraction",
            POLISH.bc_anneal_fraction.to_string(),
        ),
        ("--bc-anneal-factor", POLISH.bc_anneal_factor.to_string()),
        (
            "--bc-orientation-epochs",
            POLISH.bc_orientation_epochs.to_string(),
        ),
        ("--lstm-lr", POLISH.lstm_learning_rate.to_string()),
        ("--lstm-epochs", POLISH.lstm_epochs.to_string()),
    ]
    .into_iter()
    .flat_map(|(flag, value)| [flag.to_string(), value])
    .collect()
}

/// The polishing round's TD3 (before the caller's flags, which may change it): 500 episodes
/// with the step-size agent on 10 kept robots. On the approach the first pass's selector steps
/// short of the demonstrator's full steps, and TD3 lengthens them (decision 0027).
fn polish_td3_flags() -> Vec<String> {
    vec![
        "--td3-episodes".into(),
        POLISH.td3_episodes.to_string(),
        "--robots".into(),
        POLISH.td3_robots.to_string(),
        "--td3-step-size".into(),
    ]
}

/// DAgger rounds after the first pass by default: none. Since the demonstrator corrects the
/// tilt to what each cell takes, one round has raised the deep, tight cells and lowered others,
/// by how much depending on the episodes it drew (a shallow Φ250 cell from 0.944 to 0.908 in
/// one run and to 0.420 in another; docs/learning-reference.md § Training in detail).
const DEFAULT_DAGGER_ROUNDS: usize = 0;

/// Flags a round sets itself; after `--` they would break the chain of rounds.
const OWN_FLAGS: [&str; 7] = [
    "--out",
    "--resume",
    "--seed",
    "--cell",
    "--dagger-policy",
    "--init-policy",
    "--demos-file",
];

#[derive(Args, Clone)]
pub struct PolicyArgs {
    /// Run directory: round k goes to DIR/round-k, the final policy to DIR/policy.safetensors.
    #[arg(long)]
    out: PathBuf,
    /// Continue the run in --out (finished rounds and stages are kept).
    #[arg(long)]
    resume: bool,
    #[arg(long, default_value_t = assembly_cell::learning::run::TrainingSettings::default().seed)]
    seed: u64,
    /// Cell file the cells are drawn around (default: the bundled reference cell).
    #[arg(long)]
    cell: Option<PathBuf>,
    /// DAgger rounds after the first pass, each driven by the previous round's policy.
    #[arg(long, default_value_t = DEFAULT_DAGGER_ROUNDS)]
    dagger_rounds: usize,
    /// Skip the polishing round: the last DAgger round's (or the first pass's) policy is the
    /// run's.
    #[arg(long)]
    no_polish: bool,
    /// More `celld train all` flags for every round, after `--` (they override the recipe's,
    /// e.g. `-- --demos 400 --dagger-episodes 400`, but not the polishing round's own epochs,
    /// rates and position floor).
    #[arg(last = true)]
    train_flags: Vec<String>,
}

/// `train all`'s flags, parsed as the command line parses them; a later flag overrides an
/// earlier one, so the caller's flags override the recipe's.
#[derive(Parser)]
#[command(args_override_self = true)]
struct AllFlags {
    #[command(flatten)]
    args: TrainArgs,
}

impl PolicyArgs {
    /// The rounds of the run: the first pass, the DAgger rounds and the polishing round.
    fn rounds(&self) -> usize {
        self.dagger_rounds + 1 + usize::from(!self.no_polish)
    }

    fn is_polish(&self, round: usize) -> bool {
        !self.no_polish && round == self.dagger_rounds + 1
    }

    /// Round k's directory: DIR/round-k, the polishing round's DIR/polish.
    fn round_dir(&self, round: usize) -> PathBuf {
        if self.is_polish(round) {
            self.out.join("polish")
        } else {
            self.out.join(format!("round-{round}"))
        }
    }

    /// Round `round`'s `train all` command line (without the program name).
    fn round_flags(&self, round: usize) -> Vec<String> {
        let mut flags: Vec<String> = vec!["--out".into(), path(&self.round_dir(round))];
        flags.extend(["--seed".into(), self.seed.to_string()]);
        if let Some(cell) = &self.cell {
            flags.extend(["--cell".into(), path(cell)]);
        }
        if self.resume {
            flags.push("--resume".into());
        }
        flags.extend(RECIPE.iter().map(|flag| flag.to_string()));
        let last = self.round_dir(round.saturating_sub(1)).join(POLICY);
        if round > 0 && !self.is_polish(round) {
            flags.extend(DAGGER_ROUND.iter().map(|flag| flag.to_string()));
            flags.extend(["--dagger-policy".into(), path(&last)]);
        }
        if self.is_polish(round) {
            flags.extend(polish_td3_flags());
        }
        flags.extend(self.train_flags.iter().cloned());
        // The polish's schedule is its own: it comes after the caller's flags.
        if self.is_polish(round) {
            flags.extend(polish_flags());
            flags.extend(["--init-policy".into(), path(&last)]);
        }
        flags
    }

    fn round_args(&self, round: usize) -> Result<TrainArgs> {
        let flags = self.round_flags(round);
        let command_line = std::iter::once("celld train all".to_string()).chain(flags);
        AllFlags::try_parse_from(command_line)
            .map(|parsed| parsed.args)
            .map_err(|e| anyhow::anyhow!("the flags after --: {}", e.render()))
    }
}

fn path(path: &Path) -> String {
    path.to_string_lossy().into_owned()
}

/// Runs the rounds in order and copies the last one's policy to `--out`.
pub fn run(args: PolicyArgs) -> Result<()> {
    for flag in &args.train_flags {
        let name = flag.split('=').next().unwrap_or(flag);
        if OWN_FLAGS.contains(&name) {
            bail!("{name} after --: `celld train policy` sets it for each round itself");
        }
    }
    // Every round's settings are parsed before the first one starts.
    let settings = (0..args.rounds())
        .map(|round| args.round_args(round))
        .collect::<Result<Vec<_>>>()?;
    let rounds = settings.len();
    for (round, round_args) in settings.into_iter().enumerate() {
        eprintln!(
            "round {} of {rounds}: `celld train all` with {} (a later flag wins)",
            round + 1,
            args.round_flags(round).join(" ")
        );
        let run = Run::open(round_args).with_context(|| format!("round {}", round + 1))?;
        for stage in [Stage::BcAndLstm, Stage::Td3] {
            run.stage(stage)
                .with_context(|| format!("round {}", round + 1))?;
        }
    }
    let last = args.round_dir(rounds - 1).join(POLICY);
    let policy = args.out.join(POLICY);
    let bytes = std::fs::read(&last).with_context(|| format!("{}", last.display()))?;
    write_atomically(&policy, &bytes)?;
    eprintln!("policy: {}", policy.display());
    Ok(())
}
