//! Service figures (docs/design.md §9), printed rather than asserted:
//! - step rows written to SQLite in batches, rows/s, each with a learned policy's proposal and
//!   two rules that changed it (every step: the most a step's record costs);
//! - what a step's record costs the control thread: building it and its telemetry JSON, with
//!   and without a proposal and rules;
//! - a real `celld serve` running expert jobs back to back: the control step's p99 alone, under
//!   1000 HTTP reads/s (and those reads' p50/p99 and errors), and with 100 telemetry
//!   subscribers plus one that never reads;
//! - the same service with 20 OPC UA clients subscribed (asyncua, PyPI): a state change's way to
//!   them (p50, p99), the control step's p99 against a quiet service, and the memory they add
//!   (`service/opcua.rs`).
//!
//! `cargo bench --bench service` (add `-- --quick` for a shorter run, and `-- opcua` or another
//! part's name for that part alone). The load generators run on
//! the same machine at nice 10, standing in for clients on other machines.

#[path = "service/opcua.rs"]
mod opcua;
mod support;

use assembly_cell::cell::StepRecord;
use assembly_cell::policy::shield::RuleId;
use assembly_cell::sim::RewardTerms;
use assembly_cell::storage::{Db, steps};
use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Read};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use support::percentile;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let quick = args.iter().any(|a| a == "--quick");
    // Names after `--` pick parts (`rows`, `record`, `http`, `opcua`); none runs them all.
    let named: Vec<&str> = args
        .iter()
        .map(String::as_str)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let runs = |part: &str| named.is_empty() || named.contains(&part);
    if runs("rows") {
        step_rows(if quick { 50_000 } else { 200_000 });
    }
    if runs("record") {
        record_cost(if quick { 20_000 } else { 200_000 });
    }
    if runs("http") {
        service(if quick { 4 } else { 40 });
    }
    if runs("opcua") {
        opcua::subscribers(if quick { 4 } else { 40 }, if quick { 10 } else { 50 });
    }
}

fn record(job_id: i64, step: u32) -> StepRecord {
    let x = f64::from(step);
    StepRecord {
        job_id,
        step,
        t_s: x * 0.25,
        state: std::array::from_fn(|i| x * 0.1 + i as f64),
        action: [0.1, -0.2, 0.3, 0.01, 0.02, -0.03],
        proposed: Some([0.15, -0.25, 0.5, 0.01, 0.02, -0.03]),
        rules: [RuleId::FullStep, RuleId::NotPastLevel]
            .into_iter()
            .collect(),
        actor: Some(assembly_cell::policy::Actor::Position),
        scale: Some(0.5),
        legs_mm: [760.0; 6],
        verdict: "allowed",
        veto_reason: None,
        reward: RewardTerms::default(),
        compute_us: 12.0,
        uncertainty: Default::default(),
        detected: None,
    }
}

fn step_rows(rows: u32) {
    let dir = tempfile::tempdir().unwrap();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let db = Db::open(&dir.path().join("bench.db")).await.unwrap();
        let job: i64 = sqlx::query_scalar(
            "INSERT INTO jobs (status, controller, seed, initial_pos_mm, initial_ori_deg)
             VALUES ('running', 'bench', 0, 50, 1) RETURNING id",
        )
        .fetch_one(&db.writer)
        .await
        .unwrap();
        let records: Vec<StepRecord> = (1..=rows).map(|s| record(job, s)).collect();
        for batch in [256usize, 1024] {
            sqlx::query("DELETE FROM steps").execute(&db.writer).await.unwrap();
            let start = Instant::now();
            for chunk in records.chunks(batch) {
                steps::insert_batch(&db, chunk).await.unwrap();
            }
            let seconds = start.elapsed().as_secs_f64();
            println!(
                "step rows into SQLite (WAL, synchronous=FULL), batches of {batch}: {rows} rows in {seconds:.2} s = {:.0} rows/s",
                f64::from(rows) / seconds
            );
        }
    });
}

/// What a step's record costs the control thread, µs: the record itself and its telemetry
/// JSON (the event sink serialises it there), p50 and p99 of `n` steps, without a proposal (the
/// expert) and with one and two rules.
fn record_cost(n: u32) {
    let expert = |step| StepRecord {
        proposed: None,
        rules: Default::default(),
        ..record(1, step)
    };
    let learned = |step| record(1, step);
    let mut p99 = Vec::new();
    for (label, make) in [
        ("without a proposal", &expert as &dyn Fn(u32) -> StepRecord),
        ("with a proposal and two rules", &learned),
    ] {
        let mut times: Vec<f64> = (1..=n)
            .map(|step| {
                let start = Instant::now();
                let json = serde_json::to_string(&make(step)).unwrap();
                std::hint::black_box(json);
                start.elapsed().as_secs_f64() * 1e6
            })
            .collect();
        let high = percentile(&mut times, 0.99);
        println!(
            "step record and its telemetry JSON, {label}: p50 {:.2} µs, p99 {high:.2} µs",
            percentile(&mut times, 0.5),
        );
        p99.push(high);
    }
    println!(
        "the proposal and rules add {:+.2} µs to the record's p99",
        p99[1] - p99[0]
    );
}

struct Server {
    child: Child,
    base: String,
    token: String,
    /// The OPC UA endpoint, when the server runs one.
    opcua_url: Option<String>,
    _dir: tempfile::TempDir,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A server with `opcua_listen` as its `opcua.listen` (`off`, or an address).
fn start_server(opcua_listen: &str) -> Server {
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_celld"))
        .args(["serve", "--listen", "127.0.0.1:0", "--db"])
        .arg(dir.path().join("celld.db"))
        .env("CELLD_STEP_PERIOD_MS", "20")
        .env("CELLD_LOG", "warn")
        .env("CELLD_OPCUA_LISTEN", opcua_listen)
        // The bundled policy's evaluation at first start would share the cores with the figures.
        .env("CELLD_EVALUATION_EPISODES", "1")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let mut opcua_url = None;
    let base = loop {
        let line = lines.next().unwrap().unwrap();
        if let Some(address) = line.strip_prefix("celld: listening on ") {
            break address.trim().to_string();
        }
    };
    for line in lines.by_ref() {
        let line = line.unwrap();
        if let Some(rest) = line.strip_prefix("celld: OPC UA ") {
            opcua_url = rest.split_whitespace().next().map(str::to_string);
        }
        if line.starts_with("celld: API ") {
            break;
        }
    }
    std::thread::spawn(move || for _ in lines.by_ref() {});
    let token = std::fs::read_to_string(dir.path().join("admin.token"))
        .unwrap()
        .trim()
        .to_string();
    Server {
        child,
        base,
        token,
        opcua_url,
        _dir: dir,
    }
}

fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .build()
        .into()
}

impl Server {
    fn post(&self, agent: &ureq::Agent, path: &str) -> Result<Value, String> {
        let request = agent
            .post(format!("{}{path}", self.base))
            .header("Authorization", format!("Bearer {}", self.token));
        Self::json(request.send_empty())
    }

    fn get(&self, agent: &ureq::Agent, path: &str) -> Result<Value, String> {
        let request = agent
            .get(format!("{}{path}", self.base))
            .header("Authorization", format!("Bearer {}", self.token));
        Self::json(request.call())
    }

    /// A 200 answer's JSON, else why not.
    fn json(
        response: Result<ureq::http::Response<ureq::Body>, ureq::Error>,
    ) -> Result<Value, String> {
        let mut response = response.map_err(|e| e.to_string())?;
        if response.status() != 200 {
            return Err(format!("status {}", response.status()));
        }
        response.body_mut().read_json().map_err(|e| e.to_string())
    }

    /// Runs `jobs` expert jobs one after another; returns every step's work time, µs.
    fn run_jobs(&self, jobs: u64, first_seed: u64) -> Vec<f64> {
        let agent = agent();
        let mut ids = Vec::new();
        for seed in first_seed..first_seed + jobs {
            let mut response = agent
                .post(format!("{}/api/jobs", self.base))
                .header("Authorization", format!("Bearer {}", self.token))
                .send_json(json!({"controller": "expert", "seed": seed}))
                .unwrap();
            let job: Value = response.body_mut().read_json().unwrap();
            ids.push(job["id"].as_i64().unwrap());
        }
        let mut compute = Vec::new();
        for id in ids {
            loop {
                let job = self.get(&agent, &format!("/api/jobs/{id}")).unwrap();
                if !matches!(job["status"].as_str(), Some("queued" | "running")) {
                    break;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
            let steps = self.get(&agent, &format!("/api/jobs/{id}/steps")).unwrap();
            compute.extend(
                steps["items"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|s| s["compute_us"].as_f64().unwrap()),
            );
        }
        compute
    }
}

/// Clients in a plant run on other machines; here they share this one, so keep them (and this
/// thread, which they inherit it from) off the CPU the server gives its control thread under
/// `control.cpu` (the same plan; with `CELLD_CONTROL_CPU=off` they may run anywhere).
fn stay_off_the_control_cpu() {
    use assembly_cell::cell::cpu;
    let choice = std::env::var("CELLD_CONTROL_CPU")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or_default();
    let available = cpu::available().unwrap();
    if let Ok(Some(placement)) = cpu::plan(&available, choice) {
        cpu::pin_current_thread(&placement.others).unwrap();
        println!(
            "server control thread on CPU {}; load generators on CPUs {:?}",
            placement.control, placement.others
        );
    }
}

/// The load generators share this machine's two cores with the server; in a plant they run
/// elsewhere. At nice 10 they take the CPU the server leaves, as remote clients would.
fn behave_as_remote_client() {
    #[cfg(target_os = "linux")]
    // SAFETY: setpriority only reads its integer arguments; it applies to this thread alone.
    unsafe {
        libc::setpriority(libc::PRIO_PROCESS, 0, 10);
    }
}

/// Reads at `rate` requests/s from `threads` threads until `stop`; latencies in ms.
fn load(
    server: &Arc<Server>,
    rate: u64,
    threads: u64,
    stop: Arc<AtomicBool>,
) -> (Vec<(f64, f64)>, u64) {
    let errors = Arc::new(AtomicU64::new(0));
    let handles: Vec<_> = (0..threads)
        .map(|t| {
            let (server, stop, errors) = (server.clone(), stop.clone(), errors.clone());
            std::thread::spawn(move || {
                behave_as_remote_client();
                let agent = agent();
                let interval = Duration::from_secs_f64(threads as f64 / rate as f64);
                let mut next = Instant::now() + interval.mul_f64(t as f64 / threads as f64);
                let mut latencies = Vec::new();
                let mut n = 0u64;
                while !stop.load(Ordering::Relaxed) {
                    std::thread::sleep(next.saturating_duration_since(Instant::now()));
                    // Two latencies: from sending (the server's answer time) and from the
                    // scheduled time (which also counts this client waking late).
                    let scheduled = next;
                    let sent = Instant::now();
                    let path = if n.is_multiple_of(2) {
                        "/api/cell"
                    } else {
                        "/api/jobs?limit=10"
                    };
                    if server.get(&agent, path).is_err() {
                        errors.fetch_add(1, Ordering::Relaxed);
                    }
                    latencies.push((
                        sent.elapsed().as_secs_f64() * 1e3,
                        scheduled.elapsed().as_secs_f64() * 1e3,
                    ));
                    next += interval;
                    n += 1;
                }
                latencies
            })
        })
        .collect();
    let mut all = Vec::new();
    for handle in handles {
        all.extend(handle.join().unwrap());
    }
    (all, errors.load(Ordering::Relaxed))
}

fn service(jobs: u64) {
    let server = Arc::new(start_server("off"));
    stay_off_the_control_cpu();
    // Warm up (first policy build, page cache).
    server.run_jobs(1, 1000);

    let mut alone = server.run_jobs(jobs, 1);
    let alone_p99 = percentile(&mut alone, 0.99);
    println!(
        "control step alone: {} steps, p50 {:.1} µs, p99 {:.1} µs",
        alone.len(),
        percentile(&mut alone, 0.5),
        alone_p99
    );

    let stop = Arc::new(AtomicBool::new(false));
    let loader = {
        let (server, stop) = (server.clone(), stop.clone());
        std::thread::spawn(move || load(&server, 1000, 4, stop))
    };
    let started = Instant::now();
    let mut loaded = server.run_jobs(jobs, 1);
    stop.store(true, Ordering::Relaxed);
    let (latencies, errors) = loader.join().unwrap();
    let seconds = started.elapsed().as_secs_f64();
    let loaded_p99 = percentile(&mut loaded, 0.99);
    let mut answered: Vec<f64> = latencies.iter().map(|l| l.0).collect();
    let mut scheduled: Vec<f64> = latencies.iter().map(|l| l.1).collect();
    println!(
        "HTTP reads during jobs: {} requests in {seconds:.1} s ({:.0}/s), {errors} errors; from sending p50 {:.2} ms, p99 {:.2} ms; from the schedule p99 {:.2} ms",
        latencies.len(),
        latencies.len() as f64 / seconds,
        percentile(&mut answered, 0.5),
        percentile(&mut answered, 0.99),
        percentile(&mut scheduled, 0.99)
    );
    println!(
        "control step under that load: p99 {loaded_p99:.1} µs ({:+.1}% against alone)",
        (loaded_p99 / alone_p99 - 1.0) * 100.0
    );

    // 100 subscribers that read everything, and one that never reads.
    let readers: Vec<_> = (0..100)
        .map(|_| {
            let url = format!(
                "{}/api/telemetry?access_token={}",
                server.base, server.token
            );
            std::thread::spawn(move || {
                behave_as_remote_client();
                let response = ureq::get(url).call().unwrap();
                let mut reader = response.into_body().into_reader();
                let mut buffer = [0u8; 8192];
                while let Ok(n) = reader.read(&mut buffer) {
                    if n == 0 {
                        break;
                    }
                }
            })
        })
        .collect();
    let stalled = std::net::TcpStream::connect(server.base.trim_start_matches("http://")).unwrap();
    use std::io::Write;
    write!(
        &stalled,
        "GET /api/telemetry?access_token={} HTTP/1.1\r\nHost: x\r\n\r\n",
        server.token
    )
    .unwrap();
    std::thread::sleep(Duration::from_millis(500));
    let mut subscribed = server.run_jobs(jobs, 1);
    let subscribed_p99 = percentile(&mut subscribed, 0.99);
    let metrics = ureq::get(format!("{}/metrics", server.base))
        .call()
        .unwrap()
        .into_body()
        .read_to_string()
        .unwrap();
    let gauge = |name: &str| {
        metrics
            .lines()
            .find(|l| l.starts_with(name))
            .map(|l| l.rsplit(' ').next().unwrap().to_string())
            .unwrap_or_default()
    };
    println!(
        "control step with {} telemetry subscribers (one never reads): p99 {subscribed_p99:.1} µs ({:+.1}% against alone); events skipped by laggards: {}",
        gauge("celld_telemetry_subscribers"),
        (subscribed_p99 / alone_p99 - 1.0) * 100.0,
        gauge("celld_telemetry_lagged_events_total"),
    );
    drop(stalled);
    drop(server);
    for reader in readers {
        let _ = reader.join();
    }
}
