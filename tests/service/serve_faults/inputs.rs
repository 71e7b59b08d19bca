//! Inputs beyond the cell: numbers no cell can hold refused with the field named, a policy over
//! `policies.max_parameters` refused, the role checked before the body is read, settings
//! refused at startup, and no backtrace in what a user is shown even with RUST_BACKTRACE=1.

use super::serve_support::Server;
use serde_json::{Value, json};
use std::process::Command;
use std::time::Duration;

/// No backtrace in `text`: none of std's frame locations, headers or this crate's paths.
fn assert_no_backtrace(text: &str) {
    assert!(
        !text.contains("stack backtrace")
            && !text.contains("Stack backtrace")
            && !text.contains("at src/")
            && !text.contains("at ./src/")
            && !text.contains("/rustc/"),
        "a backtrace is shown: {text}"
    );
}

fn message(body: &Value) -> String {
    let text = body["error"]["message"]
        .as_str()
        .unwrap_or_default()
        .to_string();
    assert_no_backtrace(&text);
    text
}

fn step_line(episode: u32, step: u32, px: &str) -> String {
    format!(
        r#"{{"episode":{episode},"step":{step},"state":[0,0,0,0,0,0,{px},0,-50,0,0,0],"action":[1,0,0,0,0,0],"actor":"position","scale":0.5}}"#
    )
}

#[test]
fn numbers_beyond_the_cell_and_policies_beyond_the_limit_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(
        dir.path(),
        &[
            ("RUST_BACKTRACE", "1"),
            // Below the bundled hierarchical policy's 30,561 parameters.
            ("CELLD_MAX_POLICY_PARAMETERS", "30000"),
        ],
    );
    let admin = server.admin.clone();

    // A demonstration with 1e308 in episode 1, step 4: refused naming episode, step, field.
    let body = [
        step_line(0, 0, "1"),
        step_line(1, 3, "2"),
        step_line(1, 4, "1e308"),
    ]
    .join("\n");
    let (status, answer) =
        server.post_raw("/api/demonstrations", &admin, "text/plain", body.as_bytes());
    assert_eq!(status, 422, "{answer}");
    let text = message(&answer);
    assert!(
        text.contains("episode 1, step 4: state[6] (Px) = 1e308 mm"),
        "{text}"
    );
    // NaN written as a string is not a number: the line is named.
    let body = [step_line(0, 0, "1"), step_line(0, 1, "\"NaN\"")].join("\n");
    let (status, answer) =
        server.post_raw("/api/demonstrations", &admin, "text/plain", body.as_bytes());
    assert_eq!(status, 422, "{answer}");
    assert!(message(&answer).contains("line 2"), "{answer}");
    let (_, listing) = server.get("/api/demonstrations", Some(&admin));
    assert_eq!(listing["items"], json!([]), "nothing was stored");

    // A job's initial offset beyond the workspace, named; any u64 seed is taken.
    let (status, answer) = server.post(
        "/api/jobs",
        Some(&admin),
        Some(json!({"controller": "expert", "initial": {"pos_mm": 1e308, "ori_deg": 1}})),
    );
    assert_eq!(status, 422, "{answer}");
    assert!(message(&answer).contains("initial.pos_mm"), "{answer}");
    let job = server.create_job(&admin, json!({"controller": "expert", "seed": u64::MAX}));
    assert_eq!(job["seed"], json!(u64::MAX));

    // Policies over the limit: 422 naming the count, the limit and the largest tensor.
    let policies = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("policies");
    for (file, tensor) in [
        ("default.safetensors", "high.lstm.weight_hh_l0"),
        ("td3.safetensors", "actor.2.weight"),
    ] {
        let bytes = std::fs::read(policies.join(file)).unwrap();
        let (status, answer) = server.post_raw(
            "/api/policies?name=big",
            &admin,
            "application/octet-stream",
            &bytes,
        );
        assert_eq!(status, 422, "{file}: {answer}");
        assert_eq!(answer["error"]["code"], "too_many_parameters", "{answer}");
        let text = message(&answer);
        assert!(
            text.contains("policies.max_parameters = 30000") && text.contains(tensor),
            "{text}"
        );
    }

    // A training run that diverges (a learning rate no network survives) fails naming the
    // epoch, and its stored error carries no backtrace though RUST_BACKTRACE=1 is set.
    let (status, run) = server.post(
        "/api/training",
        Some(&admin),
        Some(json!({
            "part": "all", "seed": 5, "episodes": 1, "record": 10,
            "settings": {"actor_width": 16, "bc_epochs": 3, "bc_orientation_epochs": 3,
                         "bc_learning_rate": 1e30, "lstm_hidden": 8, "lstm_epochs": 3,
                         "eval_every": 0, "eval_episodes": 2, "polish_td3_episodes": 1}
        })),
    );
    assert_eq!(status, 202, "{run}");
    let id = run["id"].as_i64().unwrap();
    let done = server.poll(
        &format!("/api/training/{id}"),
        "ended",
        Duration::from_secs(300),
        |run| !matches!(run["status"].as_str(), Some("running" | "queued")),
    );
    assert_eq!(done["status"], "failed", "{done}");
    let error = done["error"].as_str().unwrap();
    assert!(error.contains("diverged at epoch"), "{error}");
    assert_no_backtrace(error);
}

#[test]
fn the_role_is_checked_before_the_body_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[]);
    let viewer = server.token("viewer");
    let operator = server.token("operator");
    // A bad body and a good one get the same answer from a caller without the role.
    for (path, token, bad, good) in [
        (
            "/api/jobs",
            &viewer,
            "{not json",
            r#"{"controller":"expert"}"#,
        ),
        ("/api/training", &operator, r#"{"seed":-1}"#, "{}"),
        (
            "/api/policies/1/evaluate",
            &operator,
            "[1,2",
            r#"{"episodes":1}"#,
        ),
        ("/api/policies/1/activate", &viewer, "{", "{}"),
    ] {
        for body in [bad, good] {
            let (status, answer) =
                server.post_raw(path, token, "application/json", body.as_bytes());
            assert_eq!(status, 403, "{path} with {body}: {answer}");
            message(&answer);
        }
    }
    // Uploads: a bad query or body is not looked at either.
    for path in ["/api/policies", "/api/demonstrations?name="] {
        let (status, answer) = server.post_raw(path, &operator, "text/plain", b"\xff");
        assert_eq!(status, 403, "{path}: {answer}");
    }
    let (status, _) = server.get("/api/audit?limit=x", Some(&operator));
    assert_eq!(status, 403);
}

#[test]
fn absurd_settings_stop_the_service_at_startup_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    for (variable, value, key) in [
        ("CELLD_DEADLINE_MS", "1e308", "control.deadline_ms"),
        ("CELLD_STEP_PERIOD_MS", "NaN", "control.step_period_ms"),
        (
            "CELLD_ACTIVATION_THRESHOLD",
            "inf",
            "policies.activation_threshold",
        ),
        (
            "CELLD_MAX_POLICY_PARAMETERS",
            "0",
            "policies.max_parameters",
        ),
    ] {
        let output = Command::new(env!("CARGO_BIN_EXE_celld"))
            .args(["serve", "--listen", "127.0.0.1:0", "--db"])
            .arg(dir.path().join("celld.db"))
            .env("RUST_BACKTRACE", "1")
            .env("CELLD_CONTROL_CPU", "off")
            .env("CELLD_OPCUA_LISTEN", "off")
            .env(variable, value)
            .output()
            .expect("run celld serve");
        assert!(!output.status.success(), "{variable}={value} was accepted");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(stderr.contains(key), "{variable}={value}: {stderr}");
        assert_no_backtrace(&stderr);
    }
}

/// A database URL is not a path: refused by name, and no directory named after its scheme is
/// left behind.
#[test]
fn a_database_url_is_refused_and_makes_no_directory() {
    let dir = tempfile::tempdir().unwrap();
    for url in ["postgres://cell@db.plant/celld", "sqlite://celld.db"] {
        let output = Command::new(env!("CARGO_BIN_EXE_celld"))
            .current_dir(dir.path())
            .args(["serve", "--listen", "127.0.0.1:0", "--db", url])
            .env("CELLD_CONTROL_CPU", "off")
            .env("CELLD_OPCUA_LISTEN", "off")
            .output()
            .expect("run celld serve");
        assert!(!output.status.success(), "--db {url} was accepted");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(stderr.contains("is a URL"), "--db {url}: {stderr}");
        assert_no_backtrace(&stderr);
        assert_eq!(
            std::fs::read_dir(dir.path()).unwrap().count(),
            0,
            "--db {url} left something behind"
        );
    }
}
