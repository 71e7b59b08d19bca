//! The results page (docs/results.md), made from a report's data alone, each table with the
//! `celld eval` command that measures a cell of it.

use super::data::{Cell, Report, Summary};
use super::{DRAWN_NOISE_UP_TO, rules};
use assembly_cell::policy::eval::DEFAULT_KEPT_ROBOTS;
use std::fmt::Write as _;

/// Where the page's links lead, relative to the page.
pub(super) struct Links {
    /// The folder of report.json and the figures, ending in `/` (empty: the page's own).
    pub data: String,
    /// The docs folder, ending in `/` (empty: the page's own).
    pub docs: String,
    /// report.json's path as `celld report --from` takes it.
    pub data_file: String,
    /// Fig. 7's SVG files are there, to link when the data hold no curves to draw them from.
    pub figures_exist: bool,
}

/// The page, and what of it the data could not make (each a sentence, also on the page).
pub(super) fn render(report: &Report, links: &Links) -> (String, Vec<String>) {
    let mut missing = Vec::new();
    if report.without_rules.is_none() {
        missing.push(
            "\"What the networks decide\" (each learned policy without its rules): this \
             report.json was written before the report measured it"
                .to_string(),
        );
    }
    if report.curves.is_none() {
        missing.push(
            "Fig. 7's learning curves: this report.json was written before the report kept \
             them, so the figures are not drawn again and the curves' summaries are not on this page"
                .to_string(),
        );
    }
    let mut md = String::new();
    header(&mut md, report, links, &missing);
    let eval = EvalLine::new(report);
    for (title, cells, cell_flag) in [
        (
            "Table 5: every method, phi170 (simulation column)",
            &report.table5,
            "",
        ),
        (
            "Table 6: phi200 without retraining",
            &report.table6,
            " --cell cells/phi200.toml",
        ),
    ] {
        let _ = writeln!(md, "## {title}\n");
        let _ = writeln!(
            md,
            "A row: `{}`.\n",
            eval.line(&format!("METHOD{cell_flag}"))
        );
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
    robustness(&mut md, report, &eval);
    match &report.without_rules {
        Some(without) => {
            let _ = writeln!(
                md,
                "## What the networks decide: every learned policy on phi170, with its rules and without\n"
            );
            let _ = writeln!(
                md,
                "The columns without rules: `{}`; with them, Table 5's row.\n",
                eval.line("POLICY --rules none")
            );
            rules::render(&mut md, &report.table5, without);
        }
        None => {
            let _ = writeln!(md, "## What the networks decide\n");
            let _ = writeln!(
                md,
                "Not made again from this report.json, which holds no evaluation without rules. \
                 A row: `{}`.\n",
                eval.line("POLICY --rules none")
            );
        }
    }
    let all: Vec<&Cell> = report
        .table5
        .iter()
        .chain(&report.table6)
        .chain(&report.generalisation)
        .collect();
    generalisation(&mut md, &all, &eval);
    mismatch(&mut md, report, &eval);
    figure(&mut md, report, links);
    (md, missing)
}

fn header(md: &mut String, report: &Report, links: &Links, missing: &[String]) {
    let _ = writeln!(md, "# Results: the paper's tables on the twin\n");
    let made_by = match &report.made_by {
        Some(script) => format!("Made by `{script}`, which runs `{}`", report.command),
        None => format!("Made by `{}`", report.command),
    };
    let robots = match report.robots() {
        Some(0) => "a robot the cell has never seen in every episode".to_string(),
        Some(n) => format!(
            "the episodes shared among {n} robots, each kept and its drift remembered from \
             episode to episode as a cell in service does (docs/estimation.md §3a)"
        ),
        None => "the robots as each evaluation records them".to_string(),
    };
    let _ = writeln!(
        md,
        "{made_by}: {} episodes per cell, evaluation seed {}, {robots}. Success is judged on the \
         twin's true pose; avg steps count successful episodes only. Every move is allowed only \
         if its probability of contact under the estimate's uncertainty is below 1e-4 \
         (docs/estimation.md), so the cell waits until it is sure.\n",
        report.episodes, report.seed
    );
    let _ = writeln!(
        md,
        "Everything here is made from [report.json]({0}report.json), the data of that run: \
         `celld report --from {2}` writes this page again from them without running anything, \
         and each table names the `celld eval` command that measures one of its \
         cells. Longer comparisons, on 16,000 to 512,000 episodes a figure with the same seeds \
         for every controller, are kept with the commands that measured them: [where the \
         policies stand]({1}experiments/2026-12-07-81d9a69-where-the-policies-stand.md), the \
         [learning reference]({1}learning-reference.md) and the [experiment \
         records]({1}experiments/), among them [every controller with a robot new to the cell \
         in every episode]({1}experiments/2026-11-26-1c6ace4-remembering-the-robot.md).\n",
        links.data, links.docs, links.data_file
    );
    if !missing.is_empty() {
        let _ = writeln!(md, "Not made again from this report.json:\n");
        for item in missing {
            let _ = writeln!(md, "- {item}.");
        }
        let _ = writeln!(
            md,
            "\n`scripts/report.sh` measures everything again, these included (about an hour on \
             2 cores with its four training runs).\n"
        );
    }
}

/// A `celld eval` line with the report's episodes, seed and robots.
struct EvalLine {
    tail: String,
}

impl EvalLine {
    fn new(report: &Report) -> EvalLine {
        let robots = match report.robots() {
            Some(n) if n != DEFAULT_KEPT_ROBOTS => format!(" --robots {n}"),
            _ => String::new(),
        };
        EvalLine {
            tail: format!(
                " --episodes {} --seed {}{robots}",
                report.episodes, report.seed
            ),
        }
    }

    /// `celld eval --controller` followed by `what`, then the episodes, seed and robots.
    fn line(&self, what: &str) -> String {
        format!("celld eval --controller {what}{}", self.tail)
    }
}

fn robustness(md: &mut String, report: &Report, eval: &EvalLine) {
    let learned = report.learned();
    let find = |label: &str, condition: &str| {
        report
            .robustness
            .iter()
            .find(|c| c.controller == label && c.condition == condition)
            .map_or("-".to_string(), |c| {
                format!("{:.3}", c.summary.success_rate)
            })
    };
    let table = |md: &mut String, title: &str, command: &str, columns: &[String]| {
        let _ = writeln!(md, "## {title}\n");
        let _ = writeln!(md, "{command}\n");
        let _ = writeln!(md, "| policy | {} |", columns.join(" | "));
        let _ = writeln!(md, "|---|{}", "---|".repeat(columns.len()));
        for label in &learned {
            let row: Vec<String> = columns.iter().map(|c| find(label, c)).collect();
            let _ = writeln!(md, "| {label} | {} |", row.join(" | "));
        }
        let _ = writeln!(md);
    };
    let columns = |items: &[&str]| items.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    table(
        md,
        "Table 2: success under pure position or orientation errors (rows: policies, i.e. training conditions)",
        &format!(
            "A cell: `{}` (a position error: DEG 0; an orientation error: MM 0).",
            eval.line("POLICY --init-pos-mm MM --init-ori-deg DEG")
        ),
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
    table(
        md,
        "Table 3: success under combined errors",
        &format!(
            "A cell: `{}`.",
            eval.line("POLICY --init-pos-mm MM --init-ori-deg DEG")
        ),
        &combined,
    );
    let noise: Vec<String> = super::NOISE_LEVELS
        .iter()
        .map(|n| format!("noise ×{n}"))
        .collect();
    table(
        md,
        "Table 4: success by camera noise (× the spec's point σ; initial 50 mm / 1 deg)",
        &format!("A cell: `{}`.", eval.line("POLICY --noise-scale K")),
        &noise,
    );
}

/// The generalisation table: a row per controller, a column per cell (in the order first met).
fn generalisation(md: &mut String, cells: &[&Cell], eval: &EvalLine) {
    let _ = writeln!(
        md,
        "## Generalisation: every method on cells it was not trained on\n"
    );
    let drawn_robots = cells
        .iter()
        .find(|c| c.summary.rest.contains_key("drawn_cells"))
        .and_then(|c| c.summary.rest.get("kept_robots")?.as_u64());
    let _ = writeln!(
        md,
        "Each cell: success rate / avg steps (successful episodes), and the commonest failure \
         when some episodes failed. phi170 is the cell the policies were trained on; the others \
         differ in diameter, clearance, depth, holes, robot or camera placement (`cells/`). \
         The last two columns run the same number of episodes on cells drawn over the ranges \
         the product is specified for (`celld eval --randomise-cells`, \
         docs/learning-reference.md): ten episodes to a cell, each with its own camera noise \
         (0.5–2×, as training draws it; then 0.5–{DRAWN_NOISE_UP_TO}×, \
         `--randomise-noise-up-to {DRAWN_NOISE_UP_TO}`) and calibration error (0–3×).\n"
    );
    let _ = writeln!(
        md,
        "A cell file's column: `{}`. The drawn cells: `{}`, and the same with \
         `--randomise-noise-up-to {DRAWN_NOISE_UP_TO}`.\n",
        eval.line("METHOD --cell cells/NAME.toml"),
        match drawn_robots {
            Some(n) => eval.line(&format!("METHOD --randomise-cells --robots {n}")),
            None => eval.line("METHOD --randomise-cells --robots N"),
        }
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

/// The mismatch table: a row per Table 5 controller, a column per condition (in the order
/// first met).
fn mismatch(md: &mut String, report: &Report, eval: &EvalLine) {
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
    let _ = writeln!(
        md,
        "A cell: `{}`, `{}` or `{}`.\n",
        eval.line("METHOD --noise-scale K"),
        eval.line("METHOD --calibration-scale K"),
        eval.line("METHOD --fault NAME")
    );
    let mut labels: Vec<&str> = Vec::new();
    for c in &report.mismatch {
        if !labels.contains(&c.condition.as_str()) {
            labels.push(&c.condition);
        }
    }
    let _ = writeln!(md, "| method | {} |", labels.join(" | "));
    let _ = writeln!(md, "|---|{}", "---|".repeat(labels.len()));
    for controller in report.table5.iter().map(|c| &c.controller) {
        let row: Vec<String> = labels
            .iter()
            .map(|label| {
                report
                    .mismatch
                    .iter()
                    .find(|c| &c.controller == controller && c.condition == *label)
                    .map_or("-".to_string(), |c| {
                        format!(
                            "{:.3} / {} / {}",
                            c.summary.success_rate,
                            steps(&c.summary),
                            c.summary.failures.get("contact").copied().unwrap_or(0)
                        )
                    })
            })
            .collect();
        let _ = writeln!(md, "| {controller} | {} |", row.join(" | "));
    }
    let _ = writeln!(md);
    // Each evaluation once: the nominal columns repeat Table 5's.
    let mut distinct: Vec<&Cell> = Vec::new();
    for c in &report.mismatch {
        if !distinct
            .iter()
            .any(|d| d.controller == c.controller && d.summary == c.summary)
        {
            distinct.push(c);
        }
    }
    let contacts: Vec<(&Cell, usize)> = distinct
        .iter()
        .filter_map(|c| Some((*c, *c.summary.failures.get("contact")?)))
        .filter(|(_, n)| *n > 0)
        .collect();
    let total: usize = contacts.iter().map(|(_, n)| n).sum();
    let listed: Vec<String> = contacts
        .iter()
        .map(|(c, n)| format!("{} at {}: {n}", c.controller, c.condition))
        .collect();
    let _ = writeln!(
        md,
        "Episodes ended by contact over the table's {} evaluations: {total}{}.\n",
        distinct.len(),
        if listed.is_empty() {
            String::new()
        } else {
            format!(" ({})", listed.join("; "))
        }
    );
}

fn figure(md: &mut String, report: &Report, links: &Links) {
    let images = |md: &mut String| {
        for name in ["return", "success", "steps"] {
            let _ = writeln!(md, "![{name}]({}fig7_{name}.svg)\n", links.data);
        }
    };
    match &report.curves {
        Some(curves) if !curves.is_empty() => {
            let _ = writeln!(md, "## Fig. 7: learning curves\n");
            let _ = writeln!(
                md,
                "The training runs that write them are in `scripts/report.sh`.\n"
            );
            images(md);
            for curve in curves {
                let last: Vec<_> = curve.episodes.iter().rev().take(50).collect();
                let success =
                    last.iter().filter(|r| r.success).count() as f64 / last.len().max(1) as f64;
                let _ = writeln!(
                    md,
                    "- {}: {} episodes; success over the last {} training episodes {:.2}",
                    curve.label,
                    curve.episodes.len(),
                    last.len(),
                    success
                );
            }
        }
        Some(_) => {}
        None => {
            let _ = writeln!(md, "## Fig. 7: learning curves\n");
            if links.figures_exist {
                let _ = writeln!(
                    md,
                    "Not drawn again from this report.json, which holds no learning curves: the \
                     figures below are the ones `scripts/report.sh` last drew beside it, from the \
                     training runs it names.\n"
                );
                images(md);
            } else {
                let _ = writeln!(
                    md,
                    "Not drawn again from this report.json, which holds no learning curves; \
                     `scripts/report.sh` draws them with the training runs it names.\n"
                );
            }
        }
    }
}

/// The failures by reason, `reason count` comma-separated.
pub(super) fn failures(summary: &Summary) -> String {
    let counted: Vec<String> = summary
        .failures
        .iter()
        .map(|(k, v)| format!("{k} {v}"))
        .collect();
    counted.join(", ")
}

pub(super) fn steps(summary: &Summary) -> String {
    summary
        .avg_steps
        .map_or("-".to_string(), |s| format!("{s:.1}"))
}

#[cfg(test)]
mod tests {
    use super::{Links, render};
    use crate::cli::report::data::Report;
    use serde_json::json;

    fn cell(controller: &str, condition: &str, contacts: usize, wall_s: f64) -> serde_json::Value {
        let failures = if contacts > 0 {
            json!({ "contact": contacts })
        } else {
            json!({})
        };
        json!({
            "controller": controller,
            "condition": condition,
            "summary": {
                "cell": "phi170", "success_rate": 1.0 - contacts as f64 / 10.0,
                "avg_steps": 30.0, "avg_reward": 60.0, "failures": failures,
                "kept_robots": 10, "wall_s": wall_s
            }
        })
    }

    #[test]
    fn the_contacts_under_mismatch_count_each_evaluation_once() {
        let a = cell("a", "phi170", 0, 1.0);
        let b = cell("b", "phi170", 1, 2.0);
        let nominal = |c: &serde_json::Value, condition: &str| {
            let mut c = c.clone();
            c["condition"] = json!(condition);
            c
        };
        let report: Report = serde_json::from_value(json!({
            "command": "celld report", "episodes": 10, "seed": 1,
            "robustness": [], "table5": [a, b], "table6": [], "generalisation": [],
            "mismatch": [
                nominal(&a, "noise ×1"), cell("a", "noise ×4", 2, 3.0),
                nominal(&b, "noise ×1"), nominal(&b, "calibration ×1"),
                cell("b", "robot_lag", 3, 4.0)
            ],
            "without_rules": [], "curves": []
        }))
        .unwrap();
        let links = Links {
            data: "report/".into(),
            docs: String::new(),
            data_file: "docs/report/report.json".into(),
            figures_exist: false,
        };
        let (page, missing) = render(&report, &links);
        assert!(missing.is_empty());
        // a: nominal (0) and noise ×4 (2); b: nominal (1, shown twice) and robot_lag (3).
        assert!(
            page.contains(
                "over the table's 4 evaluations: 6 (a at noise ×4: 2; b at noise ×1: 1; \
                 b at robot_lag: 3)."
            ),
            "{page}"
        );
        assert!(
            page.contains("| b | 0.900 / 30.0 / 1 | - | 0.900 / 30.0 / 1 | 0.700 / 30.0 / 3 |"),
            "{page}"
        );
    }
}
