//! The client examples (`examples/*.rs`, `examples/python/celld_client.py`) run as
//! `examples/README.md` writes them against a real `celld serve`, and what each prints is what
//! the API itself then answers: the job it followed, the evaluation it waited for, the history
//! it read.
//!
//! `cargo test` builds the examples into `target/<profile>/examples/`, beside the directory of
//! this test's binary; run alone, this test needs `cargo build --examples` first.

use crate::serve_support;

use serde_json::Value;
use serve_support::Server;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::Duration;

/// 20 ms per control step: an expert job takes about a second.
const QUICK: [(&str, &str); 1] = [("CELLD_STEP_PERIOD_MS", "20")];

/// Long enough for any example here on a loaded machine; only a hung example reaches it.
const HANG: Duration = Duration::from_secs(300);

/// The built example `name`, checked to be newer than its sources.
fn example(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("the test's own path");
    // target/<profile>/deps/examples_run-HASH → target/<profile>/examples/NAME
    let profile_dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("the test binary is in target/<profile>/deps");
    let program = profile_dir.join("examples").join(name);
    let built = std::fs::metadata(&program)
        .and_then(|m| m.modified())
        .unwrap_or_else(|_| {
            panic!(
                "{} is not built: `cargo test` builds the examples, or `cargo build --examples`",
                program.display()
            )
        });
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples");
    for source in [root.join(format!("{name}.rs")), root.join("client/mod.rs")] {
        let written = std::fs::metadata(&source).unwrap().modified().unwrap();
        assert!(
            written <= built,
            "{} is older than {}: `cargo build --examples`",
            program.display(),
            source.display()
        );
    }
    program
}

/// A temporary directory with the service's database in `data/`, so that the examples' default
/// token file, `data/admin.token`, is there when they run from the directory.
struct Cell {
    dir: tempfile::TempDir,
    server: Server,
}

impl Cell {
    fn start() -> Cell {
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("data");
        std::fs::create_dir(&data).unwrap();
        let server = Server::start(&data, &QUICK);
        Cell { dir, server }
    }

    /// `program args` run in the directory with `CELLD_URL` naming the service and no
    /// `CELLD_TOKEN`, to its end.
    fn run(&self, program: impl AsRef<std::ffi::OsStr>, args: &[&str]) -> Output {
        let mut command = Command::new(program);
        command
            .args(args)
            .current_dir(self.dir.path())
            .env("CELLD_URL", &self.server.base)
            .env_remove("CELLD_TOKEN");
        run_to_end(command)
    }

    fn job_list(&self) -> Vec<Value> {
        let (status, page) = self
            .server
            .get("/api/jobs?limit=1000", Some(&self.server.admin));
        assert_eq!(status, 200, "{page}");
        page["items"].as_array().unwrap().clone()
    }
}

/// Runs `command` to its end (killed after [`HANG`]), its output kept.
fn run_to_end(mut command: Command) -> Output {
    let child = command
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {command:?}: {e}"));
    let pid = child.id() as i32;
    let (send, receive) = std::sync::mpsc::channel();
    std::thread::spawn(move || send.send(child.wait_with_output()));
    match receive.recv_timeout(HANG) {
        Ok(output) => output.unwrap(),
        Err(_) => {
            // SAFETY: a plain signal to the child this test started.
            unsafe { libc::kill(pid, libc::SIGKILL) };
            panic!("{command:?} did not end within {HANG:?}");
        }
    }
}

/// The output's stdout as lines, after checking that it exited 0.
fn succeeded(output: &Output, what: &str) -> Vec<String> {
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{what} failed ({}):\n{stdout}\n{}",
        output.status,
        String::from_utf8_lossy(&output.stderr)
    );
    stdout.lines().map(str::to_string).collect()
}

/// The whitespace-separated word after `word` in `line`.
fn after<'a>(line: &'a str, word: &str) -> &'a str {
    let mut words = line.split_whitespace();
    words.find(|w| *w == word);
    words
        .next()
        .unwrap_or_else(|| panic!("no word after {word:?} in {line:?}"))
}

/// `job ID ended STATUS[ (REASON)]: N steps...`: the id, the status and the steps.
fn job_end(lines: &[String]) -> (i64, String, i64) {
    let last = lines.last().expect("some output");
    assert!(
        last.starts_with("job ") && last.contains(" ended "),
        "{last}"
    );
    let id = after(last, "job").parse().unwrap();
    let status = after(last, "ended").trim_end_matches(':').to_string();
    let steps = last.split(": ").nth(1).unwrap();
    let steps = steps.split_whitespace().next().unwrap().parse().unwrap();
    (id, status, steps)
}

#[test]
fn follow_job_prints_every_step_of_the_job_it_started_and_the_end_the_api_keeps() {
    let cell = Cell::start();
    let output = cell.run(
        example("follow_job"),
        &["--controller", "expert", "--seed", "3"],
    );
    let lines = succeeded(&output, "follow_job");
    let (id, status, steps) = job_end(&lines);

    // The telemetry's end can come before the storage writer's batch holding it commits.
    cell.server.wait_final(id);
    let listed = cell.job_list();
    let job = listed
        .iter()
        .find(|job| job["id"] == id)
        .unwrap_or_else(|| panic!("job {id} is not in the job list: {listed:?}"));
    assert_eq!(job["status"], status);
    assert_eq!(job["steps"], steps);
    assert_eq!(
        (&job["controller"], &job["seed"]),
        (&"expert".into(), &3.into())
    );

    // Every stored step was printed, in order, with its verdict.
    let printed: Vec<(i64, &str)> = lines
        .iter()
        .filter(|line| line.starts_with("step "))
        .map(|line| {
            let verdict = if line.contains("  vetoed") {
                "vetoed"
            } else {
                "allowed"
            };
            (after(line, "step").parse().unwrap(), verdict)
        })
        .collect();
    let stored: Vec<(i64, String)> = cell
        .server
        .steps(id)
        .iter()
        .map(|s| {
            (
                s["step"].as_i64().unwrap(),
                s["verdict"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    assert_eq!(stored.len() as i64, steps);
    assert_eq!(
        printed,
        stored
            .iter()
            .map(|(n, v)| (*n, v.as_str()))
            .collect::<Vec<_>>()
    );
}

#[test]
fn evaluate_policy_waits_for_the_evaluation_the_api_reports() {
    let cell = Cell::start();
    let file =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/policy_small.safetensors");
    let file = file.to_str().unwrap();
    let args = [
        "--file",
        file,
        "--episodes",
        "20",
        "--token",
        &cell.server.admin,
    ];
    let lines = succeeded(
        &cell.run(example("evaluate_policy"), &args),
        "evaluate_policy",
    );
    assert!(lines[0].contains(" uploaded as policy "), "{lines:?}");
    let policy_id: i64 = after(&lines[0], "policy").parse().unwrap();
    let last = lines.last().unwrap();
    let evaluation_id: i64 = after(last, "evaluation").parse().unwrap();
    assert_eq!(after(last, "policy"), policy_id.to_string());
    let printed_rate = after(last, "rate");

    let (status, policy) = cell.server.get(
        &format!("/api/policies/{policy_id}"),
        Some(&cell.server.admin),
    );
    assert_eq!(status, 200, "{policy}");
    assert_eq!(policy["name"], "policy_small", "named after the file");
    let evaluation = &policy["evaluation"];
    assert_eq!(evaluation["id"], evaluation_id);
    assert_eq!(evaluation["status"], "done");
    assert_eq!(evaluation["episodes"], 20);
    let rate = evaluation["success_rate"].as_f64().unwrap();
    assert_eq!(printed_rate, format!("{rate:.3}"));
    let stored = cell.server.get_bytes(
        &format!("/api/policies/{policy_id}/file"),
        &cell.server.admin,
    );
    assert_eq!(stored, std::fs::read(file).unwrap());

    // The same file again is the same policy, with an evaluation of its own.
    let again = succeeded(
        &cell.run(example("evaluate_policy"), &args),
        "evaluate_policy",
    );
    assert!(
        again[0].contains(&format!(" already stored as policy {policy_id} ")),
        "{again:?}"
    );
    let second: i64 = after(again.last().unwrap(), "evaluation").parse().unwrap();
    assert!(second > evaluation_id, "{again:?}");
}

#[test]
fn run_history_lists_the_jobs_and_writes_the_steps_the_api_holds() {
    let cell = Cell::start();
    let operator = cell.server.token("operator");
    let mut ids = Vec::new();
    for seed in [1, 2] {
        let job = cell.server.create_job(
            &operator,
            serde_json::json!({"controller": "expert", "seed": seed}),
        );
        ids.push(job["id"].as_i64().unwrap());
    }
    for id in &ids {
        cell.server.wait_final(*id);
    }
    let viewer = cell.server.token("viewer");
    let csv = cell.dir.path().join("steps.csv");
    let mut command = Command::new(example("run_history"));
    command
        .args(["--limit", "5", "--csv", csv.to_str().unwrap()])
        .current_dir(cell.dir.path())
        .env("CELLD_URL", &cell.server.base)
        .env("CELLD_TOKEN", &viewer);
    let lines = succeeded(&run_to_end(command), "run_history");

    let listed: Vec<i64> = cell
        .job_list()
        .iter()
        .map(|j| j["id"].as_i64().unwrap())
        .collect();
    assert_eq!(
        lines[0],
        format!("{} of {} jobs", listed.len(), listed.len())
    );
    let printed: Vec<i64> = lines
        .iter()
        .filter(|line| line.starts_with("job ") && line.contains(" seed "))
        .map(|line| after(line, "job").parse().unwrap())
        .collect();
    assert_eq!(printed, listed, "newest first");

    let newest = listed[0];
    let steps = cell.server.steps(newest).len();
    let summary = format!("job {newest}: {steps} steps stored,");
    assert!(lines.iter().any(|l| l.starts_with(&summary)), "{lines:?}");
    let (status, expected) = cell.server.get(
        &format!("/api/jobs/{newest}/steps?format=csv"),
        Some(&cell.server.admin),
    );
    assert_eq!(status, 200);
    assert_eq!(
        Value::String(std::fs::read_to_string(&csv).unwrap()),
        expected
    );

    // A token the service does not know: a non-zero exit naming the refusal.
    let refused = cell.run(example("run_history"), &["--token", "celld_not_a_token"]);
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("401"), "{stderr}");
}

#[test]
fn the_python_client_starts_a_job_through_the_description_and_reads_it_back() {
    let cell = Cell::start();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/python/celld_client.py");
    let output = cell.run("python3", &[script.to_str().unwrap(), "--seed", "4"]);
    let lines = succeeded(&output, "celld_client.py");
    let (id, status, steps) = job_end(&lines);
    let job = cell.server.job(id);
    assert_eq!(job["status"], status);
    assert_eq!(job["steps"], steps);
    assert_eq!(job["seed"], 4);
    assert_eq!(job["controller"], "expert");
    assert!(lines.last().unwrap().contains(&format!("({steps} stored)")));

    let output = cell.run("python3", &[script.to_str().unwrap(), "--operations"]);
    let operations = succeeded(&output, "celld_client.py --operations");
    let (_, document) = cell.server.get("/api/openapi.json", None);
    let described: usize = document["paths"]
        .as_object()
        .unwrap()
        .values()
        .map(|item| item.as_object().unwrap().len())
        .sum();
    assert_eq!(operations.len(), described);
}
