//! `celld report`: the structure of the paper's Tables 2–6 and Fig. 7, measured on our twin, as
//! Markdown, JSON and SVG.
//!
//! - Tables 2 and 3: success of each policy (a row per `--policy`, i.e. per training condition)
//!   under test conditions: pure position offsets (10/30/50 mm), pure orientation errors
//!   (3/6/9 deg), and both combined.
//! - Table 4: success by camera noise level (× the spec's point σ).
//! - Table 5: avg steps, avg reward and success of every controller on the reference cell.
//! - Table 6: the same on phi200, without retraining.
//! - Generalisation: success and avg steps of every controller on phi170, phi200 and the
//!   [`GENERALISATION_CELLS`], none of them used in training, and on cells drawn over the
//!   specified ranges (one for every ten episodes), with the camera noise as training draws it
//!   and up to four times the data sheet's.
//! - Mismatch: success, avg steps and contacts of every Table 5 controller when the twin departs
//!   from the cell file: camera noise ×0.5 to ×4, calibration error ×1 to ×3, and each injected
//!   fault (`sim::fault`).
//! - Fig. 7: learning curves (return and success, moving averages) of the `--curve` files
//!   written by `celld train td3` (td3_curve.json) and `celld train flat` (td3-flat_curve.json).

mod rules;

use super::progress::Progress;
use super::svg;
use anyhow::{Context, Result, bail};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::learning::refine::EpisodeRecord;
use assembly_cell::policy::eval::{self, EvalSummary};
use assembly_cell::policy::learned::LearnedPolicy;
use assembly_cell::policy::shield::RuleSelection;
use assembly_cell::policy::{self, ControllerFactory};
use assembly_cell::sim::randomise::CellRanges;
use assembly_cell::sim::{EnvOptions, Fault, InitialConditions, Mismatch};
use clap::Args;
use serde::Serialize;
use serde_json::json;
use std::fmt::Write as _;
use std::path::PathBuf;

#[derive(Args)]
pub struct ReportArgs {
    /// Episodes per table cell.
    #[arg(long, default_value_t = 1000)]
    episodes: usize,
    #[arg(long, default_value = "docs/report")]
    out: PathBuf,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Robots each evaluation shares its episodes among, each kept and its drift remembered
    /// (`celld eval --robots`); 0: a new robot every episode.
    #[arg(long, default_value_t = eval::DEFAULT_KEPT_ROBOTS)]
    robots: u32,
    /// Learned policies to tabulate, as LABEL=FILE (hierarchical or flat; repeatable); default:
    /// the bundled ones.
    #[arg(long = "policy")]
    policies: Vec<String>,
    /// Learning curves for Fig. 7, as LABEL=td3_curve.json or LABEL=td3-flat_curve.json
    /// (repeatable).
    #[arg(long = "curve")]
    curves: Vec<String>,
    /// The script that ran this command (e.g. scripts/report.sh), named in the report's header.
    #[arg(long = "made-by", value_name = "SCRIPT")]
    made_by: Option<String>,
}

/// One table cell: a controller under one condition.
#[derive(Serialize)]
struct Cell {
    controller: String,
    condition: String,
    summary: EvalSummary,
}

/// Makes a controller factory for a cell.
type FactoryFor = Box<dyn Fn(&CellConfig) -> Result<ControllerFactory> + Send + Sync>;

struct Controller {
    label: String,
    factory: FactoryFor,
}

fn labelled(value: &str, flag: &str) -> Result<(String, PathBuf)> {
    match value.split_once('=') {
        Some((label, path)) if !label.is_empty() && !path.is_empty() => {
            Ok((label.to_string(), PathBuf::from(path)))
        }
        _ => bail!("{flag} {value}: expected LABEL=FILE"),
    }
}

fn learned(label: String, path: PathBuf) -> Result<Controller> {
    // Checked now, before any work starts.
    let loaded = LearnedPolicy::from_path(&path)
        .with_context(|| format!("--policy {label}={}", path.display()))?
        .with_name(label.clone());
    Ok(Controller {
        label,
        factory: Box::new(move |cell| {
            let loaded = loaded.clone().with_rules(&cell.rules);
            Ok(Box::new(move || Box::new(loaded.clone())))
        }),
    })
}

fn builtin(name: &'static str) -> Controller {
    Controller {
        label: name.to_string(),
        factory: Box::new(move |cell| Ok(policy::builtin_factory(name, cell)?)),
    }
}

pub fn run(args: ReportArgs) -> Result<()> {
    if args.episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    let mut learned_policies = Vec::new();
    for value in &args.policies {
        let (label, path) = labelled(value, "--policy")?;
        learned_policies.push(learned(label, path)?);
    }
    if learned_policies.is_empty() {
        for name in policy::LEARNED_CONTROLLERS {
            learned_policies.push(builtin(name));
        }
    }
    let mut curves = Vec::new();
    for value in &args.curves {
        let (label, path) = labelled(value, "--curve")?;
        curves.push((label, read_curve(&path)?));
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("--out {}: cannot create", args.out.display()))?;
    let reference = CellConfig::reference();
    let phi200 = CellConfig::parse(include_str!("../../cells/phi200.toml"), "cells/phi200.toml")?;
    let default = InitialConditions::from_cell(&reference);
    let conditions: Vec<(String, InitialConditions, f64)> = [10.0, 30.0, 50.0]
        .iter()
        .map(|&mm| (format!("{mm} mm"), (mm, 0.0), 1.0))
        .chain(
            [3.0, 6.0, 9.0]
                .iter()
                .map(|&deg| (format!("{deg} deg"), (0.0, deg), 1.0)),
        )
        .chain([10.0, 30.0, 50.0].iter().flat_map(|&mm| {
            [3.0, 6.0, 9.0]
                .iter()
                .map(move |&deg| (format!("{mm} mm + {deg} deg"), (mm, deg), 1.0))
        }))
        .chain(NOISE_LEVELS.iter().map(|&noise| {
            (
                format!("noise ×{noise}"),
                (default.offset_mm, default.orientation_deg),
                noise,
            )
        }))
        .map(|(label, (offset_mm, orientation_deg), noise)| {
            (
                label,
                InitialConditions {
                    offset_mm,
                    orientation_deg,
                },
                noise,
            )
        })
        .collect();
    let builtins: Vec<Controller> = policy::BUILTIN_CONTROLLERS
        .iter()
        .map(|name| builtin(name))
        .collect();
    let mismatches = mismatch_conditions();
    let extra = mismatches.iter().filter(|(_, m)| !m.is_none()).count();
    let unseen = generalisation_cells()?;
    // Per controller: Tables 5 and 6, the two columns of drawn cells, the mismatches and the
    // unseen cells.
    let total = learned_policies.len() * (conditions.len() + 1)
        + (builtins.len() + learned_policies.len()) * (4 + extra + unseen.len());
    let bar = Progress::new(
        total as u64,
        "report",
        "{bar:30} {pos}/{len} evaluations {elapsed} (eta {eta}) {msg}",
    );
    let evaluate = |controller: &Controller,
                    cell: &CellConfig,
                    initial,
                    mismatch: Mismatch,
                    condition: &str|
     -> Result<Cell> {
        bar.set_message(format!(
            "{} · {} · {condition}",
            controller.label, cell.name
        ));
        let factory = (controller.factory)(cell)?;
        let options = mismatch.apply(EnvOptions {
            initial,
            kept_robots: args.robots,
            ..EnvOptions::from_cell(cell)
        });
        let (summary, _) =
            eval::evaluate(cell, options, args.episodes, args.seed, &factory, &|_| {});
        bar.inc(1);
        Ok(Cell {
            controller: controller.label.clone(),
            condition: condition.to_string(),
            summary,
        })
    };
    let mut robustness = Vec::new();
    for controller in &learned_policies {
        for (label, initial, noise) in &conditions {
            let mismatch = Mismatch {
                noise_scale: *noise,
                ..Mismatch::NONE
            };
            robustness.push(evaluate(controller, &reference, *initial, mismatch, label)?);
        }
    }
    let mut table5 = Vec::new();
    let mut table6 = Vec::new();
    let default_phi200 = InitialConditions::from_cell(&phi200);
    for controller in builtins.iter().chain(&learned_policies) {
        table5.push(evaluate(
            controller,
            &reference,
            default,
            Mismatch::NONE,
            "phi170",
        )?);
        table6.push(evaluate(
            controller,
            &phi200,
            default_phi200,
            Mismatch::NONE,
            "phi200",
        )?);
    }
    // Table 5's episodes of each learned policy with no rule: what the networks decide.
    let mut bare_reference = reference.clone();
    bare_reference.rules = bare_reference.rules.selected(&RuleSelection::None);
    let mut without_rules = Vec::new();
    for controller in &learned_policies {
        without_rules.push(evaluate(
            controller,
            &bare_reference,
            default,
            Mismatch::NONE,
            "phi170, no rules",
        )?);
    }
    // The same episodes on cells drawn over the specified ranges, ten episodes to a kept robot
    // and its cell: with the camera noise drawn as in training (up to twice the data sheet's),
    // and over the whole range the product is specified for (up to four times).
    let drawn_robots = (args.episodes / 10).max(1) as u32;
    let drawn_columns = [
        (
            format!("{drawn_robots} cells drawn around phi170"),
            CellRanges::default(),
        ),
        (
            format!("{drawn_robots} cells drawn around phi170, noise to ×4"),
            CellRanges::drawn(Some(4.0)).expect("four times is within the noise range"),
        ),
    ];
    let evaluate_drawn =
        |controller: &Controller, (drawn_column, ranges): &(String, CellRanges)| -> Cell {
            bar.set_message(format!("{} · {drawn_column}", controller.label));
            let make = |cell: &CellConfig| {
                (controller.factory)(cell).expect("Table 5 made this controller for a cell")()
            };
            let options = EnvOptions {
                initial: default,
                kept_robots: drawn_robots,
                ..EnvOptions::from_cell(&reference)
            };
            let (mut summary, _) = eval::evaluate_on_drawn_cells(
                &reference,
                ranges,
                options,
                args.episodes,
                args.seed,
                &make,
                &|_| {},
            );
            summary.cell = drawn_column.clone();
            bar.inc(1);
            Cell {
                controller: controller.label.clone(),
                condition: drawn_column.clone(),
                summary,
            }
        };
    let mut generalisation = Vec::new();
    for controller in builtins.iter().chain(&learned_policies) {
        for cell in &unseen {
            let initial = InitialConditions::from_cell(cell);
            generalisation.push(evaluate(
                controller,
                cell,
                initial,
                Mismatch::NONE,
                &cell.name,
            )?);
        }
        for column in &drawn_columns {
            generalisation.push(evaluate_drawn(controller, column));
        }
    }
    // The twin as the cell file says is Table 5's own evaluation (the same options and seed).
    let mut mismatch = Vec::new();
    for (controller, nominal_cell) in builtins.iter().chain(&learned_policies).zip(&table5) {
        for (label, conditions) in &mismatches {
            if conditions.is_none() {
                mismatch.push(Cell {
                    controller: nominal_cell.controller.clone(),
                    condition: label.clone(),
                    summary: nominal_cell.summary.clone(),
                });
            } else {
                mismatch.push(evaluate(
                    controller,
                    &reference,
                    default,
                    *conditions,
                    label,
                )?);
            }
        }
    }
    bar.finish_and_clear();
    let command = command_line(std::env::args().skip(1));
    let tables = Tables {
        robustness: &robustness,
        table5: &table5,
        table6: &table6,
        generalisation: &generalisation,
        mismatch: &mismatch,
        without_rules: &without_rules,
    };
    let markdown = render(&args, &command, &learned_policies, &tables, &curves);
    std::fs::write(args.out.join("report.md"), markdown)?;
    std::fs::write(
        args.out.join("report.json"),
        serde_json::to_vec_pretty(&json!({
            "command": command,
            "made_by": args.made_by,
            "episodes": args.episodes,
            "seed": args.seed,
            "robustness": robustness,
            "table5": table5,
            "table6": table6,
            "generalisation": generalisation,
            "mismatch": mismatch,
            "without_rules": without_rules,
        }))?,
    )?;
    if !curves.is_empty() {
        std::fs::write(
            args.out.join("fig7_return.svg"),
            svg::line_plot(
                "Return per episode (moving average of 20)",
                "episode",
                "return",
                &series(&curves, |r| r.return_),
            ),
        )?;
        std::fs::write(
            args.out.join("fig7_success.svg"),
            svg::line_plot(
                "Success (moving average of 20)",
                "episode",
                "success rate",
                &series(&curves, |r| f64::from(u8::from(r.success))),
            ),
        )?;
        std::fs::write(
            args.out.join("fig7_steps.svg"),
            svg::line_plot(
                "Steps per episode (moving average of 20)",
                "episode",
                "steps",
                &series(&curves, |r| f64::from(r.steps)),
            ),
        )?;
    }
    println!("report written to {}", args.out.display());
    Ok(())
}

/// The generalisation table's cells beyond phi170 and phi200, across the range a deployed policy
/// must cope with: diameter 100–250 mm, radial clearance 0.03–0.1 mm, depth 40–100 mm, 4–16
/// holes, another robot and another camera placement. No training run uses them.
const GENERALISATION_CELLS: [(&str, &str); 4] = [
    (
        "cells/phi100-deep.toml",
        include_str!("../../cells/phi100-deep.toml"),
    ),
    (
        "cells/phi250-shallow.toml",
        include_str!("../../cells/phi250-shallow.toml"),
    ),
    (
        "cells/phi140-robot.toml",
        include_str!("../../cells/phi140-robot.toml"),
    ),
    (
        "cells/phi210-camera.toml",
        include_str!("../../cells/phi210-camera.toml"),
    ),
];

fn generalisation_cells() -> Result<Vec<CellConfig>> {
    GENERALISATION_CELLS
        .iter()
        .map(|(path, text)| Ok(CellConfig::parse(text, path)?))
        .collect()
}

/// Camera noise levels of Table 4, × the spec's point σ.
const NOISE_LEVELS: [f64; 5] = [0.0, 0.5, 1.0, 2.0, 4.0];

/// Camera noise levels of the mismatch table, × the spec's point σ.
const MISMATCH_NOISE: [f64; 4] = [0.5, 1.0, 2.0, 4.0];

/// Calibration error levels of the mismatch table, × the cell file's.
const MISMATCH_CALIBRATION: [f64; 3] = [1.0, 2.0, 3.0];

/// The mismatch table's columns: a label and the twin's departure from the cell file.
fn mismatch_conditions() -> Vec<(String, Mismatch)> {
    let noise = MISMATCH_NOISE.iter().map(|&noise_scale| {
        (
            format!("noise ×{noise_scale}"),
            Mismatch {
                noise_scale,
                ..Mismatch::NONE
            },
        )
    });
    let calibration = MISMATCH_CALIBRATION.iter().map(|&calibration_scale| {
        (
            format!("calibration ×{calibration_scale}"),
            Mismatch {
                calibration_scale,
                ..Mismatch::NONE
            },
        )
    });
    let faults = Fault::ALL.iter().map(|&fault| {
        (
            fault.code().to_string(),
            Mismatch {
                fault: Some(fault),
                ..Mismatch::NONE
            },
        )
    });
    noise.chain(calibration).chain(faults).collect()
}

/// Episodes of an evaluation that ended in contact.
fn contacts(summary: &EvalSummary) -> usize {
    summary.failures.get("contact").copied().unwrap_or(0)
}

fn read_curve(path: &PathBuf) -> Result<Vec<EpisodeRecord>> {
    #[derive(serde::Deserialize)]
    struct Curve {
        episodes: Vec<EpisodeRecord>,
    }
    let bytes = std::fs::read(path).with_context(|| format!("--curve {}", path.display()))?;
    let curve: Curve = serde_json::from_slice(&bytes)
        .with_context(|| format!("--curve {}: not a td3_curve.json", path.display()))?;
    if curve.episodes.is_empty() {
        bail!("--curve {}: no episodes", path.display());
    }
    Ok(curve.episodes)
}

fn series(
    curves: &[(String, Vec<EpisodeRecord>)],
    value: impl Fn(&EpisodeRecord) -> f64,
) -> Vec<(String, Vec<(f64, f64)>)> {
    curves
        .iter()
        .map(|(label, records)| {
            let values: Vec<f64> = records.iter().map(&value).collect();
            let points = (0..values.len())
                .map(|i| {
                    let from = i.saturating_sub(19);
                    let window = &values[from..=i];
                    (
                        records[i].episode as f64,
                        window.iter().sum::<f64>() / window.len() as f64,
                    )
                })
                .collect();
            (label.clone(), points)
        })
        .collect()
}

/// The failures by reason, `reason count` comma-separated.
fn failures(summary: &EvalSummary) -> String {
    let counted: Vec<String> = summary
        .failures
        .iter()
        .map(|(k, v)| format!("{k} {v}"))
        .collect();
    counted.join(", ")
}

fn steps(summary: &EvalSummary) -> String {
    summary
        .avg_steps
        .map_or("-".to_string(), |s| format!("{s:.1}"))
}

/// The command as the report names it: `celld` and the arguments after the program's own path
/// (which may be a build directory), without `--made-by` (named apart), each quoted as a shell
/// reads it back. Paths are printed as given, so relative ones stay relative.
fn command_line(args: impl Iterator<Item = String>) -> String {
    let mut words = vec!["celld".to_string()];
    let mut args = args.peekable();
    while let Some(arg) = args.next() {
        if arg == "--made-by" {
            args.next();
            continue;
        }
        if arg.starts_with("--made-by=") {
            continue;
        }
        words.push(shell_quoted(&arg));
    }
    words.join(" ")
}

/// `arg` as a shell reads it back: in single quotes when it holds anything but plain word
/// characters (a `--curve` label with spaces), so the command in the report can be run again.
fn shell_quoted(arg: &str) -> String {
    let plain = |c: char| c.is_ascii_alphanumeric() || "-_./=:,+@%".contains(c);
    if !arg.is_empty() && arg.chars().all(plain) {
        arg.to_string()
    } else {
        format!("'{}'", arg.replace('\'', "'\\''"))
    }
}

/// The evaluated table cells, for [`render`].
struct Tables<'a> {
    /// Tables 2–4.
    robustness: &'a [Cell],
    table5: &'a [Cell],
    table6: &'a [Cell],
    /// Every Table 5 controller on each of [`GENERALISATION_CELLS`].
    generalisation: &'a [Cell],
    mismatch: &'a [Cell],
    /// Every learned policy on Table 5's episodes with no rule.
    without_rules: &'a [Cell],
}

fn render(
    args: &ReportArgs,
    command: &str,
    learned: &[Controller],
    tables: &Tables,
    curves: &[(String, Vec<EpisodeRecord>)],
) -> String {
    let Tables {
        robustness,
        table5,
        table6,
        generalisation,
        mismatch,
        without_rules,
    } = *tables;
    let mut md = String::new();
    let _ = writeln!(md, "# The paper's tables on our twin\n");
    let made_by = match &args.made_by {
        Some(script) => format!("Made by `{script}`, which runs `{command}`"),
        None => format!("Made by `{command}`"),
    };
    let _ = writeln!(
        md,
        "{made_by}: {} episodes per cell, evaluation seed {}, {}. Success is judged on the \
         twin's true pose; avg steps count successful episodes only.\n",
        args.episodes,
        args.seed,
        match args.robots {
            0 => "a robot the cell has never seen in every episode".to_string(),
            n => format!(
                "the episodes shared among {n} robots, each kept and its drift remembered \
                 from episode to episode as a cell in service does (docs/estimation.md §3a)"
            ),
        }
    );
    let find = |label: &str, condition: &str| {
        robustness
            .iter()
            .find(|c| c.controller == label && c.condition == condition)
            .map_or("-".to_string(), |c| {
                format!("{:.3}", c.summary.success_rate)
            })
    };
    let table = |md: &mut String, title: &str, columns: &[String]| {
        let _ = writeln!(md, "## {title}\n");
        let _ = writeln!(md, "| policy | {} |", columns.join(" | "));
        let _ = writeln!(md, "|---|{}", "---|".repeat(columns.len()));
        for controller in learned {
            let row: Vec<String> = columns.iter().map(|c| find(&controller.label, c)).collect();
            let _ = writeln!(md, "| {} | {} |", controller.label, row.join(" | "));
        }
        let _ = writeln!(md);
    };
    let columns = |items: &[&str]| items.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    table(
        &mut md,
        "Table 2: success under pure position or orientation errors (rows: policies, i.e. training conditions)",
        &columns(&["10 mm", "30 mm", "50 mm", "3 deg", "6 deg", "9 deg"]),
    );
    let combined: Vec<String> = [10, 30, 50]
        .iter()
        .flat_map(|mm| {
            [3, 6, 9]
                .iter()
                .map(move |deg| format!("{mm} mm + {deg} deg"))
        })
        .collect();
    table(&mut md, "Table 3: success under combined errors", &combined);
    let noise: Vec<String> = NOISE_LEVELS.iter().map(|n| format!("noise ×{n}")).collect();
    table(
        &mut md,
        "Table 4: success by camera noise (× the spec's point σ; initial 50 mm / 1 deg)",
        &noise,
    );
    for (title, cells) in [
        ("Table 5: every method, phi170 (simulation column)", table5),
        ("Table 6: phi200 without retraining", table6),
    ] {
        let _ = writeln!(md, "## {title}\n");
        let _ = writeln!(
            md,
            "| method | avg steps | avg reward | success | failures |"
        );
        let _ = writeln!(md, "|---|---|---|---|---|");
        for c in cells {
            let _ = writeln!(
                md,
                "| {} | {} | {:.1} | {:.3} | {} |",
                c.controller,
                steps(&c.summary),
                c.summary.avg_reward,
                c.summary.success_rate,
                failures(&c.summary)
            );
        }
        let _ = writeln!(md);
    }
    rules::render(&mut md, table5, without_rules);
    let all: Vec<&Cell> = table5.iter().chain(table6).chain(generalisation).collect();
    render_generalisation(&mut md, &all);
    render_mismatch(&mut md, table5, mismatch);
    if !curves.is_empty() {
        let _ = writeln!(md, "## Fig. 7: learning curves\n");
        let _ = writeln!(
            md,
            "![return](fig7_return.svg)\n\n![success](fig7_success.svg)\n\n![steps](fig7_steps.svg)\n"
        );
        for (label, records) in curves {
            let last: Vec<&EpisodeRecord> = records.iter().rev().take(50).collect();
            let success = last.iter().filter(|r| r.success).count() as f64 / last.len() as f64;
            let _ = writeln!(
                md,
                "- {label}: {} episodes; success over the last {} training episodes {:.2}",
                records.len(),
                last.len(),
                success
            );
        }
    }
    md
}

/// The generalisation table: a row per controller, a column per cell (in the order first met).
fn render_generalisation(md: &mut String, cells: &[&Cell]) {
    let _ = writeln!(
        md,
        "## Generalisation: every method on cells it was not trained on\n"
    );
    let _ = writeln!(
        md,
        "Each cell: success rate / avg steps (successful episodes), and the commonest failure \
         when some episodes failed. phi170 is the cell the policies were trained on; the others \
         differ in diameter, clearance, depth, holes, robot or camera placement (`cells/`). \
         The last two columns run the same number of episodes on cells drawn over the ranges \
         the product is specified for (`celld eval --randomise-cells`, docs/learning.md): ten \
         episodes to a cell, each with its own camera noise (0.5–2×, as training draws it; \
         then 0.5–4×, `--randomise-noise-up-to 4`) and calibration error (0–3×).\n"
    );
    let mut names: Vec<&str> = Vec::new();
    let mut controllers: Vec<&str> = Vec::new();
    for c in cells {
        if !names.contains(&c.summary.cell.as_str()) {
            names.push(&c.summary.cell);
        }
        if !controllers.contains(&c.controller.as_str()) {
            controllers.push(&c.controller);
        }
    }
    let _ = writeln!(md, "| method | {} |", names.join(" | "));
    let _ = writeln!(md, "|---|{}", "---|".repeat(names.len()));
    for controller in controllers {
        let row: Vec<String> = names
            .iter()
            .map(|name| {
                cells
                    .iter()
                    .find(|c| c.controller == controller && c.summary.cell == *name)
                    .map_or("-".to_string(), |c| {
                        let commonest = c.summary.failures.iter().max_by_key(|(_, n)| **n);
                        match commonest {
                            Some((reason, _)) => format!(
                                "{:.3} / {} ({reason})",
                                c.summary.success_rate,
                                steps(&c.summary)
                            ),
                            None => {
                                format!("{:.3} / {}", c.summary.success_rate, steps(&c.summary))
                            }
                        }
                    })
            })
            .collect();
        let _ = writeln!(md, "| {controller} | {} |", row.join(" | "));
    }
    let _ = writeln!(md);
}

/// The mismatch table: a row per Table 5 controller, a column per condition.
fn render_mismatch(md: &mut String, table5: &[Cell], mismatch: &[Cell]) {
    let _ = writeln!(
        md,
        "## Mismatch: every method, phi170, when the twin departs from the cell file\n"
    );
    let _ = writeln!(
        md,
        "Each cell: success rate / avg steps (successful episodes) / episodes ended by contact. \
         Noise × the spec's point σ; calibration × the cell file's calibration error (the radius \
         of the ball the robot's true joint centres are drawn in); a fault starts at a step drawn \
         in 5..=35 and lasts to the end of the episode (docs/configuration.md). Noise ×1 and \
         calibration ×1 are Table 5's phi170 column.\n"
    );
    let labels: Vec<String> = mismatch_conditions()
        .into_iter()
        .map(|(label, _)| label)
        .collect();
    let _ = writeln!(md, "| method | {} |", labels.join(" | "));
    let _ = writeln!(md, "|---|{}", "---|".repeat(labels.len()));
    for controller in table5.iter().map(|c| &c.controller) {
        let row: Vec<String> = labels
            .iter()
            .map(|label| {
                mismatch
                    .iter()
                    .find(|c| &c.controller == controller && &c.condition == label)
                    .map_or("-".to_string(), |c| {
                        format!(
                            "{:.3} / {} / {}",
                            c.summary.success_rate,
                            steps(&c.summary),
                            contacts(&c.summary)
                        )
                    })
            })
            .collect();
        let _ = writeln!(md, "| {controller} | {} |", row.join(" | "));
    }
    let _ = writeln!(md);
}

#[cfg(test)]
mod tests {
    use super::{command_line, generalisation_cells, mismatch_conditions, shell_quoted};

    #[test]
    fn the_generalisation_cells_span_the_ranges_a_deployed_policy_must_cope_with() {
        let cells = generalisation_cells().unwrap();
        let radial_clearance = |c: &assembly_cell::config::cell::CellConfig| {
            (c.bore.diameter_mm - c.shaft.diameter_mm) / 2.0
        };
        for c in &cells {
            assert!((100.0..=250.0).contains(&c.bore.diameter_mm), "{}", c.name);
            let clearance = radial_clearance(c);
            assert!(
                (0.03 - 1e-9..=0.1 + 1e-9).contains(&clearance),
                "{}",
                c.name
            );
            assert!((40.0..=100.0).contains(&c.bore.depth_mm), "{}", c.name);
            assert!((4..=16).contains(&c.bore.holes), "{}", c.name);
        }
        let span = |f: &dyn Fn(&assembly_cell::config::cell::CellConfig) -> f64| {
            let values: Vec<f64> = cells.iter().map(f).collect();
            (
                values.iter().cloned().fold(f64::INFINITY, f64::min),
                values.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
            )
        };
        // The ends of each range are covered, and the robot and the camera differ too.
        assert_eq!(span(&|c| c.bore.diameter_mm), (100.0, 250.0));
        let (least, most) = span(&radial_clearance);
        assert!((least - 0.03).abs() < 1e-9 && (most - 0.1).abs() < 1e-9);
        assert_eq!(span(&|c| c.bore.depth_mm), (40.0, 100.0));
        assert_eq!(span(&|c| f64::from(c.bore.holes)), (4.0, 16.0));
        let reference = assembly_cell::config::cell::CellConfig::reference();
        assert!(cells.iter().any(|c| c.robot != reference.robot));
        assert!(
            cells
                .iter()
                .any(|c| c.camera.position_mm != reference.camera.position_mm)
        );
    }

    #[test]
    fn a_quoted_argument_reads_back_the_same_through_a_shell() {
        for arg in [
            "--curve",
            "BC+TD3 (hierarchical)=/tmp/r/td3_curve.json",
            "it's",
            "",
            "a$b`c`\"d\"",
        ] {
            let out = std::process::Command::new("sh")
                .arg("-c")
                .arg(format!("printf '%s' {}", shell_quoted(arg)))
                .output()
                .unwrap();
            assert_eq!(String::from_utf8(out.stdout).unwrap(), arg);
        }
        assert_eq!(shell_quoted("--episodes"), "--episodes");
    }

    #[test]
    fn the_command_is_named_celld_without_the_script_it_was_made_by() {
        let args = [
            "report",
            "--made-by",
            "scripts/report.sh",
            "--curve",
            "BC+TD3 (hierarchical)=runs/report/T27/td3_curve.json",
            "--made-by=x",
        ]
        .map(String::from);
        assert_eq!(
            command_line(args.into_iter()),
            "celld report --curve 'BC+TD3 (hierarchical)=runs/report/T27/td3_curve.json'"
        );
    }

    #[test]
    fn the_mismatch_table_has_every_noise_calibration_and_fault_column() {
        let labels: Vec<String> = mismatch_conditions().into_iter().map(|(l, _)| l).collect();
        assert_eq!(
            labels,
            [
                "noise ×0.5",
                "noise ×1",
                "noise ×2",
                "noise ×4",
                "calibration ×1",
                "calibration ×2",
                "calibration ×3",
                "camera_shift",
                "occlusion",
                "frozen_camera",
                "out_of_order",
                "robot_lag",
                "robot_short",
            ]
        );
        let nominal: Vec<_> = mismatch_conditions()
            .into_iter()
            .filter(|(_, m)| m.is_none())
            .map(|(l, _)| l)
            .collect();
        assert_eq!(nominal, ["noise ×1", "calibration ×1"]);
    }
}
