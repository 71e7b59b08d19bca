//! The cell's PackML state and production counters over HTTP: a job runs through Execute to
//! Complete and is counted; Stop and the e-stop refuse jobs until a reset; the counters and
//! transitions survive a restart.

use crate::serve_support;

use serde_json::{Value, json};
use serve_support::Server;
use std::time::Duration;

fn machine(server: &Server) -> Value {
    let (status, body) = server.get("/api/cell/machine", Some(&server.admin));
    assert_eq!(status, 200, "{body}");
    body
}

/// Polls until the cell is in `state` and the stored transitions have caught up with it (the
/// storage writer stores them a moment after the state changes).
fn wait_state(server: &Server, state: &str) -> Value {
    let what = format!("reached {state}");
    server.poll("/api/cell/machine", &what, Duration::from_secs(60), |m| {
        m["state"] == state && m["transitions"][0]["to_state"] == state
    })
}

/// The states' names in the stored transitions, oldest first.
fn path(machine: &Value) -> Vec<String> {
    let mut transitions: Vec<&Value> = machine["transitions"].as_array().unwrap().iter().collect();
    transitions.reverse();
    transitions
        .iter()
        .map(|t| t["to_state"].as_str().unwrap().to_string())
        .collect()
}

#[test]
fn jobs_stop_and_estop_drive_the_packml_states_and_the_counters_persist() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = Server::start(dir.path(), &[]);
    let operator = server.token("operator");
    let viewer = server.token("viewer");
    let start = machine(&server);
    assert_eq!(start["state"], "Idle");
    assert_eq!(start["state_number"], 4);
    assert_eq!(start["counters"]["processed"], 0);

    // A job runs Idle → Starting → Execute → Completing → Complete and counts one good part.
    let job = server.create_job(&operator, json!({"controller": "expert", "seed": 5}));
    let ended = server.wait_final(job["id"].as_i64().unwrap());
    assert_eq!(ended["status"], "succeeded", "{ended}");
    let done = wait_state(&server, "Complete");
    assert_eq!(
        path(&done),
        ["Starting", "Execute", "Completing", "Complete"]
    );
    assert_eq!(done["counters"]["processed"], 1);
    assert_eq!(done["counters"]["good"], 1);
    let cycle = done["counters"]["last_cycle_time_s"].as_f64().unwrap();
    assert!(cycle > 0.0, "{done}");
    assert_eq!(done["cycle_times"][0]["job_id"], job["id"]);

    // A viewer may not stop; an operator's stop leaves the cell Stopped, refusing jobs.
    let (status, _) = server.post("/api/cell/stop", Some(&viewer), None);
    assert_eq!(status, 403);
    let (status, cell) = server.post("/api/cell/stop", Some(&operator), None);
    assert_eq!(status, 200, "{cell}");
    assert_eq!(cell["machine"]["state"], "Stopped");
    assert_eq!(cell["machine"]["stop_reason"]["code"], "stop");
    assert_eq!(cell["accepting_jobs"], false);
    let (status, refused) = server.post(
        "/api/jobs",
        Some(&operator),
        Some(json!({"controller": "expert"})),
    );
    assert_eq!(status, 409, "{refused}");
    let message = refused["error"]["message"].as_str().unwrap();
    assert!(message.contains("Stopped"), "{refused}");
    let (status, again) = server.post("/api/cell/stop", Some(&operator), None);
    assert_eq!(status, 409, "{again}");
    let (status, cell) = server.post("/api/cell/reset", Some(&operator), None);
    assert_eq!(status, 200, "{cell}");
    assert_eq!(cell["machine"]["state"], "Idle");

    // The e-stop aborts; a reset is Clear then Reset.
    let (status, cell) = server.post("/api/cell/estop", Some(&operator), None);
    assert_eq!(status, 200, "{cell}");
    assert_eq!(cell["machine"]["state"], "Aborted");
    assert_eq!(cell["machine"]["stop_reason"]["id"], 1);
    assert_eq!(cell["machine"]["counters"]["estops"], 1);
    server.post("/api/cell/reset", Some(&operator), None);
    let idle = wait_state(&server, "Idle");
    let tail: Vec<String> = path(&idle).into_iter().rev().take(4).collect();
    assert_eq!(tail, ["Idle", "Resetting", "Stopped", "Clearing"]);

    // A restart keeps the counters and the record of transitions.
    server.terminate(Duration::from_secs(15));
    let server = Server::start(dir.path(), &[]);
    let after = machine(&server);
    assert_eq!(after["state"], "Idle");
    assert_eq!(after["counters"], idle["counters"]);
    assert_eq!(after["transitions"], idle["transitions"]);
}

/// Hold pauses the running job after its move; unhold lets it finish.
#[test]
fn hold_pauses_a_job_and_unhold_finishes_it() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[("CELLD_STEP_PERIOD_MS", "40")]);
    let job = server.create_job(&server.admin, json!({"controller": "expert", "seed": 9}));
    let id = job["id"].as_i64().unwrap();
    server.wait_job(id, "took a step", |job| job["steps"].as_u64() > Some(0));
    let (status, cell) = server.post("/api/cell/hold", Some(&server.admin), None);
    assert_eq!(status, 200, "{cell}");
    assert_eq!(cell["machine"]["state"], "Held");
    // The storage writer stores steps every 100 ms: let the last one land.
    std::thread::sleep(Duration::from_millis(300));
    let held_at = server.steps(id).len();
    std::thread::sleep(Duration::from_millis(400));
    assert_eq!(server.steps(id).len(), held_at, "a held job takes no step");
    assert_eq!(server.job(id)["status"], "running");
    let (status, cell) = server.post("/api/cell/unhold", Some(&server.admin), None);
    assert_eq!(status, 200, "{cell}");
    let ended = server.wait_final(id);
    assert_eq!(ended["status"], "succeeded", "{ended}");
    assert!(ended["steps"].as_u64().unwrap() > held_at as u64);
}
