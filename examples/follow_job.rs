//! Starts a job on a running `celld serve` and follows it live: subscribes to the telemetry
//! stream (`GET /api/telemetry`, Server-Sent Events), creates the job (`POST /api/jobs`,
//! operator or admin) and prints each of its steps and its end as the cell runs it.
//!
//! ```sh
//! cargo run --example follow_job -- [--controller NAME] [--seed N] [--url URL] [--token TOKEN]
//! ```
//!
//! `--controller`: `active` (default: the active policy, or the configured controller while
//! none is), a built-in controller (`expert`...), a bundled policy or `policy:<id>`. Each
//! step line gives the move made (mm, then degrees about x, y, z), the actor, the supervisor's
//! verdict and what the cell noticed; the last line is `job ID ended STATUS ...`. Exits 0 once
//! the job has ended, however it ended; non-zero when the service refuses or the stream ends
//! first.

mod client;

use anyhow::{Context as _, bail};
use client::{Client, Flags};
use serde_json::{Value, json};

const USAGE: &str = "usage: follow_job [--controller NAME] [--seed N] [--url URL] \
                     [--token TOKEN | --token-file FILE]";

fn main() {
    if let Err(error) = run() {
        eprintln!("follow_job: {error:#}");
        std::process::exit(1);
    }
}

fn run() -> anyhow::Result<()> {
    let flags = Flags::parse(&["controller", "seed"], USAGE)?;
    let controller = flags.get("controller").unwrap_or("active");
    let seed: Option<u64> = flags.parsed("seed")?;
    let client = Client::from_flags(&flags)?;

    // Subscribe first, so that no step of the job is missed. The stream's first event is the
    // cell's latches as they are now.
    let mut events = client.events("/api/telemetry")?;
    let first = events
        .next()
        .context("the telemetry stream ended before its first event")??;
    if first.name == "cell" && first.json()?["estop_latched"] == true {
        bail!("the cell is e-stopped: an operator resets it first (POST /api/cell/reset)");
    }

    let mut request = json!({"controller": controller});
    if let Some(seed) = seed {
        request["seed"] = seed.into();
    }
    let job = client.post("/api/jobs", Some(&request))?;
    let id = job["id"].as_i64().context("the new job has no id")?;
    println!(
        "job {id} {}: controller {}, seed {}",
        job["status"].as_str().unwrap_or("?"),
        job["controller"].as_str().unwrap_or("?"),
        job["seed"]
    );

    for event in events {
        let event = event?;
        match event.name.as_str() {
            "step" => {
                let step = event.json()?;
                if step["job_id"] == id {
                    println!("{}", step_line(&step));
                }
            }
            "job" => {
                let change = event.json()?;
                if change["job_id"] != id {
                    continue;
                }
                match change["status"].as_str() {
                    Some("running") => println!("job {id} running"),
                    Some(status) => {
                        let reason = change["failure_reason"]
                            .as_str()
                            .map(|r| format!(" ({r})"))
                            .unwrap_or_default();
                        println!(
                            "job {id} ended {status}{reason}: {} steps, reward {:.3}",
                            change["steps"],
                            change["reward"].as_f64().unwrap_or(f64::NAN)
                        );
                        return Ok(());
                    }
                    None => bail!("a job event without a status: {}", event.data),
                }
            }
            "lagged" => println!("(fell behind: {} events skipped)", event.json()?["skipped"]),
            "cell" if event.json()?["estop_latched"] == true => println!("e-stop"),
            _ => {}
        }
    }
    bail!("the telemetry stream ended before job {id} did")
}

/// `step 12  move (+0.000, +0.000, -0.500) mm (+0.00, +0.00, +0.00)°  position  allowed`,
/// with the veto's reason and anything the cell detected.
fn step_line(step: &Value) -> String {
    let action: Vec<f64> = (0..6)
        .map(|i| step["action"][i].as_f64().unwrap_or(f64::NAN))
        .collect();
    let mut line = format!(
        "step {:3}  t {:6.2} s  move ({:+.3}, {:+.3}, {:+.3}) mm ({:+.2}, {:+.2}, {:+.2})°  {:11}  {}",
        step["step"].as_i64().unwrap_or(-1),
        step["t_s"].as_f64().unwrap_or(f64::NAN),
        action[0],
        action[1],
        action[2],
        action[3],
        action[4],
        action[5],
        step["actor"].as_str().unwrap_or("-"),
        step["verdict"].as_str().unwrap_or("?"),
    );
    if let Some(reason) = step["veto_reason"].as_str() {
        line += &format!(" ({reason})");
    }
    if let Some(detected) = step["detected"].as_str() {
        line += &format!("  detected {detected}");
    }
    line
}
