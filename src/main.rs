//! `celld`: the assembly cell service and its tools.

use anyhow::{Context, Result, bail};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::config::service::PolicyConfig;
use assembly_cell::policy::hierarchical::HierarchicalPolicy;
use assembly_cell::policy::learned::LearnedPolicy;
use assembly_cell::policy::shield::{RuleId, RuleSelection};
use assembly_cell::policy::{self, eval};
use assembly_cell::sim::randomise::CellRanges;
use assembly_cell::sim::{EnvOptions, Fault, InitialConditions};
use clap::{Args, Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;

mod cli;

#[derive(Parser)]
#[command(
    name = "celld",
    version,
    about = "Runs the Φ170 shaft-in-bore assembly cell: the service, its twin, training and evaluation",
    long_about = "Runs the Φ170 shaft-in-bore assembly cell. With no command, celld serves the \
                  twin of the reference cell on 127.0.0.1:8080 and prints the dashboard link \
                  (the same as `celld serve`). Docs: README.md and docs/."
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

// Parsed once per process: the size of the largest variant (`train`'s arguments) costs nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand)]
enum Command {
    /// Run N episodes of a controller in the digital twin and summarise them.
    Eval(EvalArgs),
    /// Work with hierarchical policy files.
    #[command(subcommand)]
    Policy(PolicyCommand),
    /// Train the hierarchical policy: demonstrations, BC actors, LSTM selector, TD3.
    #[command(subcommand)]
    Train(cli::train::TrainCommand),
    /// Reproduce the structure of the paper's Tables 2–6 and Fig. 7 on the twin.
    Report(cli::report::ReportArgs),
    /// Run the cell service: dashboard, jobs, telemetry and history over HTTP (the default).
    Serve(cli::serve::ServeArgs),
    /// Time the drivers on this machine: move round trip, ingestion, e-stop to STP.
    Latency(cli::latency::LatencyArgs),
    /// Serve the digital twin as a GCS hexapod controller and an OpenIGTLink camera.
    TwinServer(cli::twin_server::TwinServerArgs),
    /// Manage API tokens.
    #[command(subcommand)]
    Token(cli::serve::TokenCommand),
    /// Check the bundled policies against their goals; exits non-zero when one is missed.
    Check(cli::check::CheckArgs),
}

#[derive(Subcommand)]
enum PolicyCommand {
    /// Print a policy file's decisions (omega, actor, scale, action) for a file of states.
    Run {
        /// The policy file (.safetensors).
        #[arg(long)]
        policy: PathBuf,
        /// One episode of states: JSON Lines, 12 numbers a line.
        #[arg(long)]
        states: PathBuf,
    },
}

#[derive(Args)]
struct EvalArgs {
    /// A built-in controller (expert, expert-state-only, expert-careful, expert-swift,
    /// visual-servo, spiral, da-dmp, hierarchical-reference, bc, td3, hierarchical-cells,
    /// hierarchical-swift-reference, hierarchical-swift-cells) or a policy file (.safetensors).
    #[arg(long, default_value = "expert")]
    controller: String,
    /// Cell file (default: the bundled reference cell, cells/phi170.toml).
    #[arg(long)]
    cell: Option<PathBuf>,
    /// Episodes to run.
    #[arg(long, default_value_t = 1000)]
    episodes: usize,
    /// Seed of the evaluation (each episode's seed is derived from it).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Initial offset from the mouth pose, mm (default: the cell file's, 50 mm).
    #[arg(long)]
    init_pos_mm: Option<f64>,
    /// Initial orientation error, deg (default: the cell file's, 1 deg).
    #[arg(long)]
    init_ori_deg: Option<f64>,
    /// Multiplies the camera's point noise (0 = noiseless, 1 = the spec).
    #[arg(long, default_value_t = 1.0)]
    noise_scale: f64,
    /// Multiplies the robot's kinematic calibration error, the radius of the ball its true joint
    /// centres are drawn in (0 = perfectly calibrated, 1 = the cell file's).
    #[arg(long, default_value_t = 1.0)]
    calibration_scale: f64,
    /// Inject a fault in every episode, from a step drawn in 5..=35 to the end: camera_shift,
    /// occlusion, frozen_camera, out_of_order, robot_lag or robot_short (docs/configuration.md).
    #[arg(long, value_name = "NAME")]
    fault: Option<Fault>,
    /// Robots the episodes are shared among. Each is kept for its share, and the cell starts
    /// each episode from the drift it learned of that robot in the ones before, as a cell in
    /// service does (docs/estimation.md §3a). 0: every episode a robot the cell has never seen.
    #[arg(long, default_value_t = eval::DEFAULT_KEPT_ROBOTS)]
    robots: u32,
    /// Imperfections of the twin to switch off (comma-separated).
    #[arg(long, value_enum, value_delimiter = ',')]
    without: Vec<Imperfection>,
    /// Run on cells drawn around --cell over the ranges the product is specified for, as
    /// `celld train all --randomise-cells` draws them (docs/learning-reference.md): each kept robot on a
    /// cell of its own (with --robots 0, each episode), its camera noise and calibration error
    /// drawn too. The draws come from --seed, so they are not the cells a training run saw.
    #[arg(long, conflicts_with_all = ["noise_scale", "calibration_scale"])]
    randomise_cells: bool,
    /// With --randomise-cells: the camera noise is drawn from 0.5 times the data sheet's up to
    /// this multiple (default 2, as training draws it; at most 16).
    #[arg(long, value_name = "SCALE", requires = "randomise_cells")]
    randomise_noise_up_to: Option<f64>,
    /// The rules between a learned policy's proposal and the supervisor to run with
    /// (docs/policy-rules.md): all (the cell file's `[rules]`), none (the networks' own moves),
    /// or a comma-separated list of rule names (only those).
    #[arg(long, default_value = "all", value_name = "all|none|LIST")]
    rules: RuleSelection,
    /// With --randomise-cells: also print each drawn cell (what was drawn, and its success
    /// rate over its own episodes) and how many cells reach --threshold: the activation
    /// gate's question asked of every cell. `--robots 100 --episodes 100000`: 100 cells of
    /// 1000 episodes each, the gate's count.
    #[arg(long, requires = "randomise_cells")]
    per_cell: bool,
    /// With --per-cell: the success rate a cell must reach (default: the service's
    /// `policies.activation_threshold`, 0.95).
    #[arg(long, requires = "per_cell")]
    threshold: Option<f64>,
    /// Print the summary as one JSON object on the last line.
    #[arg(long)]
    json: bool,
}

/// The twin's imperfections, as `--without` names them.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
#[value(rename_all = "snake_case")]
enum Imperfection {
    CameraNoise,
    DroppedPoints,
    Outliers,
    Latency,
    CalibrationError,
    ExecutionError,
    All,
}

impl Imperfection {
    fn switch_off(self, cell: &mut CellConfig) {
        let switches = &mut cell.imperfections;
        match self {
            Imperfection::CameraNoise => switches.camera_noise = false,
            Imperfection::DroppedPoints => switches.dropped_points = false,
            Imperfection::Outliers => switches.outliers = false,
            Imperfection::Latency => switches.latency = false,
            Imperfection::CalibrationError => switches.calibration_error = false,
            Imperfection::ExecutionError => switches.execution_error = false,
            Imperfection::All => {
                for each in Self::value_variants().iter().filter(|v| **v != Self::All) {
                    each.switch_off(cell);
                }
            }
        }
    }
}

fn main() -> ExitCode {
    // candle 0.11 re-reads the CPU count on every matmul unless RAYON_NUM_THREADS is set.
    assembly_cell::threads::init_cpu_threads();
    let command = Cli::parse()
        .command
        .unwrap_or_else(|| Command::Serve(Default::default()));
    if !matches!(command, Command::Serve(_) | Command::TwinServer(_)) {
        stop_quietly_when_stdout_closes();
    }
    let result = match command {
        Command::Eval(args) => run_eval(args),
        Command::Policy(PolicyCommand::Run { policy, states }) => run_policy(&policy, &states),
        Command::Train(command) => cli::train::run(command),
        Command::Report(args) => cli::report::run(args),
        Command::Serve(args) => cli::serve::serve(args),
        Command::Token(command) => cli::serve::token(command),
        Command::TwinServer(args) => cli::twin_server::run(args),
        Command::Latency(args) => cli::latency::run(args),
        Command::Check(args) => cli::check::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            // `{:#}`: the causes, no backtrace; and none a library wrote into its message.
            eprintln!(
                "error: {}",
                assembly_cell::error_text::without_backtrace(&format!("{error:#}"))
            );
            ExitCode::FAILURE
        }
    }
}

/// `celld eval … | head` ends quietly when the reader goes away, as Unix tools do, instead of
/// panicking in `println!` (Rust ignores SIGPIPE). Not for `serve`: a service outlives a
/// closed pipe.
fn stop_quietly_when_stdout_closes() {
    // SAFETY: called from `main` before any other thread exists; it restores the default
    // disposition of one signal.
    #[cfg(unix)]
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

fn load_cell(path: Option<&PathBuf>) -> Result<CellConfig> {
    match path {
        Some(path) => Ok(CellConfig::load(path)?),
        None => Ok(CellConfig::reference()),
    }
}

fn run_eval(args: EvalArgs) -> Result<()> {
    let mut cell = load_cell(args.cell.as_ref())?;
    cell.rules = cell.rules.selected(&args.rules);
    for imperfection in &args.without {
        imperfection.switch_off(&mut cell);
    }
    if args.episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    let mut initial = InitialConditions::from_cell(&cell);
    if let Some(mm) = args.init_pos_mm {
        if !(mm.is_finite() && mm >= 0.0) {
            bail!("--init-pos-mm must be a finite number ≥ 0, got {mm}");
        }
        initial.offset_mm = mm;
    }
    if let Some(deg) = args.init_ori_deg {
        if !(deg.is_finite() && (0.0..=cell.episode.workspace_tilt_deg).contains(&deg)) {
            bail!(
                "--init-ori-deg must lie in [0, {}] deg (the workspace tilt), got {deg}",
                cell.episode.workspace_tilt_deg
            );
        }
        initial.orientation_deg = deg;
    }
    if !(args.noise_scale.is_finite() && args.noise_scale >= 0.0) {
        bail!(
            "--noise-scale must be a finite number ≥ 0, got {}",
            args.noise_scale
        );
    }
    if !(args.calibration_scale.is_finite() && args.calibration_scale >= 0.0) {
        bail!(
            "--calibration-scale must be a finite number ≥ 0, got {}",
            args.calibration_scale
        );
    }
    let ranges = CellRanges::drawn(args.randomise_noise_up_to)
        .map_err(|e| anyhow::anyhow!("--randomise-noise-up-to {e}"))?;
    let threshold = args
        .threshold
        .unwrap_or(PolicyConfig::default().activation_threshold);
    if !(0.0..=1.0).contains(&threshold) {
        bail!("--threshold must lie in [0, 1], got {threshold}");
    }
    // Fail on an unknown name or a bad policy file before any work starts.
    let policy_file = controller_file(&args.controller);
    let factory: policy::ControllerFactory = match &policy_file {
        Some(path) => {
            let loaded = LearnedPolicy::from_path(path)
                .with_context(|| format!("--controller {}", path.display()))?
                .with_rules(&cell.rules);
            Box::new(move || Box::new(loaded.clone()))
        }
        None => policy::builtin_factory(&args.controller, &cell).context("--controller")?,
    };
    // On a drawn cell a built-in controller is made for that cell (the experts read its
    // geometry); a policy file reads the cell from its observations.
    let controller_for = |drawn: &CellConfig| -> Box<dyn policy::Controller> {
        match &policy_file {
            Some(_) => factory(),
            None => policy::builtin(&args.controller, drawn).expect("checked above"),
        }
    };
    let options = EnvOptions {
        noise_scale: args.noise_scale,
        calibration_scale: args.calibration_scale,
        fault: args.fault,
        initial,
        kept_robots: args.robots,
        robot_seed: 0,
    };
    let progress = ProgressBar::new(args.episodes as u64);
    progress.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} episodes  {elapsed} (eta {eta})")
            .expect("valid template"),
    );
    let on_episode = |_: &eval::EpisodeReport| progress.inc(1);
    let (summary, reports) = if args.randomise_cells {
        eval::evaluate_on_drawn_cells(
            &cell,
            &ranges,
            options,
            args.episodes,
            args.seed,
            &controller_for,
            &on_episode,
        )
    } else {
        eval::evaluate(
            &cell,
            options,
            args.episodes,
            args.seed,
            &factory,
            &on_episode,
        )
    };
    progress.finish_and_clear();
    let (cells, noise, calibration) = match summary.drawn_cells {
        Some(drawn) => (
            format!("{drawn} cells drawn around {}", summary.cell),
            format!("{}–{} drawn", ranges.noise_scale.0, ranges.noise_scale.1),
            format!(
                "{}–{} drawn",
                ranges.calibration_scale.0, ranges.calibration_scale.1
            ),
        ),
        None => (
            summary.cell.clone(),
            summary.noise_scale.to_string(),
            summary.calibration_scale.to_string(),
        ),
    };
    println!(
        "{} on {cells}: {} episodes, seed {}, initial {} mm / {} deg, noise ×{noise}, calibration ×{calibration}, fault {}, {}",
        summary.controller,
        summary.episodes,
        summary.seed,
        summary.init_pos_mm,
        summary.init_ori_deg,
        summary.fault.as_deref().unwrap_or("none"),
        match summary.kept_robots {
            0 => "a new robot each episode".to_string(),
            n => format!("{n} kept robots"),
        },
    );
    println!(
        "  success rate {:.4} ({} of {})",
        summary.success_rate, summary.successes, summary.episodes
    );
    match summary.avg_steps {
        Some(steps) => println!("  avg steps (successes) {steps:.2}"),
        None => println!("  avg steps (successes) -"),
    }
    println!(
        "  avg reward {:.2}, avg vetoes {:.2}",
        summary.avg_reward, summary.avg_vetoes
    );
    for (reason, count) in &summary.failures {
        println!("  failed: {reason} × {count}");
    }
    if let Some(rules) = &summary.rules {
        let fired: Vec<String> = RuleId::ALL
            .into_iter()
            .filter(|id| rules.by_rule[*id as usize] > 0)
            .map(|id| format!("{id} {:.1} %", 100.0 * rules.share(id)))
            .collect();
        println!(
            "  rules {}: changed {:.1} % of {} decisions{}{}",
            args.rules.label(),
            100.0 * rules.changed_share(),
            rules.decisions,
            if fired.is_empty() { "" } else { ": " },
            fired.join(", ")
        );
    }
    println!("  wall {:.3} s", summary.wall_s);
    let mut json = serde_json::to_value(&summary)?;
    if args.per_cell {
        let cells = eval::per_drawn_cell(&cell, &ranges, options, args.seed, &reports);
        print_per_cell(&cells, threshold);
        json["per_cell"] = serde_json::to_value(&cells)?;
        json["threshold"] = threshold.into();
        json["cells_reaching"] = eval::reaching(&cells, threshold).into();
    }
    if args.json {
        println!("{json}");
    }
    Ok(())
}

/// Each drawn cell and its success rate, then how many reach `threshold` and the lowest.
fn print_per_cell(cells: &[eval::DrawnCell], threshold: f64) {
    println!("  per drawn cell (success over its own episodes; gate ≥ {threshold}):");
    for c in cells {
        println!(
            "    cell {:>3}: bore Φ{:.1} mm, clearance {:.3} mm, depth {:.1} mm, robot ×{:.3}, \
             camera {:.0} mm at {:.1}°, noise ×{:.2}, calibration ×{:.2}: {:.4} ({} of {}){}",
            c.index,
            c.bore_diameter_mm,
            c.radial_clearance_mm,
            c.depth_mm,
            c.robot_scale,
            c.camera_distance_mm,
            c.camera_elevation_deg,
            c.noise_scale,
            c.calibration_scale,
            c.success_rate,
            c.successes,
            c.episodes,
            if c.reaches(threshold) { "" } else { "  below" },
        );
    }
    let lowest = cells
        .iter()
        .min_by(|a, b| a.success_rate.total_cmp(&b.success_rate));
    println!(
        "  {} of {} cells reach {threshold}{}",
        eval::reaching(cells, threshold),
        cells.len(),
        lowest.map_or(String::new(), |c| format!(
            "; lowest {:.4} (cell {})",
            c.success_rate, c.index
        )),
    );
}

/// A `--controller` value that names a policy file rather than a built-in controller.
fn controller_file(name: &str) -> Option<PathBuf> {
    let path = PathBuf::from(name);
    (name.ends_with(".safetensors") || path.is_file()).then_some(path)
}

fn run_policy(policy: &PathBuf, states: &PathBuf) -> Result<()> {
    let mut policy = HierarchicalPolicy::from_path(policy)
        .with_context(|| format!("--policy {}", policy.display()))?;
    let file = std::fs::File::open(states)
        .with_context(|| format!("--states {}: cannot open", states.display()))?;
    policy::run::run_states(
        &mut policy,
        std::io::BufReader::new(file),
        std::io::stdout().lock(),
    )
    .with_context(|| format!("--states {}", states.display()))?;
    Ok(())
}
