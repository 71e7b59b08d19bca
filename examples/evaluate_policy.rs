//! Uploads a policy file to a running `celld serve` and waits for its evaluation: registers the
//! file (`POST /api/policies?name=NAME`, admin), asks for the Table 5 evaluation on the
//! cell's twin (`POST /api/policies/{id}/evaluate`, admin) and reads the policy
//! (`GET /api/policies/{id}`) every half second, printing each change of the evaluation's
//! status (queued with its place in the work queue, running) and then its result.
//!
//! ```sh
//! cargo run --example evaluate_policy -- [--file FILE] [--name NAME] [--episodes N]
//!     [--seed S] [--noise-scale X] [--url URL] [--token TOKEN]
//! ```
//!
//! `--file` defaults to `policies/swift-cells.safetensors`; `--name` to the file's name without
//! its extension. The same bytes uploaded again are the policy already stored (a new evaluation
//! of it is still asked for). `--episodes`, `--seed` and `--noise-scale` default to the
//! service's (its `policies.evaluation_episodes`, seed 1, scale 1). The last line is
//! `evaluation E of policy P done: ...`. Exits non-zero when the service refuses, or the
//! evaluation fails.

mod client;

use anyhow::{Context as _, bail};
use client::{Client, Flags, query_value};
use serde_json::{Value, json};
use std::path::Path;
use std::time::{Duration, Instant};

const USAGE: &str = "usage: evaluate_policy [--file FILE] [--name NAME] [--episodes N] \
                     [--seed S] [--noise-scale X] [--url URL] [--token TOKEN | --token-file FILE]";

fn main() {
    if let Err(error) = run() {
        eprintln!("evaluate_policy: {error:#}");
        std::process::exit(1);
    }
}

fn run() -> anyhow::Result<()> {
    let flags = Flags::parse(&["file", "name", "episodes", "seed", "noise-scale"], USAGE)?;
    let file = Path::new(
        flags
            .get("file")
            .unwrap_or("policies/swift-cells.safetensors"),
    );
    let name = match flags.get("name") {
        Some(name) => name.to_string(),
        None => file
            .file_stem()
            .and_then(|stem| stem.to_str())
            .context("--file names no file")?
            .to_string(),
    };
    let mut request = json!({});
    if let Some(episodes) = flags.parsed::<u64>("episodes")? {
        request["episodes"] = episodes.into();
    }
    if let Some(seed) = flags.parsed::<u64>("seed")? {
        request["seed"] = seed.into();
    }
    if let Some(scale) = flags.parsed::<f64>("noise-scale")? {
        request["noise_scale"] = scale.into();
    }
    let client = Client::from_flags(&flags)?;
    let bytes = std::fs::read(file).with_context(|| format!("cannot read {}", file.display()))?;

    let (status, policy) = client.post_bytes(
        &format!("/api/policies?name={}", query_value(&name)),
        &bytes,
    )?;
    let id = policy["id"].as_i64().context("the policy has no id")?;
    let stored = if status == 201 {
        "uploaded as"
    } else {
        "already stored as"
    };
    println!(
        "{} ({} bytes) {stored} policy {id} `{}` ({}), sha256 {}",
        file.display(),
        bytes.len(),
        policy["name"].as_str().unwrap_or("?"),
        policy["status"].as_str().unwrap_or("?"),
        policy["sha256"].as_str().unwrap_or("?"),
    );

    let evaluation = client.post(&format!("/api/policies/{id}/evaluate"), Some(&request))?;
    let evaluation_id = evaluation["id"].clone();
    println!(
        "evaluation {evaluation_id} of policy {id}: {} episodes, seed {}, noise ×{}",
        evaluation["episodes"], evaluation["seed"], evaluation["noise_scale"]
    );

    let start = Instant::now();
    let mut last = String::new();
    loop {
        let policy = client.get(&format!("/api/policies/{id}"))?;
        let evaluation = &policy["evaluation"];
        if evaluation["id"] != evaluation_id {
            bail!(
                "policy {id}'s latest evaluation is now {}, asked for after {evaluation_id}",
                evaluation["id"]
            );
        }
        let status = evaluation["status"].as_str().unwrap_or("?");
        let now = match status {
            "queued" => format!(
                "queued, place {} in the work queue",
                evaluation["queue_position"]
            ),
            other => other.to_string(),
        };
        if now != last {
            println!("{:6.1} s  {now}", start.elapsed().as_secs_f64());
            last = now;
        }
        match status {
            "queued" | "running" => std::thread::sleep(Duration::from_millis(500)),
            "done" => {
                println!("{}", result_line(id, evaluation));
                return Ok(());
            }
            _ => bail!(
                "evaluation {evaluation_id} of policy {id} ended {status}: {}",
                evaluation["error"].as_str().unwrap_or("no reason given")
            ),
        }
    }
}

/// `evaluation 3 of policy 2 done: success rate 0.950 of 200 episodes, 35.2 steps on
/// average (successes), failures {"contact": 10}`.
fn result_line(id: i64, evaluation: &Value) -> String {
    let steps = evaluation["avg_steps"]
        .as_f64()
        .map_or("no success".to_string(), |s| {
            format!("{s:.1} steps on average (successes)")
        });
    format!(
        "evaluation {} of policy {id} done: success rate {:.3} of {} episodes, {steps}, \
         failures {}, rules {}, cell {}",
        evaluation["id"],
        evaluation["success_rate"].as_f64().unwrap_or(f64::NAN),
        evaluation["episodes"],
        evaluation["failures"],
        evaluation["rules"].as_str().unwrap_or("?"),
        evaluation["cell_hash"].as_str().unwrap_or("?"),
    )
}
