//! Background work under a burst: evaluations and training runs wait in one bounded queue
//! behind `work.concurrency`, a full queue refuses with 429, the e-stop answers meanwhile, and
//! SIGTERM ends the process within the 10 s docs/service.md promises with every unfinished
//! piece marked failed.

use crate::serve_support::Server;
use serde_json::{Value, json};
use std::path::Path;
use std::time::Duration;

/// A training run that goes on until cancelled (tiny networks, endless TD3).
fn endless_training() -> Value {
    json!({
        "part": "all",
        "seed": 5,
        "episodes": 100_000,
        "record": 12,
        "settings": {"actor_width": 16, "bc_epochs": 3, "bc_orientation_epochs": 3,
                     "lstm_hidden": 8, "lstm_epochs": 3, "eval_every": 0, "eval_episodes": 2,
                     "polish_td3_episodes": 100_000}
    })
}

fn ended(status: &Value) -> bool {
    !matches!(status.as_str(), Some("queued" | "running"))
}

/// Waits for the bundled policy's evaluation at first start to end, so the queue is empty.
fn bundled_evaluated(server: &Server) {
    server.poll("/api/policies/1", "ended its evaluation", LONG, |p| {
        ended(&p["evaluation"]["status"])
    });
}

const LONG: Duration = Duration::from_secs(120);

/// A POST answered with its status, `Retry-After` and JSON body.
fn post(server: &Server, path: &str, body: Value) -> (u16, Option<u64>, Value) {
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .http_status_as_error(false)
        .build()
        .into();
    let mut response = agent
        .post(format!("{}{path}", server.base))
        .header("Authorization", format!("Bearer {}", server.admin))
        .send_json(body)
        .expect("the server answers");
    let retry_after = response
        .headers()
        .get("retry-after")
        .map(|v| v.to_str().unwrap().parse().expect("Retry-After in seconds"));
    let body = response.body_mut().read_json().unwrap_or(Value::Null);
    (response.status().as_u16(), retry_after, body)
}

/// The database file read from beside the running server (SQLite's WAL lets a second process
/// read), through a runtime of the test's own.
struct Rows {
    runtime: tokio::runtime::Runtime,
    pool: sqlx::SqlitePool,
}

impl Rows {
    fn open(path: &Path) -> Rows {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        // Read-write but only read: a read-only connection cannot open a WAL database whose
        // server has stopped and removed its shared-memory file.
        let options = sqlx::sqlite::SqliteConnectOptions::new().filename(path);
        let pool = runtime
            .block_on(
                sqlx::sqlite::SqlitePoolOptions::new()
                    .max_connections(1)
                    .connect_with(options),
            )
            .expect("the database opens");
        Rows { runtime, pool }
    }

    /// `(id, status, error)` of every row of `table` (`policy_evaluations`, `training_runs`).
    fn statuses(&self, table: &str) -> Vec<(i64, String, Option<String>)> {
        let sql = format!("SELECT id, status, error FROM {table} ORDER BY id");
        self.runtime
            .block_on(sqlx::query_as(&sql).fetch_all(&self.pool))
            .unwrap()
    }

    /// Evaluations and training runs `running` now, read in one statement.
    fn running(&self) -> i64 {
        self.runtime
            .block_on(
                sqlx::query_scalar(
                    "SELECT (SELECT count(*) FROM policy_evaluations WHERE status = 'running')
                          + (SELECT count(*) FROM training_runs WHERE status = 'running')",
                )
                .fetch_one(&self.pool),
            )
            .unwrap()
    }
}

#[test]
fn a_burst_of_evaluations_waits_in_a_bounded_queue_and_the_estop_still_answers() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(
        dir.path(),
        &[
            ("CELLD_WORK_CONCURRENCY", "2"),
            ("CELLD_WORK_QUEUE_LENGTH", "6"),
        ],
    );
    bundled_evaluated(&server);
    let rows = Rows::open(&server.db);

    // Two runs take both places until cancelled.
    let mut blockers = Vec::new();
    for _ in 0..2 {
        let (status, _, run) = post(&server, "/api/training", endless_training());
        assert_eq!(status, 202, "{run}");
        assert_eq!(run["status"], "running", "{run}");
        assert_eq!(run["queue_position"], Value::Null);
        blockers.push(run["id"].as_i64().unwrap());
    }

    // 30 evaluations and a training run asked for at once: six places wait, in order, shared
    // by both kinds; every one past them is refused naming the limit.
    let (mut accepted, mut refused) = (Vec::new(), 0);
    let mut queued_run = None;
    for seed in 0..30 {
        if seed == 3 {
            let (status, _, run) = post(&server, "/api/training", endless_training());
            assert_eq!(status, 202, "{run}");
            assert_eq!(
                (&run["status"], &run["queue_position"]),
                (&json!("queued"), &json!(4))
            );
            queued_run = run["id"].as_i64();
        }
        let (status, retry_after, answer) = post(
            &server,
            "/api/policies/1/evaluate",
            json!({"episodes": 8, "seed": seed}),
        );
        match status {
            202 => {
                assert_eq!(answer["status"], "queued", "{answer}");
                let place = accepted.len() + 1 + usize::from(queued_run.is_some());
                assert_eq!(answer["queue_position"], place, "{answer}");
                accepted.push(answer["id"].as_i64().unwrap());
            }
            429 => {
                refused += 1;
                assert_eq!(answer["error"]["code"], "queue_full", "{answer}");
                let message = answer["error"]["message"].as_str().unwrap();
                assert!(message.contains("work.queue_length = 6"), "{message}");
                assert!(retry_after.is_some_and(|s| s >= 1), "{retry_after:?}");
            }
            _ => panic!("{status}: {answer}"),
        }
        assert!(rows.running() <= 2);
    }
    assert_eq!((accepted.len(), refused), (5, 25));
    let queued_run = queued_run.unwrap();

    // Lists show the places too; a queued run cancelled leaves the queue, the others move up.
    let (_, runs) = server.get("/api/training", Some(&server.admin));
    let listed = runs["items"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["id"] == queued_run)
        .unwrap();
    assert_eq!(listed["queue_position"], 4, "{listed}");
    let (_, policy) = server.get("/api/policies/1", Some(&server.admin));
    assert_eq!(policy["evaluation"]["id"], *accepted.last().unwrap());
    assert_eq!(policy["evaluation"]["queue_position"], 6, "{policy}");
    let (status, answer) = server.post(
        &format!("/api/training/{queued_run}/cancel"),
        Some(&server.admin),
        None,
    );
    assert_eq!((status, &answer["status"]), (202, &json!("cancelled")));
    let (_, run) = server.get(&format!("/api/training/{queued_run}"), Some(&server.admin));
    assert_eq!(run["status"], "cancelled", "{run}");
    let (_, policy) = server.get("/api/policies/1", Some(&server.admin));
    assert_eq!(policy["evaluation"]["queue_position"], 5, "{policy}");

    // The e-stop answers while the queue is full and both places compute.
    let operator = server.token("operator");
    let (status, cell) = server.post("/api/cell/estop", Some(&operator), None);
    assert_eq!(status, 200, "{cell}");
    assert_eq!(cell["estop_latched"], true);
    let (status, cell) = server.post("/api/cell/reset", Some(&operator), None);
    assert_eq!(status, 200, "{cell}");

    // The blockers cancelled, the evaluations run to the end, never more than two at once, the
    // last one's place only ever moving up.
    for id in &blockers {
        let (status, _) = server.post(
            &format!("/api/training/{id}/cancel"),
            Some(&server.admin),
            None,
        );
        assert_eq!(status, 202);
    }
    let last = *accepted.last().unwrap();
    let place = std::cell::Cell::new(5);
    server.poll("/api/policies/1", "evaluated the burst", LONG, |policy| {
        assert!(rows.running() <= 2);
        let evaluation = &policy["evaluation"];
        assert_eq!(evaluation["id"], last);
        if let Some(now) = evaluation["queue_position"].as_u64() {
            assert!(now <= place.get(), "{} then {now}", place.get());
            place.set(now);
        }
        ended(&evaluation["status"])
    });
    // With two places computing side by side, an evaluation ahead of the last may end after
    // it, and a cancelled run stops only at its next check: wait for every one to end.
    let deadline = std::time::Instant::now() + LONG;
    let (evaluations, runs) = loop {
        let evaluations = rows.statuses("policy_evaluations");
        let runs = rows.statuses("training_runs");
        let is_over = |status: &str| status != "queued" && status != "running";
        let all_ended = accepted.iter().all(|id| {
            evaluations
                .iter()
                .any(|(e, status, _)| e == id && is_over(status))
        }) && runs.iter().all(|(_, status, _)| is_over(status));
        if all_ended || std::time::Instant::now() > deadline {
            break (evaluations, runs);
        }
        assert!(rows.running() <= 2);
        std::thread::sleep(Duration::from_millis(50));
    };
    for id in &accepted {
        let (_, status, error) = evaluations.iter().find(|(e, ..)| e == id).unwrap();
        assert_eq!((status.as_str(), error), ("done", &None), "evaluation {id}");
    }
    assert!(
        runs.iter().all(|(_, status, _)| status == "cancelled"),
        "{runs:?}"
    );
}

#[test]
fn sigterm_with_work_running_and_queued_exits_in_time_and_marks_it_failed() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = Server::start(
        dir.path(),
        &[
            ("CELLD_WORK_CONCURRENCY", "2"),
            ("CELLD_WORK_QUEUE_LENGTH", "4"),
        ],
    );
    bundled_evaluated(&server);
    // Running: a training run and a long evaluation; queued: two evaluations and a run.
    let (status, _, running_run) = post(&server, "/api/training", endless_training());
    assert_eq!((status, &running_run["status"]), (202, &json!("running")));
    let (status, _, running_evaluation) = post(
        &server,
        "/api/policies/1/evaluate",
        json!({"episodes": 10_000}),
    );
    assert_eq!(
        (status, &running_evaluation["status"]),
        (202, &json!("running")),
        "{running_evaluation}"
    );
    let mut queued = Vec::new();
    for path in [
        "/api/policies/1/evaluate",
        "/api/training",
        "/api/policies/1/evaluate",
    ] {
        let body = if path == "/api/training" {
            endless_training()
        } else {
            json!({"episodes": 8})
        };
        let (status, _, answer) = post(&server, path, body);
        assert_eq!(
            (status, &answer["status"]),
            (202, &json!("queued")),
            "{answer}"
        );
        queued.push(answer["id"].as_i64().unwrap());
    }

    let (exit, took) = server.terminate(Duration::from_secs(30));
    assert!(exit.success(), "{exit:?}");
    assert!(
        took < Duration::from_secs(10),
        "docs/service.md promises the process is gone within 10 s of SIGTERM; it took {took:?}"
    );

    // Marked at shutdown itself (the leftovers pass at the next start words it otherwise).
    let stopped = "the service was stopped (SIGTERM or SIGINT)";
    let rows = Rows::open(&server.db);
    let evaluations = rows.statuses("policy_evaluations");
    let runs = rows.statuses("training_runs");
    drop(rows);
    let find = |rows: &[(i64, String, Option<String>)], id: &Value| {
        let id = id.as_i64().unwrap();
        rows.iter().find(|(r, ..)| *r == id).unwrap().clone()
    };
    let (_, status, error) = find(&evaluations, &running_evaluation["id"]);
    assert_eq!(status, "failed");
    assert_eq!(error.unwrap(), format!("{stopped} during the evaluation"));
    let (_, status, error) = find(&runs, &running_run["id"]);
    assert_eq!(status, "failed");
    assert_eq!(error.unwrap(), format!("{stopped} during the run"));
    for (id, rows, what) in [
        (queued[0], &evaluations, "the evaluation"),
        (queued[1], &runs, "the run"),
        (queued[2], &evaluations, "the evaluation"),
    ] {
        let (_, status, error) = find(rows, &json!(id));
        assert_eq!(status, "failed", "{id}");
        assert_eq!(error.unwrap(), format!("{stopped} before {what} started"));
    }

    // After a restart the API says the same; nothing waits or runs from before.
    let server = Server::start(dir.path(), &[]);
    let (_, run) = server.get(&format!("/api/training/{}", queued[1]), Some(&server.admin));
    assert_eq!(run["status"], "failed", "{run}");
    assert_eq!(run["queue_position"], Value::Null);
    assert!(run["error"].as_str().unwrap().contains("SIGTERM"), "{run}");
    let (_, runs) = server.get("/api/training", Some(&server.admin));
    assert!(
        runs["items"]
            .as_array()
            .unwrap()
            .iter()
            .all(|r| ended(&r["status"])),
        "{runs}"
    );
    let rows = Rows::open(&server.db);
    let leftovers: Vec<_> = rows
        .statuses("policy_evaluations")
        .into_iter()
        .filter(|(id, status, _)| {
            // The bundled policy has its finished evaluation: none is started again.
            *id <= queued[2] && matches!(status.as_str(), "queued" | "running")
        })
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}
