//! The policy registry over HTTP: upload checks, evaluation, the activation gate, rollback.

use crate::serve_support;

use assembly_cell::policy::eval;
use assembly_cell::storage::Db;
use serde_json::{Map, Value, json};
use serve_support::Server;
use std::time::Duration;

/// The bundled default, `hierarchical-swift-cells`.
const DEFAULT: &[u8] = include_bytes!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/policies/swift-cells.safetensors"
));
/// `hierarchical-reference`, the bundled default before it.
const REFERENCE: &[u8] = include_bytes!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/policies/default.safetensors"
));
const BC: &[u8] = include_bytes!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/policies/bc.safetensors"
));
const TD3: &[u8] = include_bytes!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/policies/td3.safetensors"
));
const ACROSS_CELLS: &[u8] = include_bytes!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/policies/across-cells.safetensors"
));

fn upload(server: &Server, token: &str, name: &str, bytes: &[u8]) -> (u16, Value) {
    server.post_raw(
        &format!("/api/policies?name={name}"),
        token,
        "application/octet-stream",
        bytes,
    )
}

/// How long an evaluation may take.
const EVALUATION: Duration = Duration::from_secs(120);

/// Polls policy `id` until its latest evaluation has ended (neither waits in the work queue
/// nor runs); answers the policy.
fn evaluation_ended(server: &Server, id: i64) -> Value {
    let path = format!("/api/policies/{id}");
    server.poll(&path, "ended its evaluation", EVALUATION, |policy| {
        !matches!(
            policy["evaluation"]["status"].as_str(),
            Some("queued" | "running")
        )
    })
}

/// Opens the database file at `path` (made with every migration when it is not there) and
/// does one thing with it, before a server starts on it.
fn with_db<T>(path: &std::path::Path, work: impl AsyncFnOnce(&Db) -> T) -> T {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(async {
            let db = Db::open(path).await.expect("the database opens");
            let answer = work(&db).await;
            db.writer.close().await;
            db.reader.close().await;
            answer
        })
}

/// A database an earlier release left, whose bundled default (the reference-cell policy) is
/// registered, evaluated and active: at the next start the new default is registered beside it
/// and evaluated, and the earlier one stays active, with its evaluation, until an admin
/// activates the new one.
#[test]
fn an_earlier_default_left_active_stays_active_beside_the_new_one() {
    let dir = tempfile::tempdir().unwrap();
    let earlier = with_db(&dir.path().join("celld.db"), async |db| {
        let workflows = assembly_cell::workflows::policies::register;
        let (policy, created) = workflows(db, "bundled-default", REFERENCE.to_vec(), "celld")
            .await
            .unwrap();
        assert!(created);
        assembly_cell::storage::policies::activate(db, policy.id)
            .await
            .unwrap();
        policy.id
    });
    let server = Server::start(dir.path(), &[]);
    let admin = server.admin.clone();
    let (_, list) = server.get("/api/policies", Some(&admin));
    let items = list["items"].as_array().unwrap();
    assert_eq!(items.len(), 2, "{list}");
    let (new, old) = (&items[0], &items[1]);
    assert_eq!(old["id"], earlier);
    assert_eq!(old["status"], "active", "{old}");
    assert_eq!(new["name"], "bundled-default");
    assert_ne!(new["sha256"], old["sha256"]);
    let new_id = new["id"].as_i64().unwrap();
    let (status, same) = upload(&server, &admin, "again", DEFAULT);
    assert_eq!((status, &same["id"]), (200, &json!(new_id)), "{same}");

    let evaluated = evaluation_ended(&server, new_id);
    assert_eq!(evaluated["evaluation"]["status"], "done", "{evaluated}");
    assert!(evaluated["evaluation"]["success_rate"].as_f64().unwrap() >= 0.95);
    // It passed the gate; the service records that it left it inactive, and why.
    let entry = server.poll(
        "/api/audit",
        "recorded the default left inactive",
        EVALUATION,
        |audit| {
            audit["items"]
                .as_array()
                .unwrap()
                .iter()
                .any(|e| e["action"] == "policy.bundled_not_activated")
        },
    );
    let entry = entry["items"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["action"] == "policy.bundled_not_activated")
        .unwrap()
        .clone();
    assert_eq!(entry["detail"]["policy_id"], new_id, "{entry}");
    assert_eq!(entry["detail"]["active_policy_id"], earlier, "{entry}");
    let (_, old) = server.get(&format!("/api/policies/{earlier}"), Some(&admin));
    assert_eq!(old["status"], "active", "{old}");
    let (_, new) = server.get(&format!("/api/policies/{new_id}"), Some(&admin));
    assert_eq!(new["status"], "candidate", "{new}");

    // The admin's activation retires the earlier default; activating that again rolls back.
    let (status, activated) = server.post(
        &format!("/api/policies/{new_id}/activate"),
        Some(&admin),
        None,
    );
    assert_eq!(status, 200, "{activated}");
    assert_eq!(activated["retired"], earlier, "{activated}");
}

fn policy_count(server: &Server) -> usize {
    let (_, list) = server.get("/api/policies", Some(&server.admin));
    list["items"].as_array().unwrap().len()
}

#[test]
fn upload_evaluate_activate_and_roll_back() {
    let dir = tempfile::tempdir().unwrap();
    // A threshold of 0 lets the test's short evaluations pass the gate.
    let server = Server::start(
        dir.path(),
        &[
            ("CELLD_STEP_PERIOD_MS", "5"),
            ("CELLD_ACTIVATION_THRESHOLD", "0"),
        ],
    );
    let admin = server.admin.clone();

    // The bundled default is registered at first start (and evaluated there).
    let (_, list) = server.get("/api/policies", Some(&admin));
    let bundled = list["items"][0].clone();
    assert_eq!(bundled["name"], "bundled-default", "{list}");

    let (status, same) = upload(&server, &admin, "again", DEFAULT);
    assert_eq!(status, 200, "the same bytes are the same policy: {same}");
    assert_eq!(same["id"], bundled["id"]);
    let (status, bc) = upload(&server, &admin, "bc", BC);
    assert_eq!(status, 201, "{bc}");
    assert_eq!(bc["status"], "candidate");
    assert_eq!(bc["shapes"]["high.head.weight"], json!([3, 64]));
    let bc_id = bc["id"].as_i64().unwrap();
    let bundled_id = bundled["id"].as_i64().unwrap();

    // The file comes back byte for byte.
    let file = server.get_bytes(&format!("/api/policies/{bc_id}/file"), &admin);
    assert_eq!(file, BC);

    // No evaluation yet: refused.
    let (status, refused) = server.post(
        &format!("/api/policies/{bc_id}/activate"),
        Some(&admin),
        None,
    );
    assert_eq!(status, 409, "{refused}");
    assert!(
        refused["error"]["message"]
            .as_str()
            .unwrap()
            .contains("no finished evaluation")
    );

    // The bundled policy's evaluation at start ends first: evaluations run one at a time.
    evaluation_ended(&server, bundled_id);
    let (status, evaluation) = server.post(
        &format!("/api/policies/{bc_id}/evaluate"),
        Some(&admin),
        Some(json!({"episodes": 10, "seed": 3})),
    );
    assert_eq!(status, 202, "{evaluation}");
    assert_eq!(evaluation["status"], "running");
    assert_eq!(evaluation["queue_position"], Value::Null);
    let evaluated = evaluation_ended(&server, bc_id);
    let result = &evaluated["evaluation"];
    assert_eq!(result["status"], "done", "{evaluated}");
    assert_eq!(result["episodes"], 10);
    let successes = (result["success_rate"].as_f64().unwrap() * 10.0).round() as u64;
    let failures: u64 = result["failures"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(
        successes + failures,
        10,
        "every episode is a success or a counted failure"
    );
    assert_eq!(result["noise_scale"], 1.0);
    assert_eq!(result["calibration_scale"], 1.0);
    assert_eq!(result["fault"], Value::Null);

    // Under a mismatch: the values are checked naming the field, and kept with the evaluation.
    let evaluate = format!("/api/policies/{bc_id}/evaluate");
    for (body, field) in [
        (json!({"noise_scale": 16.5}), "noise_scale"),
        (json!({"calibration_scale": -1}), "calibration_scale"),
        (json!({"fault": "gravity"}), "fault"),
    ] {
        let (status, refused) = server.post(&evaluate, Some(&admin), Some(body.clone()));
        assert_eq!(status, 422, "{body}: {refused}");
        let message = refused["error"]["message"].as_str().unwrap();
        assert!(message.contains(field), "{body}: {message}");
    }
    let (status, evaluation) = server.post(
        &evaluate,
        Some(&admin),
        Some(
            json!({"episodes": 3, "seed": 3, "noise_scale": 2, "calibration_scale": 0,
                    "fault": "occlusion"}),
        ),
    );
    assert_eq!(status, 202, "{evaluation}");
    assert_eq!(evaluation["noise_scale"], 2.0);
    assert_eq!(evaluation["calibration_scale"], 0.0);
    assert_eq!(evaluation["fault"], "occlusion");
    let evaluated = evaluation_ended(&server, bc_id);
    assert_eq!(evaluated["evaluation"]["status"], "done", "{evaluated}");
    assert_eq!(evaluated["evaluation"]["fault"], "occlusion");

    // On drawn cells: the cells' noise and calibration are drawn, so neither may be given.
    let (status, refused) = server.post(
        &evaluate,
        Some(&admin),
        Some(json!({"randomise_cells": true, "noise_scale": 2})),
    );
    assert_eq!(status, 422, "{refused}");
    let message = refused["error"]["message"].as_str().unwrap();
    assert!(message.contains("leave out noise_scale"), "{message}");
    let (status, across) = upload(&server, &admin, "across-cells", ACROSS_CELLS);
    assert_eq!(status, 201, "{across}");
    let across_id = across["id"].as_i64().unwrap();
    let (status, evaluation) = server.post(
        &format!("/api/policies/{across_id}/evaluate"),
        Some(&admin),
        Some(json!({"episodes": 4, "seed": 5, "randomise_cells": true})),
    );
    assert_eq!(status, 202, "{evaluation}");
    assert_eq!(evaluation["randomise_cells"], true);
    let evaluated = evaluation_ended(&server, across_id);
    let result = &evaluated["evaluation"];
    assert_eq!(result["status"], "done", "{evaluated}");
    // The same as `celld eval --randomise-cells` runs on this cell, episode for episode.
    let expected = drawn_cells_summary(ACROSS_CELLS, 4, 5);
    assert_eq!(result["success_rate"], expected.success_rate, "{result}");
    assert_eq!(result["avg_steps"], json!(expected.avg_steps), "{result}");
    // The gate reads no evaluation on drawn cells.
    let (status, refused) = server.post(
        &format!("/api/policies/{across_id}/activate"),
        Some(&admin),
        None,
    );
    assert_eq!(status, 409, "{refused}");

    // The gate reads the evaluation without a mismatch.
    let (status, activated) = server.post(
        &format!("/api/policies/{bc_id}/activate"),
        Some(&admin),
        None,
    );
    assert_eq!(status, 200, "{activated}");
    assert_eq!(activated["policy"]["status"], "active");

    // A job on "active" runs and records that policy.
    let job = server.create_job(&admin, json!({"controller": "active", "seed": 4}));
    assert_eq!(job["policy_id"], bc_id);
    assert_eq!(job["controller"], format!("policy:{bc_id}"));
    let done = server.wait_final(job["id"].as_i64().unwrap());
    assert!(done["steps"].as_i64().unwrap() > 0, "{done}");

    // Activate the bundled one (evaluated at start), then roll back to bc.
    evaluation_ended(&server, bundled_id);
    let (status, swapped) = server.post(
        &format!("/api/policies/{bundled_id}/activate"),
        Some(&admin),
        None,
    );
    assert_eq!(status, 200, "{swapped}");
    assert_eq!(swapped["retired"], bc_id);
    let (_, old) = server.get(&format!("/api/policies/{bc_id}"), Some(&admin));
    assert_eq!(old["status"], "retired");
    let (status, back) = server.post(
        &format!("/api/policies/{bc_id}/activate"),
        Some(&admin),
        None,
    );
    assert_eq!(status, 200, "rollback: {back}");
    assert_eq!(back["retired"], bundled_id);
    let job = server.create_job(&admin, json!({"controller": "active"}));
    assert_eq!(job["policy_id"], bc_id);
}

/// `celld eval --controller FILE --randomise-cells --episodes N --seed S` on the reference cell,
/// in process.
fn drawn_cells_summary(bytes: &[u8], episodes: usize, seed: u64) -> eval::EvalSummary {
    use assembly_cell::config::cell::CellConfig;
    use assembly_cell::policy::learned::LearnedPolicy;
    use assembly_cell::sim::EnvOptions;
    use assembly_cell::sim::randomise::CellRanges;
    let policy = LearnedPolicy::from_bytes(bytes).unwrap();
    let cell = CellConfig::reference();
    let options = EnvOptions {
        kept_robots: eval::DEFAULT_KEPT_ROBOTS,
        ..EnvOptions::from_cell(&cell)
    };
    let controller =
        |_: &CellConfig| Box::new(policy.clone()) as Box<dyn assembly_cell::policy::Controller>;
    let ranges = CellRanges::default();
    eval::evaluate_on_drawn_cells(
        &cell,
        &ranges,
        options,
        episodes,
        seed,
        &controller,
        &|_| {},
    )
    .0
}

#[test]
fn a_flat_td3_policy_uploads_evaluates_and_runs() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(
        dir.path(),
        &[
            ("CELLD_STEP_PERIOD_MS", "5"),
            ("CELLD_ACTIVATION_THRESHOLD", "0"),
        ],
    );
    let admin = server.admin.clone();
    let (status, td3) = upload(&server, &admin, "td3", TD3);
    assert_eq!(status, 201, "{td3}");
    assert_eq!(td3["metadata"]["format"], "assembly-cell/flat-policy");
    assert_eq!(td3["shapes"]["actor.4.weight"], json!([6, 256]));
    let id = td3["id"].as_i64().unwrap();
    let (status, evaluation) = server.post(
        &format!("/api/policies/{id}/evaluate"),
        Some(&admin),
        Some(json!({"episodes": 5, "seed": 3})),
    );
    assert_eq!(status, 202, "{evaluation}");
    let evaluated = evaluation_ended(&server, id);
    assert_eq!(evaluated["evaluation"]["status"], "done", "{evaluated}");
    let (status, activated) =
        server.post(&format!("/api/policies/{id}/activate"), Some(&admin), None);
    assert_eq!(status, 200, "{activated}");
    let job = server.create_job(&admin, json!({"controller": "active", "seed": 4}));
    assert_eq!(job["controller"], format!("policy:{id}"));
    let done = server.wait_final(job["id"].as_i64().unwrap());
    assert!(done["steps"].as_i64().unwrap() > 0, "{done}");
    // The bundled one by name.
    let job = server.create_job(&admin, json!({"controller": "td3", "seed": 5}));
    let done = server.wait_final(job["id"].as_i64().unwrap());
    assert!(done["steps"].as_i64().unwrap() > 0, "{done}");

    // A flat file that breaks its format is refused naming the tensor: renaming a tensor in
    // the header (same length, so the layout holds) leaves `actor.4.bias` missing.
    let header_len = u64::from_le_bytes(TD3[..8].try_into().unwrap()) as usize;
    let header = std::str::from_utf8(&TD3[8..8 + header_len]).unwrap();
    let mut broken = TD3[..8].to_vec();
    broken.extend_from_slice(header.replace("actor.4.bias", "actor.9.bias").as_bytes());
    broken.extend_from_slice(&TD3[8 + header_len..]);
    let (status, refused) = upload(&server, &admin, "broken", &broken);
    assert_eq!(status, 422, "{refused}");
    let message = refused["error"]["message"].as_str().unwrap();
    assert!(
        message.contains("tensor `actor.4.bias` is missing: a flat policy"),
        "{message}"
    );
}

#[test]
fn the_gate_holds_unless_forced_with_a_reason() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[]);
    let admin = server.admin.clone();
    // The flat TD3 baseline never succeeds (docs/learning-reference.md): evaluated, it is below the gate.
    let (_, td3) = upload(&server, &admin, "td3", TD3);
    let id = td3["id"].as_i64().unwrap();

    // Evaluated, but below the default 0.95.
    server.post(
        &format!("/api/policies/{id}/evaluate"),
        Some(&admin),
        Some(json!({"episodes": 5})),
    );
    let evaluated = evaluation_ended(&server, id);
    assert!(evaluated["evaluation"]["success_rate"].as_f64().unwrap() < 0.95);
    let (status, refused) =
        server.post(&format!("/api/policies/{id}/activate"), Some(&admin), None);
    assert_eq!(status, 409, "{refused}");
    assert!(
        refused["error"]["message"]
            .as_str()
            .unwrap()
            .contains("0.95"),
        "{refused}"
    );

    let (status, no_reason) = server.post(
        &format!("/api/policies/{id}/activate"),
        Some(&admin),
        Some(json!({"force": true})),
    );
    // The gate stays shut: forcing it needs a reason.
    assert_eq!(status, 409, "{no_reason}");
    assert!(
        no_reason["error"]["message"]
            .as_str()
            .unwrap()
            .contains("needs a reason"),
        "{no_reason}"
    );
    let (status, forced) = server.post(
        &format!("/api/policies/{id}/activate"),
        Some(&admin),
        Some(json!({"force": true, "reason": "commissioning test on the twin"})),
    );
    assert_eq!(status, 200, "{forced}");
    assert_eq!(forced["forced"], true);
    assert_eq!(forced["policy"]["status"], "active");

    let (_, audit) = server.get("/api/audit", Some(&admin));
    let entry = audit["items"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["action"] == "policy.activate")
        .expect("the forced activation is audited")
        .clone();
    assert_eq!(entry["detail"]["force"], true);
    assert_eq!(entry["detail"]["reason"], "commissioning test on the twin");
    assert_eq!(entry["actor"], "admin");
}

/// An evaluation with other rules than the cell's (`rules`) is stored with them and does not
/// open the gate; one with the cell's own does. A selection naming no rule is refused by name.
#[test]
fn an_evaluation_under_other_rules_is_kept_with_them_and_not_read_by_the_gate() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[]);
    let admin = server.admin.clone();
    // The reference-cell network succeeds on the reference cell with no rule too (0.99 of 2000
    // episodes), so only the rules can keep the gate shut.
    let (_, reference) = upload(&server, &admin, "reference", REFERENCE);
    let id = reference["id"].as_i64().unwrap();
    let evaluate = format!("/api/policies/{id}/evaluate");
    let (status, refused) = server.post(
        &evaluate,
        Some(&admin),
        Some(json!({"episodes": 5, "rules": ["full_step", "no_such_rule"]})),
    );
    assert_eq!(status, 422, "{refused}");
    assert!(refused.to_string().contains("no_such_rule"), "{refused}");

    let (status, started) = server.post(
        &evaluate,
        Some(&admin),
        Some(json!({"episodes": 10, "rules": "none"})),
    );
    assert_eq!(status, 202, "{started}");
    assert_eq!(started["rules"], "none");
    let bare = evaluation_ended(&server, id);
    assert_eq!(bare["evaluation"]["rules"], "none", "{bare}");
    assert!(
        bare["evaluation"]["success_rate"].as_f64().unwrap() >= 0.95,
        "{bare}"
    );
    let (status, shut) = server.post(&format!("/api/policies/{id}/activate"), Some(&admin), None);
    assert_eq!(status, 409, "{shut}");

    server.post(&evaluate, Some(&admin), Some(json!({"episodes": 10})));
    let ruled = loop {
        let ended = evaluation_ended(&server, id);
        if ended["evaluation"]["rules"] == "all" {
            break ended;
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(
        ruled["evaluation"]["success_rate"].as_f64().unwrap() >= 0.95,
        "{ruled}"
    );
    let (status, activated) =
        server.post(&format!("/api/policies/{id}/activate"), Some(&admin), None);
    assert_eq!(status, 200, "{activated}");
}

/// The safetensors pieces of a good file, to break one thing at a time: tensor name → (header
/// entry, bytes), laid out again on encoding.
struct Parts {
    metadata: Value,
    tensors: Vec<(String, Value, Vec<u8>)>,
}

fn parts() -> Parts {
    let n = u64::from_le_bytes(REFERENCE[..8].try_into().unwrap()) as usize;
    let header: Map<String, Value> = serde_json::from_slice(&REFERENCE[8..8 + n]).unwrap();
    let data = &REFERENCE[8 + n..];
    let mut parts = Parts {
        metadata: header["__metadata__"].clone(),
        tensors: Vec::new(),
    };
    for (name, info) in header.into_iter().filter(|(k, _)| k != "__metadata__") {
        let at = |i: usize| info["data_offsets"][i].as_u64().unwrap() as usize;
        let bytes = data[at(0)..at(1)].to_vec();
        parts.tensors.push((name, info, bytes));
    }
    parts
}

impl Parts {
    fn encode(&self) -> Vec<u8> {
        let mut header = Map::new();
        header.insert("__metadata__".into(), self.metadata.clone());
        let mut data = Vec::new();
        for (name, info, bytes) in &self.tensors {
            let mut info = info.clone();
            info["data_offsets"] = json!([data.len(), data.len() + bytes.len()]);
            data.extend_from_slice(bytes);
            header.insert(name.clone(), info);
        }
        let header = serde_json::to_vec(&header).unwrap();
        let mut out = (header.len() as u64).to_le_bytes().to_vec();
        out.extend_from_slice(&header);
        out.extend_from_slice(&data);
        out
    }

    fn tensor(&mut self, name: &str) -> &mut (String, Value, Vec<u8>) {
        self.tensors.iter_mut().find(|t| t.0 == name).unwrap()
    }
}

#[test]
fn each_malformed_upload_is_refused_with_its_own_message() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[("CELLD_MAX_POLICY_BYTES", "200000")]);
    let admin = server.admin.clone();
    let stored_before = policy_count(&server);

    let mut cases: Vec<(&str, Vec<u8>, u16, &str)> = Vec::new();
    cases.push((
        "not safetensors",
        b"PK\x03\x04 a zip file".to_vec(),
        422,
        "header",
    ));
    cases.push((
        "truncated",
        REFERENCE[..REFERENCE.len() - 100].to_vec(),
        422,
        "truncated",
    ));
    let mut long = REFERENCE.to_vec();
    long[..8].copy_from_slice(&(REFERENCE.len() as u64).to_le_bytes());
    cases.push((
        "header longer than the file",
        long,
        422,
        "longer than the file",
    ));
    let mut p = parts();
    p.tensors.retain(|t| t.0 != "ori.4.bias");
    cases.push(("missing tensor", p.encode(), 422, "ori.4.bias"));
    let mut p = parts();
    p.tensor("obs_mean").1["shape"] = json!([3, 4]);
    cases.push(("wrong shape", p.encode(), 422, "obs_mean"));
    let mut p = parts();
    // F16 with twice the elements: the same bytes, so only the dtype is wrong.
    p.tensor("pos.0.bias").1["dtype"] = json!("F16");
    p.tensor("pos.0.bias").1["shape"] = json!([128]);
    cases.push(("f16", p.encode(), 422, "pos.0.bias"));
    let mut p = parts();
    p.tensor("high.head.bias").2[..4].copy_from_slice(&f32::NAN.to_le_bytes());
    cases.push(("NaN weights", p.encode(), 422, "high.head.bias"));
    let mut p = parts();
    p.metadata["format"] = json!("onnx");
    cases.push(("wrong metadata", p.encode(), 422, "format"));

    for (what, bytes, status, named) in cases {
        let (got, answer) = upload(&server, &admin, "bad", &bytes);
        assert_eq!(got, status, "{what}: {answer}");
        let message = answer["error"]["message"]
            .as_str()
            .unwrap_or_else(|| panic!("{what}: {answer}"));
        assert!(
            message.contains(named),
            "{what}: `{message}` should name `{named}`"
        );
    }
    let (status, answer) = server.post_announcing(
        "/api/policies?name=big",
        &admin,
        "application/octet-stream",
        300_000,
    );
    assert_eq!(status, 413, "over the cap: {answer}");
    let message = answer["error"]["message"].as_str().unwrap();
    assert!(message.contains("limit is 200000"), "{message}");
    // A small body where the refusal comes before the body is read: a large one could still
    // be on its way when the server closes the connection.
    let (status, _) = upload(&server, &admin, "", b"x");
    assert_eq!(status, 400, "a policy needs a name");
    assert_eq!(
        policy_count(&server),
        stored_before,
        "nothing refused was stored"
    );

    // Roles: only an admin uploads, evaluates or activates.
    let operator = server.token("operator");
    // A small body: the refusal comes before the body is read, and a large one could still be
    // on its way when the server closes the connection.
    let (status, _) = upload(&server, &operator, "bc", b"x");
    assert_eq!(status, 403);
    let (status, _) = server.post("/api/policies/1/activate", Some(&operator), None);
    assert_eq!(status, 403);
    let (status, _) = server.post("/api/policies/1/evaluate", Some(&operator), None);
    assert_eq!(status, 403);
}
