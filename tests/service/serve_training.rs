//! Training runs over HTTP: progress and curve while running, waiting their turn in the work
//! queue, cancel, and the lineage demonstrations → run → policy → jobs.

use crate::serve_support;

use serde_json::{Value, json};
use serve_support::Server;
use std::time::Duration;

fn tiny(td3_episodes: usize) -> Value {
    json!({
        "part": "all",
        "seed": 5,
        "episodes": td3_episodes,
        "record": 12,
        "settings": {"actor_width": 16, "bc_epochs": 3, "bc_orientation_epochs": 3,
                     "lstm_hidden": 8, "lstm_epochs": 3, "eval_every": 0, "eval_episodes": 2,
                     "polish_td3_episodes": td3_episodes}
    })
}

/// Whether a run has ended (it neither waits nor runs).
fn ended(run: &Value) -> bool {
    !matches!(run["status"].as_str(), Some("queued" | "running"))
}

fn wait(server: &Server, id: i64, what: &str, done: impl Fn(&Value) -> bool) -> Value {
    let path = format!("/api/training/{id}");
    server.poll(&path, what, Duration::from_secs(300), done)
}

/// The id of the demonstrations a finished run recorded, and their entry in the list.
fn recorded_demonstration(server: &Server, run: &Value) -> (i64, Value) {
    let id = run["demonstration_ids"][0].as_i64().unwrap();
    let (_, listing) = server.get("/api/demonstrations", Some(&server.admin));
    let listed = listing["items"]
        .as_array()
        .unwrap()
        .iter()
        .find(|d| d["id"] == id)
        .expect("the run's demonstrations are stored")
        .clone();
    (id, listed)
}

#[test]
fn a_training_run_reports_progress_can_be_cancelled_and_leaves_a_candidate_with_lineage() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[("CELLD_STEP_PERIOD_MS", "5")]);
    let admin = server.admin.clone();
    let viewer = server.token("viewer");
    let (status, _) = server.post("/api/training", Some(&viewer), Some(tiny(4)));
    assert_eq!(status, 403);
    let (status, refused) = server.post(
        "/api/training",
        Some(&admin),
        Some(json!({"settings": {"bc_epochs": 0}})),
    );
    assert_eq!(status, 422, "{refused}");
    assert!(
        refused["error"]["message"]
            .as_str()
            .unwrap()
            .contains("bc_epochs")
    );
    for (settings, named) in [
        (json!({"demonstrator": "a person"}), "demonstrator"),
        (
            json!({"bc_bore_lateral_weight": 0.0}),
            "bc_bore_lateral_weight",
        ),
        (json!({"actor_width": 1_000_000}), "actor_width"),
        (json!({"td3_episodes": 10_000_000}), "td3_episodes"),
    ] {
        let (status, refused) = server.post(
            "/api/training",
            Some(&admin),
            Some(json!({ "settings": settings })),
        );
        assert_eq!(status, 422, "{refused}");
        let message = refused["error"]["message"].as_str().unwrap();
        assert!(message.contains(named), "{message}");
    }

    // A long run: its curve is readable while it runs; a second run waits its turn in the
    // work queue (one at a time by default) until cancelled there; the long one cancels.
    let (status, long) = server.post("/api/training", Some(&admin), Some(tiny(100_000)));
    assert_eq!(status, 202, "{long}");
    let long_id = long["id"].as_i64().unwrap();
    let seen = wait(&server, long_id, "showed a curve", |r| {
        r["status"] == "running" && r["curve"].as_array().is_some_and(|c| !c.is_empty())
    });
    assert!(seen["progress"].as_f64().unwrap() > 0.0, "{seen}");
    assert_eq!(seen["queue_position"], Value::Null);
    let (status, second) = server.post("/api/training", Some(&admin), Some(tiny(4)));
    assert_eq!(status, 202, "{second}");
    assert_eq!(second["status"], "queued", "{second}");
    assert_eq!(second["queue_position"], 1, "{second}");
    let second_id = second["id"].as_i64().unwrap();
    let (_, listed) = server.get("/api/training", Some(&admin));
    let entry = listed["items"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["id"] == second_id)
        .unwrap()
        .clone();
    assert_eq!(
        (&entry["status"], &entry["queue_position"]),
        (&json!("queued"), &json!(1))
    );
    let (status, answer) = server.post(
        &format!("/api/training/{second_id}/cancel"),
        Some(&admin),
        None,
    );
    assert_eq!((status, &answer["status"]), (202, &json!("cancelled")));
    let (_, dequeued) = server.get(&format!("/api/training/{second_id}"), Some(&admin));
    assert_eq!(dequeued["status"], "cancelled", "{dequeued}");
    assert_eq!(dequeued["queue_position"], Value::Null);
    assert_eq!(dequeued["curve"], json!([]), "it never ran: {dequeued}");
    let (status, _) = server.post(
        &format!("/api/training/{long_id}/cancel"),
        Some(&viewer),
        None,
    );
    assert_eq!(status, 403);
    let (status, _) = server.post(
        &format!("/api/training/{long_id}/cancel"),
        Some(&admin),
        None,
    );
    assert_eq!(status, 202);
    let cancelled = wait(&server, long_id, "ended", ended);
    assert_eq!(cancelled["status"], "cancelled", "{cancelled}");
    assert_eq!(cancelled["policy_id"], Value::Null);

    // A short run to the end, recording the bundled policy's demonstrator with its bore weight.
    let mut careful = tiny(4);
    careful["settings"]["demonstrator"] = json!("expert-careful");
    careful["settings"]["bc_bore_lateral_weight"] = json!(30.0);
    let (status, short) = server.post("/api/training", Some(&admin), Some(careful));
    assert_eq!(status, 202, "{short}");
    let id = short["id"].as_i64().unwrap();
    let done = wait(&server, id, "ended", ended);
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["progress"], 1.0);
    let stages: Vec<&str> = done["curve"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["stage"].as_str().unwrap())
        .collect();
    for stage in ["bc_position", "bc_orientation", "lstm", "td3"] {
        assert!(stages.contains(&stage), "{stage} missing from the curve");
    }
    assert_eq!(stages.iter().filter(|s| **s == "td3").count(), 4);

    // Lineage: demonstrations → run → policy → job.
    let (_, listed) = recorded_demonstration(&server, &done);
    assert_eq!(listed["source"], "scripted");
    assert!(
        listed["name"].as_str().unwrap().contains("expert-careful"),
        "{listed}"
    );
    assert_eq!(listed["episodes"], 12);
    let policy_id = done["policy_id"].as_i64().unwrap();
    let (_, policy) = server.get(&format!("/api/policies/{policy_id}"), Some(&admin));
    assert_eq!(policy["status"], "candidate", "{policy}");
    assert_eq!(policy["training_run_id"], id);
    assert_eq!(policy["shapes"]["pos.0.weight"], json!([16, 12]));
    // A fresh candidate, never evaluated: the gate refuses it; the admin overrides it, audited.
    let controller = format!("policy:{policy_id}");
    let (status, refused) = server.post(
        "/api/jobs",
        Some(&admin),
        Some(json!({"controller": controller})),
    );
    assert_eq!(status, 409, "{refused}");
    let job = server.create_job(
        &admin,
        json!({"controller": controller, "override_gate": {"reason": "first run of a trained policy"}}),
    );
    assert_eq!(job["policy_id"], policy_id);
    let finished = server.wait_final(job["id"].as_i64().unwrap());
    assert!(finished["steps"].as_i64().unwrap() > 0, "{finished}");

    let (_, audit) = server.get("/api/audit", Some(&admin));
    let actions: Vec<&str> = audit["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["action"].as_str().unwrap())
        .collect();
    assert!(actions.contains(&"training.start") && actions.contains(&"training.cancel"));
    assert!(actions.contains(&"job.override_gate"), "{actions:?}");
}

/// A run for any cell records its demonstrations on randomised cells with cell-scaled inputs,
/// stores them as such, and makes a version 2 policy that drives the cell; demonstrations of
/// the other kind are refused by name.
#[test]
fn a_run_for_any_cell_learns_cell_scaled_inputs_and_keeps_the_kinds_apart() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[("CELLD_STEP_PERIOD_MS", "5")]);
    let admin = server.admin.clone();
    let mut any_cell = tiny(2);
    any_cell["settings"]["for_any_cell"] = json!(true);
    let (status, started) = server.post("/api/training", Some(&admin), Some(any_cell));
    assert_eq!(status, 202, "{started}");
    let id = started["id"].as_i64().unwrap();
    let done = wait(&server, id, "ended", ended);
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["settings"]["for_any_cell"], true, "{done}");

    let (demonstration, listed) = recorded_demonstration(&server, &done);
    assert_eq!(listed["inputs"], "cell-scaled", "{listed}");
    assert!(
        listed["name"]
            .as_str()
            .unwrap()
            .contains("randomised cells"),
        "{listed}"
    );
    let policy_id = done["policy_id"].as_i64().unwrap();
    let (_, policy) = server.get(&format!("/api/policies/{policy_id}"), Some(&admin));
    assert_eq!(policy["metadata"]["format_version"], "2", "{policy}");
    assert_eq!(policy["metadata"]["inputs"], "cell-scaled", "{policy}");
    let job = server.create_job(
        &admin,
        json!({
            "controller": format!("policy:{policy_id}"),
            "override_gate": {"reason": "a trained candidate, run before its evaluation"}
        }),
    );
    let finished = server.wait_final(job["id"].as_i64().unwrap());
    assert!(finished["steps"].as_i64().unwrap() > 0, "{finished}");

    // Those demonstrations are the wrong kind for a run on the absolute state.
    let (status, refused) = server.post(
        "/api/training",
        Some(&admin),
        Some(json!({"demonstrations": [demonstration]})),
    );
    assert_eq!(status, 422, "{refused}");
    let message = refused["error"]["message"].as_str().unwrap();
    assert!(
        message.contains("cell-scaled") && message.contains(&demonstration.to_string()),
        "{message}"
    );
}

/// The tensors of a safetensors file, by name.
fn tensors(bytes: &[u8]) -> Vec<(String, Vec<f32>)> {
    let mut named: Vec<(String, Vec<f32>)> =
        candle_core::safetensors::load_buffer(bytes, &candle_core::Device::Cpu)
            .unwrap()
            .into_iter()
            .map(|(name, t)| (name, t.flatten_all().unwrap().to_vec1::<f32>().unwrap()))
            .collect();
    named.sort_by(|a, b| a.0.cmp(&b.0));
    named
}

#[test]
fn a_run_with_a_dagger_round_and_the_polish_learns_what_celld_train_policy_learns() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[("CELLD_STEP_PERIOD_MS", "5")]);
    let admin = server.admin.clone();
    let mut recipe = tiny(1);
    for (key, value) in [
        ("demonstrator", json!("expert-swift")),
        ("bc_bore_lateral_weight", json!(30.0)),
        ("for_any_cell", json!(true)),
        ("dagger_rounds", json!(1)),
        ("dagger_bc_epochs", json!(3)),
    ] {
        recipe["settings"][key] = value;
    }
    let (status, started) = server.post("/api/training", Some(&admin), Some(recipe));
    assert_eq!(status, 202, "{started}");
    let id = started["id"].as_i64().unwrap();
    let done = wait(&server, id, "ended", ended);
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["figures"]["dagger"][0]["episodes"], 12, "{done}");
    let lstm: Vec<i64> = done["curve"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| p["stage"] == "lstm")
        .map(|p| p["x"].as_i64().unwrap())
        .collect();
    assert_eq!(done["figures"]["polished"], true, "{done}");
    assert_eq!(
        lstm.len(),
        7,
        "both passes' selector epochs and the polish's: {lstm:?}"
    );
    assert!(lstm.windows(2).all(|w| w[0] < w[1]), "{lstm:?}");
    let policy_id = done["policy_id"].as_i64().unwrap();
    let served = server.get_bytes(&format!("/api/policies/{policy_id}/file"), &admin);

    // The command line's recipe at the same sizes.
    let out = dir.path().join("cli");
    let cli = std::process::Command::new(env!("CARGO_BIN_EXE_celld"))
        .args([
            "train",
            "policy",
            "--out",
            out.to_str().unwrap(),
            "--seed",
            "5",
            "--dagger-rounds",
            "1",
        ])
        .args([
            "--",
            "--demos",
            "12",
            "--dagger-episodes",
            "12",
            "--actor-width",
            "16",
        ])
        .args([
            "--bc-orientation-epochs",
            "3",
            "--lstm-hidden",
            "8",
            "--lstm-epochs",
            "3",
        ])
        .args([
            "--eval-every",
            "0",
            "--eval-episodes",
            "2",
            "--bc-epochs",
            "3",
            // The run's `episodes`: the polish's own 500 give way to it.
            "--td3-episodes",
            "1",
        ])
        .output()
        .unwrap();
    assert!(
        cli.status.success(),
        "{}",
        String::from_utf8_lossy(&cli.stderr)
    );
    let first_pass = std::fs::read(out.join("round-0/policy.safetensors")).unwrap();
    let trained = std::fs::read(out.join("policy.safetensors")).unwrap();
    assert_ne!(tensors(&first_pass), tensors(&trained));
    assert_eq!(tensors(&served), tensors(&trained));
}
