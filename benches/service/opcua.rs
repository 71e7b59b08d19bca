//! OPC UA clients on a real `celld serve`: `clients` asyncua sessions (PyPI; run by
//! `benches/service/opcua_subscribers.py` at nice 10, standing in for a plant's SCADA on other
//! machines) subscribed to the PackML state, the counters, the running job and the e-stop.
//! Prints the control step's p99 with them against the same service before they came and after
//! they left, the resident memory they add, and how long a state change takes to reach them:
//! from the HTTP stop or reset that makes it to each client's notification, on this machine's
//! clock.

use super::support::percentile;
use super::{Server, agent, behave_as_remote_client, start_server, stay_off_the_control_cpu};
use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

const CLIENTS: u32 = 20;
/// PackML state numbers.
const STOPPED: u32 = 2;
const IDLE: u32 = 4;

fn unix_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

/// Resident memory of process `pid`, KiB: now and its peak.
fn memory_kib(pid: u32) -> (u64, u64) {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next()?.parse().ok())
            .unwrap_or(0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// Runs the figures: `jobs` expert jobs quiet and again with the clients subscribed, then
/// `cycles` stops and resets while they watch.
pub fn subscribers(jobs: u64, cycles: u32) {
    let python = Command::new("python3")
        .args(["-c", "import asyncua"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !python {
        println!("OPC UA clients: asyncua is not installed (pip install asyncua): skipped");
        return;
    }
    let server = start_server("127.0.0.1:0");
    stay_off_the_control_cpu();
    let url = server.opcua_url.clone().expect("the OPC UA endpoint");
    server.run_jobs(1, 1000);
    let mut quiet = server.run_jobs(jobs, 1);
    let quiet_p99 = percentile(&mut quiet, 0.99);
    let (quiet_kib, _) = memory_kib(server.child.id());

    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/benches/service/opcua_subscribers.py"
    );
    let mut clients = Command::new("nice")
        .args(["-n", "10", "python3", script, "--url", &url])
        .args(["--token", &server.token, "--clients", &CLIENTS.to_string()])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .expect("start the OPC UA clients");
    let mut lines = BufReader::new(clients.stdout.take().unwrap()).lines();
    for line in lines.by_ref() {
        if line.unwrap() == "ready" {
            break;
        }
    }
    let arrivals = std::thread::spawn(move || {
        lines
            .map_while(Result::ok)
            .filter_map(|line| {
                let mut words = line.split_whitespace();
                (words.next() == Some("state")).then_some(())?;
                let state: u32 = words.next()?.parse().ok()?;
                let at: f64 = words.next()?.parse().ok()?;
                let written: f64 = words.next()?.parse().ok()?;
                Some((state, at, written))
            })
            .collect::<Vec<_>>()
    });
    let (subscribed_kib, _) = memory_kib(server.child.id());
    let mut subscribed = server.run_jobs(jobs, 1);
    let subscribed_p99 = percentile(&mut subscribed, 0.99);

    let triggers = state_changes(&server, cycles);
    let (after_kib, peak_kib) = memory_kib(server.child.id());
    drop(clients.stdin.take());
    let arrivals = arrivals.join().unwrap();
    let _ = clients.wait();
    // Quiet again once they left: the figure with them sits between two quiet ones, so drift
    // of the machine over the run is seen as such.
    let mut after = server.run_jobs(jobs, 1);
    let after_p99 = percentile(&mut after, 0.99);
    // Each arrival against the latest trigger of its state before it: the whole way, and the
    // server's part of it (to the variable's write, its source timestamp).
    let (mut latencies_ms, mut written_ms): (Vec<f64>, Vec<f64>) = arrivals
        .iter()
        .filter_map(|&(state, at, written)| {
            let sent = triggers
                .iter()
                .filter(|&&(s, t)| s == state && t <= at)
                .map(|&(_, t)| t)
                .reduce(f64::max)?;
            Some(((at - sent) * 1e3, (written - sent) * 1e3))
        })
        .unzip();
    let expected = triggers.len() * CLIENTS as usize;
    println!(
        "OPC UA: control step with {CLIENTS} subscribed clients: p99 {subscribed_p99:.1} µs against {quiet_p99:.1} µs quiet before them ({:+.1}%) and {after_p99:.1} µs after ({:+.1}%)",
        (subscribed_p99 / quiet_p99 - 1.0) * 100.0,
        (subscribed_p99 / after_p99 - 1.0) * 100.0
    );
    println!(
        "OPC UA: resident memory {:.1} MiB quiet, {:.1} MiB with the clients subscribed, {:.1} MiB after their jobs and state changes (peak {:.1} MiB): {:+.1} MiB",
        quiet_kib as f64 / 1024.0,
        subscribed_kib as f64 / 1024.0,
        after_kib as f64 / 1024.0,
        peak_kib as f64 / 1024.0,
        (after_kib.max(subscribed_kib) as f64 - quiet_kib as f64) / 1024.0
    );
    if latencies_ms.is_empty() {
        println!("OPC UA: no state change reached the clients");
        return;
    }
    println!(
        "OPC UA: a state change (HTTP stop or reset) reached the clients {} times of {expected}: p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        latencies_ms.len(),
        percentile(&mut latencies_ms, 0.5),
        percentile(&mut latencies_ms, 0.99),
        percentile(&mut latencies_ms, 1.0),
    );
    println!(
        "OPC UA: of which to the variable's write in the server: p50 {:.1} ms, p99 {:.1} ms",
        percentile(&mut written_ms, 0.5),
        percentile(&mut written_ms, 0.99),
    );
}

/// Stops and resets the cell `cycles` times, 150 ms apart; the state each made and when it
/// was asked for (unix s).
fn state_changes(server: &Server, cycles: u32) -> Vec<(u32, f64)> {
    behave_as_remote_client();
    let agent = agent();
    let mut triggers = Vec::new();
    for _ in 0..cycles {
        for (path, state) in [("/api/cell/stop", STOPPED), ("/api/cell/reset", IDLE)] {
            let at = unix_s();
            server.post(&agent, path).expect(path);
            triggers.push((state, at));
            std::thread::sleep(Duration::from_millis(150));
        }
    }
    // The last notifications' way to the clients.
    std::thread::sleep(Duration::from_millis(300));
    let _ = std::io::stdout().flush();
    triggers
}
