//! Whether a flood of idle connections keeps anyone out (docs/service.md, "Connections"),
//! printed rather than asserted. A real `celld serve` (default `http.*` settings: at most 1024
//! connections); child processes of this bench open 20,000 idle connections to it and hold
//! them. Each row gives, for a new client on a connection of its own, the p50/p99 of
//! `GET /api/health` and of an e-stop + reset pair, and the control step's p99 (its
//! `compute_us`) over expert jobs run in that state:
//! - quiet: nothing else;
//! - storm: while the 20,000 connect (no jobs: a storm lasts seconds);
//! - held: the 20,000 held (the server keeps at most its cap of them);
//! - held + evaluations: also 200 policy evaluations requested.
//!
//! `cargo bench --bench service_under_load` (`-- --quick`: fewer jobs and probes;
//! `-- --idle N`: N idle connections). The clients run on the same machine at nice 10,
//! standing in for clients on other machines.

mod support;

use serde_json::{Value, json};
use std::io::{BufRead, BufReader, ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use support::percentile;

/// Processes sharing the idle connections (each holds its share's descriptors).
const HOLDERS: usize = 4;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .map(|i| args[i + 1].clone())
    };
    if let Some(address) = arg("--hold") {
        let count = arg("--count").unwrap().parse().unwrap();
        hold(address.parse().unwrap(), count);
        return;
    }
    let quick = args.iter().any(|a| a == "--quick");
    let idle: usize = arg("--idle").map_or(20_000, |n| n.parse().unwrap());
    let (jobs, probes) = if quick { (3, 50) } else { (10, 200) };
    let limit = raise_fd_limit();
    println!("this process's file-descriptor limit: {limit}");

    let server = start_server();
    println!("celld serve at {}", server.address);
    server.run_jobs(1, 1000); // warm up
    let mut rows = Vec::new();

    let quiet = server.probe(probes, None);
    let steps = server.run_jobs(jobs, 1);
    rows.push(Row::new("quiet", quiet, steps));

    // The storm: probes run while the holders connect.
    let started = Instant::now();
    let mut holders: Vec<Holder> = (0..HOLDERS)
        .map(|i| {
            Holder::start(
                server.address,
                idle / HOLDERS + usize::from(i < idle % HOLDERS),
            )
        })
        .collect();
    let connecting = Arc::new(AtomicBool::new(true));
    let storm = {
        let (server, connecting) = (server.clone(), connecting.clone());
        std::thread::spawn(move || server.probe(usize::MAX, Some(connecting)))
    };
    let (mut connected, mut failed) = (0, 0);
    for holder in &mut holders {
        let (ok, errors) = holder.wait_connected();
        connected += ok;
        failed += errors;
    }
    connecting.store(false, Ordering::Relaxed);
    println!(
        "{connected} idle connections open in {:.1} s ({failed} failed to connect)",
        started.elapsed().as_secs_f64()
    );
    rows.push(Row::new("storm", storm.join().unwrap(), Vec::new()));

    let held = server.probe(probes, None);
    let steps = server.run_jobs(jobs, 1);
    rows.push(Row::new(&format!("{idle} held"), held, steps));

    let policy = server.bundled_policy();
    let mut started = 0;
    for seed in 0..200 {
        let (status, _) = server.call(
            "POST",
            &format!("/api/policies/{policy}/evaluate"),
            Some(json!({"episodes": 5, "seed": seed})),
        );
        started += u32::from(status == 202);
    }
    println!("evaluations started: {started} of 200");
    let busy = server.probe(probes, None);
    let steps = server.run_jobs(jobs, 1);
    rows.push(Row::new(&format!("{idle} held + evaluations"), busy, steps));

    let mut closed = 0;
    for holder in holders {
        closed += holder.finish();
    }
    println!("of {connected} idle connections, the server closed {closed} while they were held");
    println!();
    println!(
        "| state | health p50 ms | health p99 ms | e-stop+reset p50 ms | e-stop+reset p99 ms | failed | control step p99 µs |"
    );
    println!("|---|---|---|---|---|---|---|");
    for row in rows {
        row.print();
    }
}

/// Raises this process's soft RLIMIT_NOFILE to its hard limit; answers the soft limit.
fn raise_fd_limit() -> u64 {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit and setrlimit read or write only the struct they are given.
    unsafe {
        libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit);
        limit.rlim_cur = limit.rlim_max;
        if libc::setrlimit(libc::RLIMIT_NOFILE, &limit) != 0 {
            libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit);
        }
    }
    limit.rlim_cur
}

/// The clients share this machine's cores with the server; in a plant they run elsewhere.
fn behave_as_remote_client() {
    // SAFETY: setpriority only reads its integer arguments; it applies to this thread alone.
    unsafe {
        libc::setpriority(libc::PRIO_PROCESS, 0, 10);
    }
}

/// A child process's part: opens `count` idle connections, says how many opened, holds them
/// until its stdin closes, then says how many the server had closed.
fn hold(address: SocketAddr, count: usize) {
    behave_as_remote_client();
    raise_fd_limit();
    let mut streams = Vec::with_capacity(count);
    let mut failed = 0;
    for _ in 0..count {
        match TcpStream::connect_timeout(&address, Duration::from_secs(10)) {
            Ok(stream) => streams.push(stream),
            Err(_) => failed += 1,
        }
    }
    println!("connected {} {failed}", streams.len());
    std::io::stdout().flush().unwrap();
    let _ = std::io::stdin().read_to_end(&mut Vec::new());
    let mut closed = 0;
    let mut buffer = [0u8; 64];
    for stream in &mut streams {
        stream.set_nonblocking(true).unwrap();
        match stream.read(&mut buffer) {
            Err(e) if e.kind() == ErrorKind::WouldBlock => {}
            _ => closed += 1,
        }
    }
    println!("closed {closed}");
}

struct Holder {
    child: Child,
    stdin: Option<ChildStdin>,
    lines: std::io::Lines<BufReader<std::process::ChildStdout>>,
}

impl Holder {
    fn start(address: SocketAddr, count: usize) -> Holder {
        let mut child = Command::new(std::env::current_exe().unwrap())
            .args([
                "--hold",
                &address.to_string(),
                "--count",
                &count.to_string(),
            ])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let stdin = child.stdin.take();
        let lines = BufReader::new(child.stdout.take().unwrap()).lines();
        Holder {
            child,
            stdin,
            lines,
        }
    }

    fn next_numbers(&mut self, prefix: &str) -> Vec<usize> {
        let line = self.lines.next().unwrap().unwrap();
        line.strip_prefix(prefix)
            .unwrap_or_else(|| panic!("holder said `{line}`"))
            .split_whitespace()
            .map(|n| n.parse().unwrap())
            .collect()
    }

    /// (opened, failed).
    fn wait_connected(&mut self) -> (usize, usize) {
        let numbers = self.next_numbers("connected ");
        (numbers[0], numbers[1])
    }

    /// How many of its connections the server had closed.
    fn finish(mut self) -> usize {
        drop(self.stdin.take());
        let closed = self.next_numbers("closed ")[0];
        self.child.wait().unwrap();
        closed
    }
}

#[derive(Clone)]
struct Server {
    /// Kills the server when the last clone goes.
    _child: Arc<ChildGuard>,
    address: SocketAddr,
    token: String,
}

struct ChildGuard {
    child: std::sync::Mutex<Child>,
    _dir: tempfile::TempDir,
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        let mut child = self.child.lock().unwrap();
        let _ = child.kill();
        let _ = child.wait();
    }
}

fn start_server() -> Server {
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_celld"))
        .args(["serve", "--listen", "127.0.0.1:0", "--db"])
        .arg(dir.path().join("celld.db"))
        .env("CELLD_STEP_PERIOD_MS", "20")
        .env("CELLD_OPCUA_LISTEN", "off")
        .env("CELLD_LOG", "error")
        // The bundled policy's evaluation at first start would share the cores with the figures.
        .env("CELLD_EVALUATION_EPISODES", "1")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let address = loop {
        let line = lines.next().unwrap().unwrap();
        if let Some(address) = line.strip_prefix("celld: listening on http://") {
            break address.trim().parse().unwrap();
        }
    };
    std::thread::spawn(move || for _ in lines.by_ref() {});
    let token = std::fs::read_to_string(dir.path().join("admin.token"))
        .unwrap()
        .trim()
        .to_string();
    Server {
        _child: Arc::new(ChildGuard {
            child: std::sync::Mutex::new(child),
            _dir: dir,
        }),
        address,
        token,
    }
}

/// What a row's probes measured, ms.
#[derive(Default)]
struct Probes {
    health: Vec<f64>,
    estop: Vec<f64>,
    failed: usize,
}

struct Row {
    name: String,
    probes: Probes,
    steps: Vec<f64>,
}

impl Row {
    fn new(name: &str, probes: Probes, steps: Vec<f64>) -> Row {
        Row {
            name: name.to_string(),
            probes,
            steps,
        }
    }

    fn print(mut self) {
        let p = |values: &mut Vec<f64>, q: f64| {
            if values.is_empty() {
                "–".to_string()
            } else {
                format!("{:.2}", percentile(values, q))
            }
        };
        let step = if self.steps.is_empty() {
            "–".to_string()
        } else {
            format!("{:.0}", percentile(&mut self.steps, 0.99))
        };
        println!(
            "| {} | {} | {} | {} | {} | {} of {} | {step} |",
            self.name,
            p(&mut self.probes.health, 0.5),
            p(&mut self.probes.health, 0.99),
            p(&mut self.probes.estop, 0.5),
            p(&mut self.probes.estop, 0.99),
            self.probes.failed,
            self.probes.health.len() + self.probes.estop.len() + self.probes.failed,
        );
    }
}

impl Server {
    /// One request on a connection of its own (`Connection: close`), as admin: status and body.
    fn call(&self, method: &str, path: &str, body: Option<Value>) -> (u16, Value) {
        self.try_call(method, path, body)
            .unwrap_or_else(|e| panic!("{method} {path}: {e}"))
    }

    fn try_call(
        &self,
        method: &str,
        path: &str,
        body: Option<Value>,
    ) -> Result<(u16, Value), String> {
        let mut stream = TcpStream::connect_timeout(&self.address, Duration::from_secs(30))
            .map_err(|e| e.to_string())?;
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap();
        let body = body.map_or(String::new(), |b| b.to_string());
        write!(
            stream,
            "{method} {path} HTTP/1.1\r\nHost: {}\r\nAuthorization: Bearer {}\r\n\
             Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
            self.address,
            self.token,
            body.len()
        )
        .map_err(|e| e.to_string())?;
        let mut answer = Vec::new();
        stream.read_to_end(&mut answer).map_err(|e| e.to_string())?;
        let answer = String::from_utf8_lossy(&answer);
        let status = answer
            .split(' ')
            .nth(1)
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| format!("no status in `{answer}`"))?;
        let body = answer.split("\r\n\r\n").nth(1).unwrap_or_default();
        Ok((status, serde_json::from_str(body).unwrap_or(Value::Null)))
    }

    /// `count` rounds (or until `running` turns false), each a health check and an e-stop +
    /// reset pair, each on new connections, 20 ms apart.
    fn probe(&self, count: usize, running: Option<Arc<AtomicBool>>) -> Probes {
        behave_as_remote_client();
        let mut probes = Probes::default();
        for _ in 0..count {
            if running.as_ref().is_some_and(|r| !r.load(Ordering::Relaxed)) {
                break;
            }
            let start = Instant::now();
            match self.try_call("GET", "/api/health", None) {
                Ok((200, _)) => probes.health.push(start.elapsed().as_secs_f64() * 1e3),
                _ => probes.failed += 1,
            }
            let start = Instant::now();
            let stopped = self.try_call("POST", "/api/cell/estop", None);
            let reset = self.try_call("POST", "/api/cell/reset", None);
            match (stopped, reset) {
                (Ok((200, _)), Ok((200, _))) => {
                    probes.estop.push(start.elapsed().as_secs_f64() * 1e3)
                }
                _ => probes.failed += 1,
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        probes
    }

    fn bundled_policy(&self) -> i64 {
        let (status, policies) = self.call("GET", "/api/policies", None);
        assert_eq!(status, 200, "{policies}");
        policies["items"][0]["id"]
            .as_i64()
            .expect("the bundled policy")
    }

    /// Runs `jobs` expert jobs one after another; every step's `compute_us`.
    fn run_jobs(&self, jobs: u64, first_seed: u64) -> Vec<f64> {
        let mut compute = Vec::new();
        for seed in first_seed..first_seed + jobs {
            let (status, job) = self.call(
                "POST",
                "/api/jobs",
                Some(json!({"controller": "expert", "seed": seed})),
            );
            assert_eq!(status, 201, "{job}");
            let id = job["id"].as_i64().unwrap();
            loop {
                let (_, job) = self.call("GET", &format!("/api/jobs/{id}"), None);
                if !matches!(job["status"].as_str(), Some("queued" | "running")) {
                    break;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
            let (_, steps) = self.call("GET", &format!("/api/jobs/{id}/steps"), None);
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
