//! `celld serve` with the real drivers against `celld twin-server`: a job runs end to end;
//! the controller going away mid-job, or the camera going silent, repeating a frame or sending
//! garbage, ends it in a hold with a named reason, keeps every step stored and the service
//! serving; after a lost controller the robot moves again only after an operator reset.

use crate::drivers_support;
use crate::serve_support;

use drivers_support::{GARBAGE, PASS, REPEAT, SILENT, TwinServer, camera_relay};
use serde_json::{Value, json};
use serve_support::Server;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::Duration;

/// `celld serve` in `dir` with the GCS robot and the OpenIGTLink camera on these loopback ports,
/// rehearsing against `celld twin-server`, at a 20 ms step period. The twin-server runs with
/// `--instant-moves`: the service's default on-target deadline (20 ms) is shorter than a step's
/// move at the cell's speeds.
fn serve_through_drivers(dir: &std::path::Path, gcs_port: u16, igtl_port: u16) -> Server {
    let (gcs, igtl) = (gcs_port.to_string(), igtl_port.to_string());
    Server::start(
        dir,
        &[
            ("CELLD_ROBOT_DRIVER", "gcs"),
            ("CELLD_ROBOT_PORT", &gcs),
            ("CELLD_ROBOT_REHEARSAL", "true"),
            ("CELLD_CAMERA_DRIVER", "igtl"),
            ("CELLD_CAMERA_PORT", &igtl),
            ("CELLD_STEP_PERIOD_MS", "20"),
            // Generous waits: a loaded test machine must not make a late answer a fault.
            ("CELLD_ROBOT_ANSWER_TIMEOUT_MS", "2000"),
            ("CELLD_CAMERA_FRAME_TIMEOUT_MS", "300"),
        ],
    )
}

fn id(job: &Value) -> i64 {
    job["id"].as_i64().unwrap()
}

#[test]
fn jobs_run_through_the_drivers_and_a_lost_controller_holds_until_an_operator_reset() {
    // Moves take their time at the cell's speeds, as a real hexapod's do.
    let twin = TwinServer::start(&[]);
    let (gcs_port, igtl_port) = (twin.gcs.port(), twin.igtl.port());
    let dir = tempfile::tempdir().unwrap();
    let server = serve_through_drivers(dir.path(), gcs_port, igtl_port);
    let (_, cell) = server.get("/api/cell", Some(&server.admin));
    assert_eq!(cell["backend"], "drivers", "{cell}");
    let operator = server.token("operator");

    let job = server.create_job(&operator, json!({"controller": "expert", "seed": 2}));
    let done = server.wait_final(id(&job));
    assert_eq!(done["status"], "succeeded", "{done}");
    // The drivers' figures: a round trip for each query, an age for each frame.
    let metrics = exposition(&server);
    assert!(count_of(&metrics, "celld_controller_round_trip_seconds_count") > 50.0);
    assert!(count_of(&metrics, "celld_camera_frame_age_seconds_count") > 10.0);
    assert_eq!(count_of(&metrics, "celld_driver_latched"), 0.0);

    // The controller goes away mid-job.
    let job = server.create_job(&operator, json!({"controller": "expert", "seed": 3}));
    let steps_path = format!("/api/jobs/{}/steps", id(&job));
    server.poll(
        &steps_path,
        "took 5 steps",
        Duration::from_secs(60),
        |body| {
            body["items"]
                .as_array()
                .is_some_and(|items| items.len() >= 5)
        },
    );
    // A running job counts the steps stored so far.
    let running = server.job(id(&job));
    assert_eq!(running["status"], "running", "{running}");
    assert!(running["steps"].as_i64().unwrap() >= 5, "{running}");
    drop(twin);
    let failed = server.wait_final(id(&job));
    assert_eq!(failed["status"], "failed", "{failed}");
    assert_eq!(failed["failure_reason"], "robot_fault", "{failed}");
    let steps = server.steps(id(&job));
    assert_eq!(steps.len() as i64, failed["steps"].as_i64().unwrap());
    let named: Vec<&str> = steps
        .iter()
        .filter_map(|step| step["detected"].as_str())
        .collect();
    assert!(
        named
            .iter()
            .any(|d| matches!(*d, "controller_dropped" | "controller_timeout")),
        "{named:?}"
    );

    // The service keeps serving and says what is latched, why and since when; a new job is
    // refused with the reason instead of accepted and failed.
    let cell = server.poll(
        "/api/cell",
        "the driver latch",
        Duration::from_secs(10),
        |cell| !cell["driver_latch"].is_null(),
    );
    assert_eq!(cell["accepting_jobs"], false, "{cell}");
    let latch = &cell["driver_latch"];
    assert!(
        matches!(
            latch["code"].as_str(),
            Some("controller_dropped" | "controller_timeout")
        ),
        "{latch}"
    );
    assert!(latch["since_unix_ms"].as_u64().unwrap() > 0, "{latch}");
    assert_eq!(count_of(&exposition(&server), "celld_driver_latched"), 1.0);
    let (status, refused) = server.post(
        "/api/jobs",
        Some(&operator),
        Some(json!({"controller": "expert", "seed": 4})),
    );
    assert_eq!(status, 409, "{refused}");
    let message = refused["error"]["message"].as_str().unwrap();
    assert!(message.contains("latched"), "{message}");

    // A reset while the controller is still down says so and keeps the latch.
    let (status, answer) = server.post("/api/cell/reset", Some(&operator), None);
    assert_eq!(status, 503, "{answer}");
    let message = answer["error"]["message"].as_str().unwrap();
    assert!(message.contains("cannot connect"), "{message}");
    let (_, cell) = server.get("/api/cell", Some(&server.admin));
    assert!(!cell["driver_latch"].is_null(), "{cell}");

    // The controller is back, its platform at another episode's start: the reset finds the
    // platform away from where the cell left it and says so first; a second reset takes it.
    let _twin = TwinServer::start_on(gcs_port, igtl_port, &[]);
    let (status, answer) = server.post("/api/cell/reset", Some(&operator), None);
    assert_eq!(status, 503, "{answer}");
    let message = answer["error"]["message"].as_str().unwrap();
    assert!(
        message.contains("from where the cell last put it"),
        "{message}"
    );
    let (_, cell) = server.get("/api/cell", Some(&server.admin));
    assert_eq!(cell["driver_latch"]["code"], "position_mismatch", "{cell}");
    let (status, cell) = server.post("/api/cell/reset", Some(&operator), None);
    assert_eq!(status, 200, "{cell}");
    assert!(cell["driver_latch"].is_null(), "{cell}");
    assert_eq!(cell["accepting_jobs"], true, "{cell}");
    let metrics = exposition(&server);
    assert_eq!(count_of(&metrics, "celld_driver_latched"), 0.0);
    assert!(count_of(&metrics, "celld_driver_reconnects_total{driver=\"robot\"}") >= 1.0);
    let job = server.create_job(&operator, json!({"controller": "expert", "seed": 6}));
    let done = server.wait_final(id(&job));
    assert_eq!(done["status"], "succeeded", "{done}");

    // A controller that goes away between jobs shows as latched without a job to find it.
    drop(_twin);
    let cell = server.poll(
        "/api/cell",
        "the idle latch",
        Duration::from_secs(10),
        |cell| !cell["driver_latch"].is_null(),
    );
    assert_eq!(cell["driver_latch"]["code"], "controller_dropped", "{cell}");
}

fn exposition(server: &Server) -> String {
    let (_, metrics) = server.get("/metrics", None);
    metrics.as_str().unwrap().to_string()
}

/// The value of the sample named `name` (with its labels) in a metrics exposition.
fn count_of(metrics: &str, name: &str) -> f64 {
    metrics
        .lines()
        .find_map(|line| line.strip_prefix(name)?.strip_prefix(' '))
        .unwrap_or_else(|| panic!("no {name} in {metrics}"))
        .trim()
        .parse()
        .unwrap()
}

/// Polls until the job has stored `count` steps.
fn wait_steps(server: &Server, job: i64, count: usize) {
    let path = format!("/api/jobs/{job}/steps");
    server.poll(&path, "took its steps", Duration::from_secs(60), |body| {
        body["items"]
            .as_array()
            .is_some_and(|items| items.len() >= count)
    });
}

#[test]
fn camera_faults_mid_job_end_it_named_with_every_step_stored_and_the_next_job_runs() {
    let twin = TwinServer::start(&["--instant-moves"]);
    let mode = Arc::new(AtomicU8::new(PASS));
    let relay = camera_relay(twin.igtl, mode.clone());
    let dir = tempfile::tempdir().unwrap();
    let server = serve_through_drivers(dir.path(), twin.gcs.port(), relay.port());
    let operator = server.token("operator");
    for (seed, fault, reason, named) in [
        (7, REPEAT, "frozen_camera", "frozen_camera"),
        (8, SILENT, "stale_camera", "camera_silent"),
        (9, GARBAGE, "stale_camera", "camera_garbage"),
    ] {
        mode.store(PASS, Ordering::SeqCst);
        let job = server.create_job(&operator, json!({"controller": "expert", "seed": seed}));
        wait_steps(&server, id(&job), 5);
        mode.store(fault, Ordering::SeqCst);
        let failed = server.wait_final(id(&job));
        assert_eq!(failed["status"], "failed", "{failed}");
        assert_eq!(failed["failure_reason"], reason, "{failed}");
        let steps = server.steps(id(&job));
        assert_eq!(steps.len() as i64, failed["steps"].as_i64().unwrap());
        assert!(
            steps.iter().any(|step| step["detected"] == named),
            "{named} in {:?}",
            steps.iter().map(|s| &s["detected"]).collect::<Vec<_>>()
        );
    }
    mode.store(PASS, Ordering::SeqCst);
    let job = server.create_job(&operator, json!({"controller": "expert", "seed": 10}));
    let done = server.wait_final(id(&job));
    assert_eq!(done["status"], "succeeded", "{done}");
}
