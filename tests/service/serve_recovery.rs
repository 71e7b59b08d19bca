//! `celld serve` stopped hard (kill -9) and softly (SIGTERM) during a job, then started again.

use crate::serve_support;

use assembly_cell::storage::Db;
use serde_json::json;
use serve_support::Server;
use std::time::Duration;

const SLOW: [(&str, &str); 1] = [("CELLD_STEP_PERIOD_MS", "60")];

/// Opens the database file of a server (stopped, or running: SQLite's WAL lets a second
/// process read) and asks it one thing.
fn ask_db<T>(path: &std::path::Path, ask: impl AsyncFnOnce(&Db) -> T) -> T {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(async {
            let db = Db::open(path).await.expect("the database opens");
            let answer = ask(&db).await;
            db.writer.close().await;
            db.reader.close().await;
            answer
        })
}

fn integrity(path: &std::path::Path) -> String {
    ask_db(path, async |db| db.integrity_check().await.unwrap())
}

#[test]
fn kill_9_during_a_job_keeps_every_committed_step() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = Server::start(dir.path(), &SLOW);
    let job = server.create_job(
        &server.admin.clone(),
        json!({"controller": "expert", "seed": 21}),
    );
    let id = job["id"].as_i64().unwrap();
    // Wait until some steps are committed, then kill mid-job.
    let seen = loop {
        let steps = server.steps(id);
        if steps.len() >= 5 {
            break steps;
        }
        std::thread::sleep(Duration::from_millis(30));
    };
    assert_eq!(server.job(id)["status"], "running");
    server.kill9();

    assert_eq!(integrity(&server.db), "ok");

    let server = Server::start(dir.path(), &SLOW);
    let after = server.job(id);
    assert_eq!(after["status"], "interrupted", "{after}");
    assert_eq!(after["failure_reason"], "service_stopped");
    let stored = server.steps(id);
    assert!(
        stored.len() >= seen.len(),
        "{} stored < {} seen before the kill",
        stored.len(),
        seen.len()
    );
    assert_eq!(
        &stored[..seen.len()],
        &seen[..],
        "committed steps are unchanged"
    );
    assert_eq!(after["steps"].as_i64().unwrap() as usize, stored.len());

    // Nothing moved on its own after the restart.
    let (_, cell) = server.get("/api/cell", Some(&server.admin));
    assert_eq!(cell["current_job"], serde_json::Value::Null);

    // A latched e-stop stays latched through a crash.
    let (status, cell) = server.post("/api/cell/estop", Some(&server.admin), None);
    assert_eq!((status, &cell["estop_latched"]), (200, &json!(true)));
    let mut server = server;
    server.kill9();
    let server = Server::start(dir.path(), &SLOW);
    let (_, cell) = server.get("/api/cell", Some(&server.admin));
    assert_eq!(cell["estop_latched"], true, "{cell}");
    let (status, _) = server.post(
        "/api/jobs",
        Some(&server.admin),
        Some(json!({"controller": "expert"})),
    );
    assert_eq!(status, 409);
}

#[test]
fn sigterm_interrupts_the_job_and_exits_promptly() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = Server::start(dir.path(), &SLOW);
    let admin = server.admin.clone();
    let running = server.create_job(&admin, json!({"controller": "expert", "seed": 22}));
    let waiting = server.create_job(&admin, json!({"controller": "expert", "seed": 23}));
    let id = running["id"].as_i64().unwrap();
    while server.steps(id).len() < 3 {
        std::thread::sleep(Duration::from_millis(30));
    }
    let (status, took) = server.terminate(Duration::from_secs(10));
    assert!(status.success(), "{status:?}");
    assert!(took < Duration::from_secs(10));

    let server = Server::start(dir.path(), &SLOW);
    let after = server.job(id);
    assert_eq!(after["status"], "interrupted", "{after}");
    assert_eq!(after["failure_reason"], "shutdown");
    assert_eq!(
        after["steps"].as_i64().unwrap() as usize,
        server.steps(id).len()
    );
    let queued = server.job(waiting["id"].as_i64().unwrap());
    assert_eq!(queued["status"], "interrupted", "{queued}");
    assert_eq!(queued["steps"], 0);
}

/// The status and error of evaluation `id`, read from the database file.
fn evaluation_row(path: &std::path::Path, id: i64) -> (String, Option<String>) {
    ask_db(path, async |db| {
        sqlx::query_as("SELECT status, error FROM policy_evaluations WHERE id = ?")
            .bind(id)
            .fetch_one(&db.reader)
            .await
            .unwrap()
    })
}

#[test]
fn an_evaluation_cut_short_by_a_kill_is_failed_and_the_bundled_policy_evaluated_again() {
    let dir = tempfile::tempdir().unwrap();
    // The service's default evaluation (1000 episodes, not the tests' 20), on one low-priority
    // thread, takes seconds: the first start's is still running when the service is killed.
    let full = [("CELLD_EVALUATION_EPISODES", "1000")];
    let mut server = Server::start(dir.path(), &full);
    let (_, bundled) = server.get("/api/policies/1", Some(&server.admin));
    assert_eq!(bundled["name"], "bundled-default", "{bundled}");
    assert_eq!(bundled["evaluation"]["status"], "running", "{bundled}");
    let cut_short = bundled["evaluation"]["id"].as_i64().unwrap();
    server.kill9();
    assert_eq!(evaluation_row(&server.db, cut_short).0, "running");

    let server = Server::start(dir.path(), &full);
    assert_eq!(
        evaluation_row(&server.db, cut_short),
        (
            "failed".to_string(),
            Some("the service stopped during the evaluation".to_string())
        )
    );
    let evaluated = server.wait_evaluated(1, Duration::from_secs(120));
    let again = &evaluated["evaluation"];
    assert!(again["id"].as_i64().unwrap() > cut_short, "{evaluated}");
    assert_eq!(again["status"], "done", "{evaluated}");
    assert_eq!(again["episodes"], 1000);
    // It passes the gate and nothing else is active, as at a first start that was not cut short.
    let active = server.poll(
        "/api/policies/1",
        "activated",
        Duration::from_secs(10),
        |policy| policy["status"] == "active",
    );
    assert_eq!(active["evaluation"]["id"], again["id"]);
}

fn stored_estop(path: &std::path::Path) -> bool {
    ask_db(path, async |db| db.cell_flag("estop").await.unwrap())
}

/// E-stops and resets from several operators at once: whatever the control thread ends with
/// is what is stored, so a restart comes up in the same state.
#[test]
fn racing_estops_and_resets_store_the_latch_the_cell_ends_with() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[]);
    for round in 0..6 {
        std::thread::scope(|scope| {
            for operator in 0..8 {
                let server = &server;
                scope.spawn(move || {
                    for press in 0..16 {
                        let path = if (press + operator + round) % 2 == 0 {
                            "/api/cell/estop"
                        } else {
                            "/api/cell/reset"
                        };
                        let (status, body) = server.post(path, Some(&server.admin), None);
                        assert_eq!(status, 200, "{path}: {body}");
                    }
                });
            }
        });
        let (_, cell) = server.get("/api/cell", Some(&server.admin));
        assert_eq!(
            stored_estop(&server.db),
            cell["estop_latched"].as_bool().unwrap(),
            "round {round}: {cell}"
        );
    }
}
