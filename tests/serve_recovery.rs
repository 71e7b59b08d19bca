//! `celld serve` stopped hard (kill -9) and softly (SIGTERM) during a job, then started again.

mod serve_support;

use assembly_cell::storage::Db;
use serde_json::json;
use serve_support::Server;
use std::time::Duration;

const SLOW: [(&str, &str); 1] = [("CELLD_STEP_PERIOD_MS", "60")];

fn integrity(db: &std::path::Path) -> String {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(async {
            let db = Db::open(db)
                .await
                .expect("the database opens after the kill");
            let answer = db.integrity_check().await.unwrap();
            db.writer.close().await;
            db.reader.close().await;
            answer
        })
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
    assert_eq!(queued["status"], "interrupted");
    assert_eq!(queued["steps"], 0);
}
