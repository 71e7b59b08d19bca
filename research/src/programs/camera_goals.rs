//! The camera's goals, measured over jobs of `expert` on the reference cell, rehearsed against
//! an in-process `celld twin-server` (instant moves), seeds 1 to JOBS:
//!
//! - `streaming`: the twin-server streams captures at 30 Hz and the driver takes the newest
//!   streamed frame; after connecting the cell sits idle IDLE_S seconds (the stream keeps
//!   sending), then runs the jobs in a row. Against the same seeds with a triggered camera
//!   (`GET_POINT`, no stream). Goal: every job succeeds, mean steps within 10 % of triggered.
//! - `tracker`: `tests/drivers/pyigtl_tracker_relay.py` (pyigtl) as a live tracker in front of
//!   the streaming camera: it fits each capture's fixtures and serves their TRANSFORMs, which
//!   the driver takes streaming. Against the same seeds in the in-process twin. Goal: no job
//!   ends `camera_shift`, successes and steps as the twin's.
//!
//! `cargo run --release -p cell-research -- camera_goals
//! [streaming|tracker|both] [JOBS] [IDLE_S]`
//! (defaults: both, 100, 10).

// Shared with tests/drivers/camera_goals_smoke.rs and tests/drivers/drivers_camera_peers.rs.
#[path = "../../../tests/support/camera_jobs.rs"]
mod camera_jobs;

use camera_jobs::{PyTrackerRelay, driver_settings, run_job};

use assembly_cell::cell::job::JobStatus;
use assembly_cell::cell::{CellBackend, DriverBackend, TwinBackend};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::drivers::twin_server::{TwinServer, TwinServerOptions};
use assembly_cell::sim::judge::Judge;
use cell_research::arg;
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// The camera's stream rate in the streaming and tracker runs, Hz.
const STREAM_HZ: f64 = 30.0;

/// What a run of jobs came to.
#[derive(Default)]
struct Tally {
    label: String,
    jobs: usize,
    succeeded: usize,
    /// Failed jobs by reason.
    failures: BTreeMap<String, usize>,
    steps: u64,
    /// Steps by what they detected.
    detected: BTreeMap<String, usize>,
    /// Per seed: succeeded, steps.
    ends: Vec<(bool, u32)>,
    /// Jobs whose verdict (judged on the estimate) the twin-server's truth disagrees with.
    truth_disagrees: Option<usize>,
    seconds: f64,
}

impl Tally {
    fn mean_steps(&self) -> f64 {
        self.steps as f64 / self.jobs.max(1) as f64
    }

    fn ended(&self, reason: &str) -> usize {
        self.failures.get(reason).copied().unwrap_or(0)
    }

    /// Steps whose `detected` names a camera shift, suspected or confirmed.
    fn shift_steps(&self) -> usize {
        self.detected
            .iter()
            .filter(|(name, _)| name.starts_with("camera_shift"))
            .map(|(_, n)| n)
            .sum()
    }

    fn failures_text(&self) -> String {
        join(&self.failures)
    }

    fn detected_text(&self) -> String {
        join(&self.detected)
    }
}

fn join(counts: &BTreeMap<String, usize>) -> String {
    if counts.is_empty() {
        return "none".into();
    }
    counts
        .iter()
        .map(|(name, n)| format!("{name} {n}"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Runs `jobs` jobs (seeds 1 to `jobs`) on `backend`, with a progress line every ten jobs and
/// one for each job that fails; each verdict checked against the truth of `server` when the
/// jobs run there.
fn run_jobs(
    label: &str,
    cell: &CellConfig,
    backend: &mut dyn CellBackend,
    server: Option<&TwinServer>,
    jobs: u64,
) -> anyhow::Result<Tally> {
    let mut tally = Tally {
        label: label.into(),
        truth_disagrees: server.map(|_| 0),
        ..Tally::default()
    };
    let judge = Judge::new(cell);
    let start = Instant::now();
    for seed in 1..=jobs {
        let (end, detected) = run_job(seed, cell, backend)?;
        let succeeded = end.status == JobStatus::Succeeded;
        if let (Some(server), Some(disagrees)) = (server, tally.truth_disagrees.as_mut()) {
            let truth = judge.errors(&server.true_f_m());
            if judge.is_success(&truth) != succeeded {
                println!("  {label}: seed {seed}: the truth disagrees with the verdict: {truth:?}");
                *disagrees += 1;
            }
        }
        tally.jobs += 1;
        tally.steps += u64::from(end.steps);
        tally.ends.push((succeeded, end.steps));
        for name in detected {
            *tally.detected.entry(name).or_default() += 1;
        }
        if succeeded {
            tally.succeeded += 1;
        } else {
            let reason = end
                .failure_reason
                .unwrap_or_else(|| format!("{:?}", end.status));
            println!(
                "  {label}: seed {seed} failed ({reason}) after {} steps",
                end.steps
            );
            *tally.failures.entry(reason).or_default() += 1;
        }
        if seed % 10 == 0 || seed == jobs {
            println!(
                "  {label}: {seed}/{jobs} jobs, {} succeeded, mean {:.1} steps, {:.0} s",
                tally.succeeded,
                tally.mean_steps(),
                start.elapsed().as_secs_f64()
            );
        }
    }
    tally.seconds = start.elapsed().as_secs_f64();
    Ok(tally)
}

/// A twin-server for `cell` on loopback, streaming at `stream_hz` (0: triggered only).
fn twin_server(cell: &CellConfig, stream_hz: f64) -> anyhow::Result<TwinServer> {
    TwinServer::start(&TwinServerOptions {
        stream_hz,
        ..TwinServerOptions::loopback(cell, 0)
    })
}

fn print_table(tallies: &[&Tally]) {
    println!(
        "| run | jobs | succeeded | truth disagrees | mean steps | ended camera_shift \
         | shift steps | failures | s |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for t in tallies {
        println!(
            "| {} | {} | {} | {} | {:.1} | {} | {} | {} | {:.0} |",
            t.label,
            t.jobs,
            t.succeeded,
            t.truth_disagrees
                .map_or_else(|| "-".to_string(), |n| n.to_string()),
            t.mean_steps(),
            t.ended("camera_shift"),
            t.shift_steps(),
            t.failures_text(),
            t.seconds
        );
    }
    for t in tallies {
        println!("steps detected, {}: {}", t.label, t.detected_text());
    }
}

/// Seeds whose outcome differs between two runs of the same seeds, and the largest step
/// difference.
fn compare(a: &Tally, b: &Tally) -> (usize, u32) {
    let differ = a
        .ends
        .iter()
        .zip(&b.ends)
        .filter(|(x, y)| x.0 != y.0)
        .count();
    let largest = a
        .ends
        .iter()
        .zip(&b.ends)
        .map(|(x, y)| x.1.abs_diff(y.1))
        .max()
        .unwrap_or(0);
    (differ, largest)
}

fn met(goal: bool) -> &'static str {
    if goal { "met" } else { "NOT met" }
}

fn streaming(cell: &CellConfig, jobs: u64, idle_s: f64) -> anyhow::Result<()> {
    println!("streaming camera at {STREAM_HZ} Hz after {idle_s} s idle, against triggered:");
    let server = twin_server(cell, STREAM_HZ)?;
    let mut backend =
        DriverBackend::connect(cell, driver_settings(server.igtl, server.gcs, false), None)?;
    println!("  connected; idle {idle_s} s while the camera streams");
    std::thread::sleep(Duration::from_secs_f64(idle_s));
    let streamed = run_jobs("streaming 30 Hz", cell, &mut backend, Some(&server), jobs)?;
    drop(backend);
    let server = twin_server(cell, 0.0)?;
    let mut backend =
        DriverBackend::connect(cell, driver_settings(server.igtl, server.gcs, true), None)?;
    let triggered = run_jobs("triggered", cell, &mut backend, Some(&server), jobs)?;
    println!();
    print_table(&[&streamed, &triggered]);
    let ratio = streamed.mean_steps() / triggered.mean_steps();
    let (differ, largest) = compare(&streamed, &triggered);
    println!(
        "mean steps streaming / triggered: {ratio:.3}; outcomes differ on {differ} seeds; \
         largest step difference {largest}"
    );
    println!(
        "goal: all {jobs} succeed streaming: {}; steps within 10 % of triggered: {}",
        met(streamed.succeeded as u64 == jobs),
        met((ratio - 1.0).abs() <= 0.1)
    );
    println!();
    Ok(())
}

fn tracker(cell: &CellConfig, jobs: u64) -> anyhow::Result<()> {
    println!("pyigtl tracker relay (TRANSFORM, streaming at {STREAM_HZ} Hz), against the twin:");
    let server = twin_server(cell, STREAM_HZ)?;
    let relay = PyTrackerRelay::start(cell, server.igtl)?;
    let mut backend = DriverBackend::connect(
        cell,
        driver_settings(relay.address, server.gcs, false),
        None,
    )?;
    let fitted = run_jobs("pyigtl tracker", cell, &mut backend, Some(&server), jobs)?;
    drop(backend);
    drop(relay);
    let mut twin = TwinBackend::new(cell, None);
    let in_twin = run_jobs("in-process twin", cell, &mut twin, None, jobs)?;
    println!();
    print_table(&[&fitted, &in_twin]);
    let ratio = fitted.mean_steps() / in_twin.mean_steps();
    let (differ, largest) = compare(&fitted, &in_twin);
    println!(
        "mean steps tracker / twin: {ratio:.3}; outcomes differ on {differ} seeds; \
         largest step difference {largest}"
    );
    println!(
        "goal: no job ends camera_shift: {}; the truth agrees with every verdict: {}; \
         successes as the twin's: {}; steps within 10 % of the twin's: {}",
        met(fitted.ended("camera_shift") == 0),
        met(fitted.truth_disagrees == Some(0)),
        met(fitted.succeeded >= in_twin.succeeded),
        met((ratio - 1.0).abs() <= 0.1)
    );
    println!();
    Ok(())
}

pub fn main() -> anyhow::Result<()> {
    let which: String = arg(1, "both".to_string())?;
    let jobs: u64 = arg(2, 100)?;
    let idle_s: f64 = arg(3, 10.0)?;
    if !(idle_s.is_finite() && idle_s >= 0.0) {
        anyhow::bail!("IDLE_S must be a finite number of seconds ≥ 0, got {idle_s}");
    }
    let cell = CellConfig::reference();
    println!(
        "reference cell, expert, seeds 1 to {jobs}, twin-server with instant moves, \
         answer and frame timeouts 2 s"
    );
    match which.as_str() {
        "streaming" => streaming(&cell, jobs, idle_s),
        "tracker" => tracker(&cell, jobs),
        "both" => {
            streaming(&cell, jobs, idle_s)?;
            tracker(&cell, jobs)
        }
        other => anyhow::bail!("the first argument is streaming, tracker or both, not {other:?}"),
    }
}
