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
//!
//! It writes its data (report.json, every evaluation and curve) and the figures to `--out`, and
//! the results page (docs/results.md) to `--page`, made from the data alone: `--from
//! report.json` makes the page and figures again from saved data without running anything.

mod data;
mod page;
mod rules;

use data::{Cell, Curve, Report};

use super::progress::Progress;
use super::svg;
use anyhow::{Context, Result, bail};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::learning::refine::EpisodeRecord;
use assembly_cell::policy::eval;
use assembly_cell::policy::learned::LearnedPolicy;
use assembly_cell::policy::shield::RuleSelection;
use assembly_cell::policy::{self, ControllerFactory};
use assembly_cell::sim::randomise::CellRanges;
use assembly_cell::sim::{EnvOptions, Fault, InitialConditions, Mismatch};
use clap::Args;
use std::path::{Path, PathBuf};

#[derive(Args)]
pub struct ReportArgs {
    /// Episodes per table cell.
    #[arg(long, default_value_t = 1000)]
    episodes: usize,
    /// The folder of the report's data (report.json) and figures.
    #[arg(long, default_value = "docs/report")]
    out: PathBuf,
    /// The results page, made from the data alone.
    #[arg(long, default_value = "docs/results.md")]
    page: PathBuf,
    /// Makes the page (and the figures, when the data hold the curves) again from a saved
    /// report.json, beside which the figures go, running nothing.
    #[arg(
        long,
        value_name = "REPORT_JSON",
        conflicts_with_all = ["episodes", "out", "seed", "robots", "policies", "curves", "made_by"]
    )]
    from: Option<PathBuf>,
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
    if let Some(from) = &args.from {
        let report = Report::read(from)?;
        let folder = from.parent().unwrap_or(Path::new("."));
        let missing = write_page(&report, folder, &args.page)?;
        for item in &missing {
            eprintln!("not made again: {item}");
        }
        println!("{} written from {}", args.page.display(), from.display());
        return Ok(());
    }
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
        curves.push(Curve {
            label,
            episodes: read_curve(&path)?,
        });
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
        Cell::measured(&controller.label, condition, &summary)
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
            format!("{drawn_robots} cells drawn around phi170, noise to ×{DRAWN_NOISE_UP_TO}"),
            CellRanges::drawn(Some(DRAWN_NOISE_UP_TO)).expect("within the noise range"),
        ),
    ];
    let evaluate_drawn =
        |controller: &Controller, (drawn_column, ranges): &(String, CellRanges)| -> Result<Cell> {
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
            Cell::measured(&controller.label, drawn_column, &summary)
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
            generalisation.push(evaluate_drawn(controller, column)?);
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
    let report = Report {
        command: command_line(std::env::args().skip(1)),
        made_by: args.made_by.clone(),
        episodes: args.episodes,
        seed: args.seed,
        robots: Some(args.robots),
        robustness,
        table5,
        table6,
        generalisation,
        mismatch,
        without_rules: Some(without_rules),
        curves: Some(curves),
    };
    std::fs::write(
        args.out.join("report.json"),
        serde_json::to_vec_pretty(&report)?,
    )
    .with_context(|| format!("--out {}: cannot write report.json", args.out.display()))?;
    // The page is made from the data as saved, so that `--from` makes the same page again.
    let saved = Report::read(&args.out.join("report.json"))?;
    write_page(&saved, &args.out, &args.page)?;
    println!(
        "report written to {} and {}",
        args.out.display(),
        args.page.display()
    );
    Ok(())
}

/// One of Fig. 7's figures: its file's name, title, y label and the value plotted.
type Figure = (
    &'static str,
    &'static str,
    &'static str,
    fn(&EpisodeRecord) -> f64,
);

/// Writes the page for `report` to `page`, and Fig. 7's figures to `folder` when the report
/// holds learning curves; returns what the data could not make.
fn write_page(report: &Report, folder: &Path, page: &Path) -> Result<Vec<String>> {
    if let Some(curves) = report.curves.as_ref().filter(|c| !c.is_empty()) {
        let figures: [Figure; 3] = [
            (
                "return",
                "Return per episode (moving average of 20)",
                "return",
                |r| r.return_,
            ),
            (
                "success",
                "Success (moving average of 20)",
                "success rate",
                |r| f64::from(u8::from(r.success)),
            ),
            (
                "steps",
                "Steps per episode (moving average of 20)",
                "steps",
                |r| f64::from(r.steps),
            ),
        ];
        for (name, title, y_label, value) in figures {
            let file = folder.join(format!("fig7_{name}.svg"));
            std::fs::write(
                &file,
                svg::line_plot(title, "episode", y_label, &series(curves, value)),
            )
            .with_context(|| format!("cannot write {}", file.display()))?;
        }
    }
    let page_folder = page.parent().unwrap_or(Path::new(""));
    let links = page::Links {
        data: relative_folder(page_folder, folder)?,
        docs: relative_folder(page_folder, Path::new("docs"))?,
        data_file: folder.join("report.json").display().to_string(),
        figures_exist: folder.join("fig7_return.svg").is_file(),
    };
    let (markdown, missing) = page::render(report, &links);
    if let Some(parent) = page.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("--page {}: cannot create its folder", page.display()))?;
    }
    std::fs::write(page, markdown)
        .with_context(|| format!("--page {}: cannot write", page.display()))?;
    Ok(missing)
}

/// `to` as a link from a page in `from`, ending in `/` (empty when they are the same folder).
fn relative_folder(from: &Path, to: &Path) -> Result<String> {
    let absolute = |p: &Path| -> Result<Vec<String>> {
        let p = if p.as_os_str().is_empty() {
            Path::new(".")
        } else {
            p
        };
        let mut parts: Vec<String> = Vec::new();
        for part in std::path::absolute(p)
            .with_context(|| format!("{}: no absolute path", p.display()))?
            .components()
        {
            match part {
                std::path::Component::Normal(name) => {
                    parts.push(name.to_string_lossy().into_owned())
                }
                std::path::Component::ParentDir => {
                    parts.pop();
                }
                _ => {}
            }
        }
        Ok(parts)
    };
    let (from, to) = (absolute(from)?, absolute(to)?);
    let shared = from.iter().zip(&to).take_while(|(a, b)| a == b).count();
    let mut link = "../".repeat(from.len() - shared);
    for part in &to[shared..] {
        link.push_str(part);
        link.push('/');
    }
    Ok(link)
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

/// The camera noise the last drawn-cells column draws up to, × the data sheet's.
const DRAWN_NOISE_UP_TO: f64 = 4.0;

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

fn series(curves: &[Curve], value: fn(&EpisodeRecord) -> f64) -> Vec<(String, Vec<(f64, f64)>)> {
    curves
        .iter()
        .map(
            |Curve {
                 label,
                 episodes: records,
             }| {
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
            },
        )
        .collect()
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

#[cfg(test)]
mod tests {
    use super::{
        ReportArgs, command_line, generalisation_cells, mismatch_conditions, relative_folder, run,
        shell_quoted,
    };
    use clap::Parser;
    use std::path::Path;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: ReportArgs,
    }

    fn parsed(words: &[&str]) -> ReportArgs {
        Cli::try_parse_from(std::iter::once("report").chain(words.iter().copied()))
            .unwrap()
            .args
    }

    fn read(path: &Path) -> String {
        std::fs::read_to_string(path).unwrap()
    }

    #[test]
    fn the_page_made_again_from_saved_data_is_the_page_the_run_wrote() {
        let dir = tempfile::tempdir().unwrap();
        let curve = dir.path().join("td3_curve.json");
        let episodes: Vec<String> = (0..30)
            .map(|i| {
                format!(
                    r#"{{"episode": {i}, "return": {}, "success": {}, "steps": {}}}"#,
                    f64::from(i) * 0.5 - 3.0,
                    i % 3 == 0,
                    40 - i
                )
            })
            .collect();
        std::fs::write(
            &curve,
            format!(r#"{{"episodes": [{}]}}"#, episodes.join(",")),
        )
        .unwrap();
        let out = dir.path().join("docs/report");
        let page = dir.path().join("docs/results.md");
        let (out_s, page_s) = (out.to_str().unwrap(), page.to_str().unwrap());
        let curve_arg = format!("a curve={}", curve.display());
        run(parsed(&[
            "--episodes",
            "1",
            "--out",
            out_s,
            "--page",
            page_s,
            "--curve",
            &curve_arg,
        ]))
        .unwrap();
        let first = read(&page);
        let figures: Vec<String> = ["return", "success", "steps"]
            .iter()
            .map(|name| read(&out.join(format!("fig7_{name}.svg"))))
            .collect();
        assert!(first.contains("## Table 5"), "{first}");
        assert!(first.contains("](report/fig7_return.svg)"), "{first}");
        assert!(
            first.contains(
                "- a curve: 30 episodes; success over the last 30 training episodes 0.33"
            )
        );
        assert!(!first.contains("Not made again"), "{first}");

        // Made again from the saved data, figures and all: the same page and figures.
        for name in ["return", "success", "steps"] {
            std::fs::remove_file(out.join(format!("fig7_{name}.svg"))).unwrap();
        }
        let again = dir.path().join("docs/again.md");
        let json = out.join("report.json");
        run(parsed(&[
            "--from",
            json.to_str().unwrap(),
            "--page",
            again.to_str().unwrap(),
        ]))
        .unwrap();
        assert_eq!(read(&again), first);
        for (name, figure) in ["return", "success", "steps"].iter().zip(&figures) {
            assert_eq!(&read(&out.join(format!("fig7_{name}.svg"))), figure);
        }

        // Data saved before the report kept its curves and its runs without rules: the page
        // says what it could not make, and the rest of it is the same.
        let mut value: serde_json::Value = serde_json::from_str(&read(&json)).unwrap();
        let object = value.as_object_mut().unwrap();
        object.remove("curves");
        object.remove("without_rules");
        let older = dir.path().join("older");
        std::fs::create_dir_all(&older).unwrap();
        std::fs::write(older.join("report.json"), value.to_string()).unwrap();
        let older_page = dir.path().join("docs/older.md");
        run(parsed(&[
            "--from",
            older.join("report.json").to_str().unwrap(),
            "--page",
            older_page.to_str().unwrap(),
        ]))
        .unwrap();
        let older_text = read(&older_page);
        assert!(older_text.contains("Not made again from this report.json:"));
        assert!(older_text.contains("Fig. 7's learning curves"));
        assert!(older_text.contains("\"What the networks decide\""));
        assert!(!older.join("fig7_return.svg").exists());
        let section = |text: &str, title: &str| {
            let from = text.find(title).unwrap();
            text[from..].split("\n## ").next().unwrap().to_string()
        };
        for title in [
            "## Table 2",
            "## Table 5",
            "## Generalisation",
            "## Mismatch",
        ] {
            assert_eq!(section(&older_text, title), section(&first, title));
        }
    }

    #[test]
    fn saved_data_that_is_not_a_report_is_refused_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let json = dir.path().join("report.json");
        std::fs::write(&json, r#"{"episodes": 3}"#).unwrap();
        let page = dir.path().join("results.md");
        let error = run(parsed(&[
            "--from",
            json.to_str().unwrap(),
            "--page",
            page.to_str().unwrap(),
        ]))
        .unwrap_err();
        assert!(
            format!("{error:#}").contains("not a report.json"),
            "{error:#}"
        );
        assert!(!page.exists());
        assert!(Cli::try_parse_from(["report", "--from", "r.json", "--episodes", "5"]).is_err());
    }

    #[test]
    fn a_folder_is_linked_relative_to_the_page() {
        let link = |from: &str, to: &str| relative_folder(Path::new(from), Path::new(to)).unwrap();
        assert_eq!(link("docs", "docs/report"), "report/");
        assert_eq!(link("docs", "docs"), "");
        assert_eq!(link("", "docs"), "docs/");
        assert_eq!(link("a/b", "c"), "../../c/");
        assert_eq!(link("a/b/../c", "a/d"), "../d/");
    }

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
