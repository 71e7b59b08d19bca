//! Fleet figures, printed rather than asserted, on a throwaway PostgreSQL of its own:
//! - `cells`: eight `celld serve` processes running expert jobs back to back at a 20 ms control
//!   period (twelve times the camera's rate) for two minutes, in no fleet, then all
//!   replicating into one PostgreSQL, twice over: the control step's p99 in each case, the replication lag's p99 (each cell's
//!   `celld_fleet_lag_seconds`, from a row's commit on the cell to its commit in the fleet),
//!   and whether every row arrived once;
//! - `outage`: two cells running jobs while PostgreSQL is stopped for ten minutes: whether
//!   every job completed, and how long after PostgreSQL's return everything had arrived.
//!
//! `cargo bench --bench fleet` (add `-- --quick` for a 20 s run and a 30 s outage, and
//! `-- cells` or `-- outage` for one part).

#[path = "../tests/support/fleet.rs"]
mod fleet_rows;
#[path = "../tests/support/postgres.rs"]
mod postgres;
mod support;

use serde_json::{Value, json};
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use support::percentile;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let quick = args.iter().any(|a| a == "--quick");
    let named: Vec<&str> = args
        .iter()
        .map(String::as_str)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let runs = |part: &str| named.is_empty() || named.contains(&part);
    let cluster = postgres::Postgres::start();
    if runs("cells") {
        cells(
            &cluster,
            8,
            Duration::from_secs(if quick { 20 } else { 120 }),
        );
    }
    if runs("outage") {
        outage(
            &cluster,
            2,
            Duration::from_secs(if quick { 30 } else { 600 }),
        );
    }
}

/// A `celld serve` of the bench's.
struct Cell {
    child: Child,
    base: String,
    token: String,
    db: PathBuf,
    id: String,
    _dir: tempfile::TempDir,
}

impl Cell {
    fn start(id: &str, fleet: Option<&str>) -> Cell {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("celld.db");
        let mut command = Command::new(env!("CARGO_BIN_EXE_celld"));
        command
            .args(["serve", "--listen", "127.0.0.1:0", "--db"])
            .arg(&db)
            .env("CELLD_STEP_PERIOD_MS", "20")
            .env("CELLD_LOG", "warn")
            .env("CELLD_OPCUA_LISTEN", "off")
            // Eight cells share two cores: none gets one of its own.
            .env("CELLD_CONTROL_CPU", "off")
            .env("CELLD_EVALUATION_EPISODES", "1")
            .env("CELLD_CELL_ID", id)
            .stdout(Stdio::piped());
        if let Some(url) = fleet {
            command.env("CELLD_FLEET_URL", url);
        }
        let mut child = command.spawn().unwrap();
        let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
        let base = loop {
            let line = lines.next().unwrap().unwrap();
            if let Some(address) = line.strip_prefix("celld: listening on ") {
                break address.trim().to_string();
            }
        };
        std::thread::spawn(move || for _ in lines.by_ref() {});
        let token = std::fs::read_to_string(dir.path().join("admin.token"))
            .unwrap()
            .trim()
            .to_string();
        Cell {
            child,
            base,
            token,
            db,
            id: id.to_string(),
            _dir: dir,
        }
    }

    fn get(&self, path: &str) -> String {
        ureq::get(format!("{}{path}", self.base))
            .header("Authorization", format!("Bearer {}", self.token))
            .call()
            .unwrap()
            .into_body()
            .read_to_string()
            .unwrap()
    }

    /// Runs expert jobs one after another until `until`; answers (jobs, those that succeeded).
    fn run_jobs_until(&self, until: Instant, first_seed: u64) -> (u64, u64) {
        let (mut jobs, mut succeeded) = (0, 0);
        while Instant::now() < until {
            let job: Value = ureq::post(format!("{}/api/jobs", self.base))
                .header("Authorization", format!("Bearer {}", self.token))
                .send_json(json!({"controller": "expert", "seed": first_seed + jobs}))
                .unwrap()
                .body_mut()
                .read_json()
                .unwrap();
            let path = format!("/api/jobs/{}", job["id"]);
            let status = loop {
                let job: Value = serde_json::from_str(&self.get(&path)).unwrap();
                if !matches!(job["status"].as_str(), Some("queued" | "running")) {
                    break job["status"].as_str().unwrap_or_default().to_string();
                }
                std::thread::sleep(Duration::from_millis(50));
            };
            jobs += 1;
            succeeded += u64::from(status == "succeeded");
        }
        (jobs, succeeded)
    }

    /// Every step's work time on this cell, µs, read from its database.
    fn step_times_us(&self) -> Vec<f64> {
        fleet_rows::cell_rows(&self.db, "steps", "job_id, step")
            .iter()
            .map(|s| s["compute_us"].as_f64().unwrap())
            .collect()
    }

    /// The upper bound of the bucket holding the `p`-quantile of the replication lag, s.
    fn lag_quantile_s(&self, p: f64) -> Option<f64> {
        let metrics = self.get("/metrics");
        let mut buckets: Vec<(f64, f64)> = metrics
            .lines()
            .filter_map(|line| line.strip_prefix("celld_fleet_lag_seconds_bucket{le=\""))
            .filter_map(|rest| {
                let (le, count) = rest.split_once("\"} ")?;
                Some((le.parse().ok()?, count.trim().parse().ok()?))
            })
            .collect();
        buckets.sort_by(|a, b| a.0.total_cmp(&b.0));
        let total = buckets.last()?.1;
        buckets
            .iter()
            .find(|(_, count)| *count >= p * total)
            .map(|(le, _)| *le)
    }
}

impl Drop for Cell {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Runs jobs on every cell side by side for `length`; answers each cell's (jobs, succeeded).
fn run_side_by_side(cells: &[Cell], length: Duration) -> Vec<(u64, u64)> {
    let until = Instant::now() + length;
    std::thread::scope(|scope| {
        let runs: Vec<_> = cells
            .iter()
            .map(|cell| scope.spawn(move || cell.run_jobs_until(until, 1)))
            .collect();
        runs.into_iter().map(|r| r.join().unwrap()).collect()
    })
}

fn step_p99_us(cells: &[Cell]) -> (usize, f64) {
    let mut times: Vec<f64> = cells.iter().flat_map(Cell::step_times_us).collect();
    (times.len(), percentile(&mut times, 0.99))
}

/// Two rounds of: the cells in no fleet, then in one, so that the machine's drift shows
/// beside the fleet's cost.
fn cells(cluster: &postgres::Postgres, count: usize, length: Duration) {
    let url = cluster.database("bench_cells");
    let mut p99 = [Vec::new(), Vec::new()];
    let mut lags = Vec::new();
    for round in 0..2 {
        for in_fleet in [false, true] {
            let cells: Vec<Cell> = (0..count)
                .map(|i| {
                    let id = format!("{}-{round}-{i}", if in_fleet { "cell" } else { "alone" });
                    Cell::start(&id, in_fleet.then_some(url.as_str()))
                })
                .collect();
            let jobs = run_side_by_side(&cells, length);
            let (steps, step_p99) = step_p99_us(&cells);
            println!(
                "round {round}, {count} cells {} for {length:?}: {} jobs, {steps} steps, control step p99 {step_p99:.1} µs",
                if in_fleet {
                    "in one fleet"
                } else {
                    "in no fleet"
                },
                jobs.iter().map(|j| j.0).sum::<u64>()
            );
            p99[usize::from(in_fleet)].push(step_p99);
            if in_fleet {
                lags.extend(cells.iter().filter_map(|c| c.lag_quantile_s(0.99)));
                report_arrivals(&url, &cells);
            }
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (alone, in_fleet) = (mean(&p99[0]), mean(&p99[1]));
    println!(
        "control step p99, mean of the rounds: {alone:.1} µs in no fleet, {in_fleet:.1} µs in one ({:+.1}%)",
        (in_fleet / alone - 1.0) * 100.0
    );
    println!(
        "replication lag p99 per cell and round (bucket upper bounds): {}; the worst {:.3} s",
        lags.iter()
            .map(|l| format!("{l:.3} s"))
            .collect::<Vec<_>>()
            .join(", "),
        lags.iter().copied().fold(0.0, f64::max)
    );
}

/// Waits until every cell has sent everything; says whether the fleet holds each one's
/// record exactly.
fn report_arrivals(url: &str, cells: &[Cell]) -> Duration {
    let start = Instant::now();
    let mut rows = 0;
    for cell in cells {
        fleet_rows::wait_caught_up(&cell.db, Duration::from_secs(600));
    }
    let caught_up = start.elapsed();
    let mut differing = 0;
    for cell in cells {
        match fleet_rows::compare(url, &cell.db, &cell.id) {
            Ok(compared) => rows += compared,
            Err(differences) => {
                differing += 1;
                println!("{}: the fleet's copy differs:\n{differences}", cell.id);
            }
        }
    }
    println!(
        "every cell caught up {:.1} s after the runs; {rows} rows compared one by one: {}",
        caught_up.as_secs_f64(),
        if differing == 0 {
            "all arrived, none twice".to_string()
        } else {
            format!("{differing} cells differ")
        }
    );
    caught_up
}

fn outage(cluster: &postgres::Postgres, count: usize, length: Duration) {
    let url = cluster.database("bench_outage");
    let cells: Vec<Cell> = (0..count)
        .map(|i| Cell::start(&format!("outage-{i}"), Some(&url)))
        .collect();
    run_side_by_side(&cells, Duration::from_secs(5));
    cluster.stop();
    let jobs = run_side_by_side(&cells, length);
    let backlog: i64 = cells.iter().map(|c| fleet_rows::backlog(&c.db)).sum();
    println!(
        "PostgreSQL stopped {length:?} while {count} cells ran jobs: {} jobs, {} succeeded; {backlog} rows waiting on the cells",
        jobs.iter().map(|j| j.0).sum::<u64>(),
        jobs.iter().map(|j| j.1).sum::<u64>(),
    );
    cluster.start_again();
    let caught_up = report_arrivals(&url, &cells);
    println!(
        "after PostgreSQL's return everything arrived in {:.1} s",
        caught_up.as_secs_f64()
    );
}
