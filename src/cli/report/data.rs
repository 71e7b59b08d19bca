//! What `celld report` saves in report.json: every evaluated table cell and the learning curves,
//! all the results page is made from, so that `celld report --from report.json` makes the page
//! again without running anything.

use anyhow::{Context, Result, bail};
use assembly_cell::learning::refine::EpisodeRecord;
use assembly_cell::policy::eval::EvalSummary;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};
use std::collections::BTreeMap;
use std::path::Path;

/// A report's data (report.json).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct Report {
    /// The `celld report` command that measured it.
    pub command: String,
    /// The script that ran the command, if any.
    #[serde(default)]
    pub made_by: Option<String>,
    /// Episodes per table cell.
    pub episodes: usize,
    /// Evaluation seed.
    pub seed: u64,
    /// Robots each evaluation shared its episodes among (absent from report.json written
    /// before it was kept: [`Report::robots`] reads it from the evaluations).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robots: Option<u32>,
    /// Tables 2–4: each learned policy under each initial error and camera noise.
    pub robustness: Vec<Cell>,
    /// Every controller on phi170.
    pub table5: Vec<Cell>,
    /// Every controller on phi200.
    pub table6: Vec<Cell>,
    /// Every controller on the unseen cell files and on drawn cells.
    pub generalisation: Vec<Cell>,
    /// Every controller when the twin departs from the cell file.
    pub mismatch: Vec<Cell>,
    /// Every learned policy on Table 5's episodes with no rule (absent from report.json
    /// written before the report measured it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub without_rules: Option<Vec<Cell>>,
    /// Fig. 7's learning curves (absent from report.json written before the report kept them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curves: Option<Vec<Curve>>,
}

/// One table cell: a controller under one condition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct Cell {
    pub controller: String,
    pub condition: String,
    pub summary: Summary,
}

/// An evaluation's summary as `celld eval --json` prints it: the fields the page reads, and
/// the rest kept as they were written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct Summary {
    pub cell: String,
    pub success_rate: f64,
    /// Over the successful episodes; none when none succeeded.
    pub avg_steps: Option<f64>,
    pub avg_reward: f64,
    /// Failures by reason.
    pub failures: BTreeMap<String, usize>,
    /// How often the rules changed a learned policy's decisions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rules: Option<RuleCounts>,
    #[serde(flatten)]
    pub rest: Map<String, Value>,
}

/// `{"decisions", "changed", "by_rule": {name: count}}`, as an evaluation writes it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct RuleCounts {
    pub decisions: u64,
    pub changed: u64,
    pub by_rule: BTreeMap<String, u64>,
}

impl RuleCounts {
    /// The share of decisions any rule changed.
    pub fn changed_share(&self) -> f64 {
        self.changed as f64 / self.decisions.max(1) as f64
    }

    /// The share of decisions the rule named `name` changed (0 when it is not counted).
    pub fn share(&self, name: &str) -> f64 {
        self.by_rule.get(name).copied().unwrap_or(0) as f64 / self.decisions.max(1) as f64
    }
}

/// One learning curve of Fig. 7: the training episodes of a `--curve` file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct Curve {
    pub label: String,
    pub episodes: Vec<EpisodeRecord>,
}

impl Cell {
    /// A cell of a measured evaluation.
    pub fn measured(controller: &str, condition: &str, summary: &EvalSummary) -> Result<Cell> {
        let summary = serde_json::from_value(serde_json::to_value(summary)?)
            .context("an evaluation's summary does not read back")?;
        Ok(Cell {
            controller: controller.to_string(),
            condition: condition.to_string(),
            summary,
        })
    }
}

impl Report {
    /// Reads report.json, naming the file in any error.
    pub fn read(path: &Path) -> Result<Report> {
        let bytes = std::fs::read(path).with_context(|| format!("--from {}", path.display()))?;
        let report: Report = serde_json::from_slice(&bytes).with_context(|| {
            format!(
                "--from {}: not a report.json written by celld report",
                path.display()
            )
        })?;
        if report.table5.is_empty() {
            bail!("--from {}: no Table 5 evaluations", path.display());
        }
        Ok(report)
    }

    /// Robots each evaluation shared its episodes among: as saved, or as Table 5's first
    /// evaluation recorded it.
    pub fn robots(&self) -> Option<u32> {
        self.robots.or_else(|| {
            self.table5
                .first()?
                .summary
                .rest
                .get("kept_robots")?
                .as_u64()
                .and_then(|n| u32::try_from(n).ok())
        })
    }

    /// The learned policies of Tables 2–4, in the order first met.
    pub fn learned(&self) -> Vec<&str> {
        let mut labels: Vec<&str> = Vec::new();
        for cell in &self.robustness {
            if !labels.contains(&cell.controller.as_str()) {
                labels.push(&cell.controller);
            }
        }
        labels
    }
}
