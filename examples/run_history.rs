//! Reads a running `celld serve`'s run history (any role): the jobs, newest first
//! (`GET /api/jobs`, filtered), one job's stored steps (`GET /api/jobs/{id}/steps`), and
//! optionally those steps as CSV (`?format=csv`) into a file; then the history summarised by
//! controller (`GET /api/stats?by=controller`).
//!
//! ```sh
//! cargo run --example run_history -- [--limit N] [--status STATUS] [--controller NAME]
//!     [--job ID] [--csv FILE] [--url URL] [--token TOKEN]
//! ```
//!
//! `--limit` defaults to 10; `--job` to the newest job listed. The first line is
//! `N of TOTAL jobs`, one line per job follows; then the job's steps: how many, the vetoes,
//! and its last step. Exits non-zero when the service refuses.

mod client;

use anyhow::Context as _;
use client::{Client, Flags, query_value};
use serde_json::Value;
use std::collections::BTreeMap;

const USAGE: &str = "usage: run_history [--limit N] [--status STATUS] [--controller NAME] \
                     [--job ID] [--csv FILE] [--url URL] [--token TOKEN | --token-file FILE]";

fn main() {
    if let Err(error) = run() {
        eprintln!("run_history: {error:#}");
        std::process::exit(1);
    }
}

fn run() -> anyhow::Result<()> {
    let flags = Flags::parse(&["limit", "status", "controller", "job", "csv"], USAGE)?;
    let limit: u32 = flags.parsed("limit")?.unwrap_or(10);
    let client = Client::from_flags(&flags)?;

    let mut query = format!("limit={limit}");
    for name in ["status", "controller"] {
        if let Some(value) = flags.get(name) {
            query += &format!("&{name}={}", query_value(value));
        }
    }
    let page = client.get(&format!("/api/jobs?{query}"))?;
    let jobs = page["items"]
        .as_array()
        .context("the job list has no items")?;
    println!("{} of {} jobs", jobs.len(), page["total"]);
    for job in jobs {
        println!("{}", job_line(job));
    }

    let id = match flags.parsed::<i64>("job")? {
        Some(id) => id,
        None => match jobs.first() {
            Some(job) => job["id"].as_i64().context("a job without an id")?,
            None => return Ok(()),
        },
    };
    let steps = client.get(&format!("/api/jobs/{id}/steps"))?;
    let steps = steps["items"]
        .as_array()
        .context("the steps have no items")?;
    let mut vetoes: BTreeMap<&str, usize> = BTreeMap::new();
    for step in steps.iter().filter(|s| s["verdict"] == "vetoed") {
        *vetoes
            .entry(step["veto_reason"].as_str().unwrap_or("?"))
            .or_default() += 1;
    }
    println!("job {id}: {} steps stored, vetoes {vetoes:?}", steps.len());
    if let Some(last) = steps.last() {
        println!(
            "  last: step {}, t {:.2} s, move [{}] (mm, deg), reward {:.3}, σ sideways {:.4} mm",
            last["step"],
            last["t_s"].as_f64().unwrap_or(f64::NAN),
            last["action"]
                .as_array()
                .into_iter()
                .flatten()
                .map(|x| format!("{:+.3}", x.as_f64().unwrap_or(f64::NAN)))
                .collect::<Vec<_>>()
                .join(", "),
            last["reward"]["total"].as_f64().unwrap_or(f64::NAN),
            last["uncertainty"]["sd_lateral_mm"]
                .as_f64()
                .unwrap_or(f64::NAN),
        );
    }
    if let Some(file) = flags.get("csv") {
        let csv = client.get_text(&format!("/api/jobs/{id}/steps?format=csv"))?;
        std::fs::write(file, &csv).with_context(|| format!("cannot write {file}"))?;
        println!(
            "job {id}: {} CSV lines written to {file}",
            csv.lines().count()
        );
    }

    let stats = client.get("/api/stats?by=controller")?;
    for group in stats["groups"].as_array().into_iter().flatten() {
        println!(
            "controller {}: {} jobs, {} finished, success rate {:.3}",
            group["key"].as_str().unwrap_or("?"),
            group["jobs"],
            group["finished"],
            group["success_rate"].as_f64().unwrap_or(f64::NAN),
        );
    }
    Ok(())
}

/// `job 7  succeeded  expert  seed 3  42 steps  reward 52.741  2026-12-07T19:32:56.678Z`.
fn job_line(job: &Value) -> String {
    let reason = job["failure_reason"]
        .as_str()
        .map(|r| format!(" ({r})"))
        .unwrap_or_default();
    format!(
        "job {}  {}{reason}  {}  seed {}  {} steps  reward {}  created {}",
        job["id"],
        job["status"].as_str().unwrap_or("?"),
        job["controller"].as_str().unwrap_or("?"),
        job["seed"],
        job["steps"],
        job["reward"]
            .as_f64()
            .map_or("-".to_string(), |r| format!("{r:.3}")),
        job["created_at"].as_str().unwrap_or("?"),
    )
}
