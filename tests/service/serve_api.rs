//! `celld serve` over HTTP: a real server on a free port with a real SQLite file.

use crate::serve_support;

use serde_json::{Value, json};
use serve_support::Server;
use std::io::BufRead;
use std::time::{Duration, Instant};

/// 20 ms per control step: an expert job (about 47 steps) takes about a second.
const QUICK: [(&str, &str); 1] = [("CELLD_STEP_PERIOD_MS", "20")];
/// 60 ms per step: a job runs long enough to be caught running.
const SLOW: [(&str, &str); 1] = [("CELLD_STEP_PERIOD_MS", "60")];

fn id(job: &Value) -> i64 {
    job["id"].as_i64().unwrap()
}

#[test]
fn jobs_run_in_order_and_every_step_is_stored() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &QUICK);
    let operator = server.token("operator");
    let first = server.create_job(&operator, json!({"controller": "expert", "seed": 1}));
    let second = server.create_job(&operator, json!({"controller": "active", "seed": 2}));
    assert_eq!(first["status"], "queued");
    assert_eq!(
        second["controller"], "expert",
        "`active` is the expert until a policy is"
    );

    // The runner takes the first job off the queue within a step or two (on a loaded machine,
    // not at once); the second then waits for the robot. The control thread takes the second
    // job in between steps of the first, so the cell's queue may show it a step after the
    // first job starts.
    let cell = server.poll(
        "/api/cell",
        "took the first job, the second waiting",
        Duration::from_secs(5),
        |cell| !cell["current_job"].is_null() && cell["queue_length"] == 1,
    );
    assert_eq!(cell["current_job"], id(&first), "{cell}");
    assert_eq!(cell["queue"], json!([id(&second)]), "{cell}");

    for job in [&first, &second] {
        let done = server.wait_final(id(job));
        assert_eq!(done["status"], "succeeded", "{done}");
        let steps = server.steps(id(job));
        assert_eq!(steps.len() as i64, done["steps"].as_i64().unwrap());
        assert!(steps.len() > 10);
        for (index, step) in steps.iter().enumerate() {
            assert_eq!(step["step"], index as i64 + 1);
            assert_eq!(step["state"].as_array().unwrap().len(), 12);
            assert_eq!(step["action"].as_array().unwrap().len(), 6);
            assert_eq!(step["legs_mm"].as_array().unwrap().len(), 6);
        }
        let total: f64 = steps
            .iter()
            .map(|s| s["reward"]["total"].as_f64().unwrap())
            .sum();
        assert!((total - done["reward"].as_f64().unwrap()).abs() < 1e-6);
        assert!(
            done["final_errors"]["depth_error_mm"]
                .as_f64()
                .unwrap()
                .abs()
                <= 0.05
        );
    }
    let a = server.job(id(&first));
    let b = server.job(id(&second));
    assert!(b["started_at"].as_str().unwrap() >= a["finished_at"].as_str().unwrap());

    // The CSV has a header and one line per step.
    let response = ureq::get(format!(
        "{}/api/jobs/{}/steps?format=csv",
        server.base,
        id(&first)
    ))
    .header("Authorization", format!("Bearer {operator}"))
    .call()
    .unwrap()
    .into_body()
    .read_to_string()
    .unwrap();
    let lines: Vec<&str> = response.lines().collect();
    assert!(lines[0].starts_with("step,t_s,state_0"));
    assert_eq!(lines.len() as i64, a["steps"].as_i64().unwrap() + 1);

    let (status, page) = server.get("/api/jobs?status=succeeded&limit=1", Some(&operator));
    assert_eq!(status, 200);
    assert_eq!(page["total"], 2);
    assert_eq!(page["items"].as_array().unwrap().len(), 1);
    assert_eq!(page["items"][0]["id"], id(&second), "newest first");

    // Time filters compare with the stored creation times; the policy filter with the job's
    // policy (the bundled one is registered as policy 1 at the first start).
    let since_first = format!("/api/jobs?since={}", a["created_at"].as_str().unwrap());
    let policy_job = server.create_job(&operator, json!({"controller": "policy:1", "seed": 3}));
    server.wait_final(id(&policy_job));
    for (query, expected) in [
        (since_first.as_str(), 3),
        ("/api/jobs?since=2999-01-01", 0),
        ("/api/jobs?until=2000-01-01", 0),
        ("/api/jobs?until=2999-01-01T00:00:00Z", 3),
        ("/api/jobs?policy_id=1", 1),
        ("/api/jobs?policy_id=1&status=running", 0),
        ("/api/jobs?policy_id=2", 0),
    ] {
        let (status, page) = server.get(query, Some(&operator));
        assert_eq!(status, 200, "{query}: {page}");
        assert_eq!(page["total"], expected, "{query}: {page}");
    }
    let (_, page) = server.get("/api/jobs?policy_id=1", Some(&operator));
    assert_eq!(page["items"][0]["id"], id(&policy_job));

    // The two expert jobs succeeded; the policy job counts as it ended.
    let (_, policy_job) = server.get(&format!("/api/jobs/{}", id(&policy_job)), Some(&operator));
    let succeeded = 2 + u64::from(policy_job["status"] == "succeeded");
    let (_, stats) = server.get("/api/stats?by=controller", Some(&operator));
    assert_eq!(stats["total"]["succeeded"], succeeded, "{stats}");
    assert_eq!(stats["groups"][0]["key"], "expert");

    let (_, metrics) = server.get("/metrics", None);
    let metrics = metrics.as_str().unwrap().to_string();
    assert!(
        metrics.contains(&format!(
            "celld_jobs_total{{status=\"succeeded\",reason=\"none\"}} {succeeded}"
        )),
        "{metrics}"
    );
}

#[test]
fn cancel_estop_and_reset() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &SLOW);
    let operator = server.token("operator");

    let job = server.create_job(&operator, json!({"controller": "expert", "seed": 3}));
    server.wait_job(id(&job), "ran", |j| j["status"] == "running");
    let (status, cancelled) = server.post(
        &format!("/api/jobs/{}/cancel", id(&job)),
        Some(&operator),
        None,
    );
    assert_eq!(status, 200, "{cancelled}");
    assert_eq!(cancelled["status"], "cancelled");
    let (status, again) = server.post(
        &format!("/api/jobs/{}/cancel", id(&job)),
        Some(&operator),
        None,
    );
    assert_eq!(status, 409, "{again}");

    let job = server.create_job(&operator, json!({"controller": "expert", "seed": 4}));
    let queued = server.create_job(&operator, json!({"controller": "expert", "seed": 5}));
    server.wait_job(id(&job), "took a step", |j| j["status"] == "running");
    while server.steps(id(&job)).len() < 2 {
        std::thread::sleep(Duration::from_millis(20));
    }
    let (status, cell) = server.post("/api/cell/estop", Some(&operator), None);
    assert_eq!(status, 200, "{cell}");
    assert_eq!(cell["estop_latched"], true);
    let stopped = server.job(id(&job));
    assert_eq!(stopped["status"], "failed");
    assert_eq!(stopped["failure_reason"], "estop");
    let dropped = server.wait_final(id(&queued));
    assert_eq!(dropped["status"], "cancelled");
    assert_eq!(dropped["failure_reason"], "estop");

    let (status, refused) = server.post(
        "/api/jobs",
        Some(&operator),
        Some(json!({"controller": "expert"})),
    );
    assert_eq!(status, 409, "no job while latched: {refused}");
    assert!(
        refused["error"]["message"]
            .as_str()
            .unwrap()
            .contains("e-stop")
    );

    let steps_at_stop = server.steps(id(&job)).len();
    let (status, cell) = server.post("/api/cell/reset", Some(&operator), None);
    assert_eq!(status, 200);
    assert_eq!(cell["estop_latched"], false);
    std::thread::sleep(Duration::from_millis(400));
    let (_, cell) = server.get("/api/cell", Some(&operator));
    assert_eq!(
        cell["current_job"],
        Value::Null,
        "reset starts nothing: {cell}"
    );
    assert_eq!(
        server.steps(id(&job)).len(),
        steps_at_stop,
        "no motion after reset"
    );
    assert_eq!(
        server.job(id(&job))["steps"].as_i64().unwrap() as usize,
        steps_at_stop
    );

    let (_, audit) = server.get("/api/audit", Some(&server.admin));
    let actions: Vec<&str> = audit["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["action"].as_str().unwrap())
        .collect();
    assert!(
        actions.contains(&"cell.estop") && actions.contains(&"cell.reset"),
        "{actions:?}"
    );

    // The queue is bounded: past 100 waiting jobs a new one is refused, naming the limit. (The
    // count read is the control thread's last published one, so a few more may slip in.)
    let mut created = 0;
    let refused = loop {
        let (status, body) = server.post(
            "/api/jobs",
            Some(&operator),
            Some(json!({"controller": "expert", "seed": created})),
        );
        match status {
            201 => created += 1,
            409 => break body,
            _ => panic!("{status}: {body}"),
        }
        assert!(created < 200, "200 jobs taken without a refusal");
    };
    assert!(created >= 100, "refused after {created}: {refused}");
    let message = refused["error"]["message"].as_str().unwrap();
    assert!(message.contains("at most 100"), "{message}");
    let (status, _) = server.post("/api/cell/estop", Some(&operator), None);
    assert_eq!(status, 200);
}

#[test]
fn roles_are_enforced() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &QUICK);
    let viewer = server.token("viewer");
    let operator = server.token("operator");

    let (status, body) = server.get("/api/jobs", None);
    assert_eq!(status, 401, "{body}");
    let (status, _) = server.get("/api/jobs", Some("celld_not_a_token"));
    assert_eq!(status, 401);
    let (status, _) = server.get("/api/jobs", Some(&viewer));
    assert_eq!(status, 200);
    let (status, body) = server.post(
        "/api/jobs",
        Some(&viewer),
        Some(json!({"controller": "expert"})),
    );
    assert_eq!(status, 403, "{body}");
    assert!(
        body["error"]["message"]
            .as_str()
            .unwrap()
            .contains("operator")
    );
    let (status, _) = server.post("/api/cell/estop", Some(&viewer), None);
    assert_eq!(status, 403);
    let (status, body) = server.post(
        "/api/tokens",
        Some(&operator),
        Some(json!({"role": "admin", "name": "sneaky"})),
    );
    assert_eq!(status, 403, "{body}");
    let (status, _) = server.get("/api/audit", Some(&operator));
    assert_eq!(status, 403);
    for open in ["/api/health", "/metrics", "/api/openapi.json"] {
        assert_eq!(server.get(open, None).0, 200, "{open}");
    }
    let (_, health) = server.get("/api/health", None);
    assert_eq!(
        (&health["database"], &health["control_thread"]),
        (&json!(true), &json!(true)),
        "{health}"
    );
    let (_, jobs) = server.get("/api/jobs", Some(&viewer));
    assert_eq!(jobs["total"], 0, "refused requests created nothing");

    // Each token can read what its own role may do (the dashboard shows only that).
    assert_eq!(server.get("/api/me", None).0, 401);
    for (token, role, operate, administer) in [
        (&viewer, "viewer", false, false),
        (&operator, "operator", true, false),
        (&server.admin, "admin", true, true),
    ] {
        let (status, me) = server.get("/api/me", Some(token));
        assert_eq!(status, 200);
        assert_eq!(me["role"], role);
        assert_eq!(me["may"]["operate"], operate, "{me}");
        assert_eq!(me["may"]["administer"], administer, "{me}");
    }
}

#[test]
fn bad_input_is_named_and_leaves_the_running_job_alone() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &QUICK);
    let operator = server.token("operator");
    let job = server.create_job(&operator, json!({"controller": "expert", "seed": 9}));

    let cases: Vec<(&str, Vec<u8>, u16, &str)> = vec![
        ("malformed JSON", b"{\"controller\": ".to_vec(), 400, "JSON"),
        (
            "unknown controller",
            br#"{"controller": "teleport"}"#.to_vec(),
            422,
            "teleport",
        ),
        (
            "wrong type",
            br#"{"controller": 5}"#.to_vec(),
            422,
            "controller",
        ),
        (
            "unknown field",
            br#"{"controller": "expert", "speed": 3}"#.to_vec(),
            422,
            "speed",
        ),
        (
            "negative offset",
            br#"{"controller": "expert", "initial": {"pos_mm": -1, "ori_deg": 1}}"#.to_vec(),
            422,
            "initial.pos_mm",
        ),
        (
            "missing policy",
            br#"{"controller": "policy:42"}"#.to_vec(),
            404,
            "42",
        ),
    ];
    for (what, body, expected, named) in cases {
        let (status, answer) = server.post_raw("/api/jobs", &operator, "application/json", &body);
        assert_eq!(status, expected, "{what}: {answer}");
        let message = answer["error"]["message"]
            .as_str()
            .unwrap_or_else(|| panic!("{what}: {answer}"));
        assert!(
            message.contains(named),
            "{what}: `{message}` should name `{named}`"
        );
    }
    let (status, answer) =
        server.post_announcing("/api/jobs", &operator, "application/json", 2 << 20);
    assert_eq!(status, 413, "oversized body: {answer}");
    assert!(
        answer["error"]["message"]
            .as_str()
            .unwrap()
            .contains("length limit"),
        "{answer}"
    );
    let (status, answer) = server.post_raw(
        "/api/jobs",
        &operator,
        "text/plain",
        br#"{"controller": "expert"}"#,
    );
    assert_eq!(status, 415, "{answer}");
    let (status, answer) = server.get("/api/jobs?status=sleeping", Some(&operator));
    assert_eq!(status, 400);
    assert!(
        answer["error"]["message"]
            .as_str()
            .unwrap()
            .contains("sleeping")
    );
    let (status, _) = server.get("/api/jobs?limit=lots", Some(&operator));
    assert_eq!(status, 400);
    let (status, answer) = server.get("/api/jobs/999", Some(&operator));
    assert_eq!(status, 404, "{answer}");
    // An id that is not a number names nothing there is.
    let (status, _) = server.get("/api/jobs/first", Some(&operator));
    assert_eq!(status, 404);
    for query in ["/api/stats?since=yesterday", "/api/jobs?until=yesterday"] {
        let (status, answer) = server.get(query, Some(&operator));
        assert_eq!(status, 400, "{query}");
        assert!(
            answer["error"]["message"]
                .as_str()
                .unwrap()
                .contains("yesterday"),
            "{answer}"
        );
    }
    let (status, _) = server.get("/api/jobs?policy_id=bundled", Some(&operator));
    assert_eq!(status, 400);
    let (status, answer) = server.get("/api/nowhere", Some(&operator));
    assert_eq!(status, 404);
    assert!(answer["error"].is_object());

    let done = server.wait_final(id(&job));
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(
        server.steps(id(&job)).len() as i64,
        done["steps"].as_i64().unwrap()
    );
    let (_, jobs) = server.get("/api/jobs", Some(&operator));
    assert_eq!(jobs["total"], 1, "no refused request stored a job");
}

#[test]
fn telemetry_streams_a_running_jobs_steps() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &QUICK);
    let viewer = server.token("viewer");
    let operator = server.token("operator");

    // The token in the query, as a browser's EventSource must send it.
    let stream = ureq::get(format!(
        "{}/api/telemetry?access_token={viewer}",
        server.base
    ))
    .call()
    .expect("subscribe");
    assert!(
        stream.headers()["content-type"]
            .to_str()
            .unwrap()
            .starts_with("text/event-stream")
    );
    let mut lines = std::io::BufReader::new(stream.into_body().into_reader()).lines();
    // First, at once, the latches as they are.
    assert_eq!(lines.next().unwrap().unwrap(), "event: cell");
    assert_eq!(
        lines.next().unwrap().unwrap(),
        "data: {\"driver_latch\":null,\"estop_latched\":false}"
    );

    let job = server.create_job(&operator, json!({"controller": "expert", "seed": 12}));
    let started = Instant::now();
    let mut event = String::new();
    let mut steps_seen = 0;
    loop {
        assert!(started.elapsed() < Duration::from_secs(60), "no end event");
        let line = lines.next().expect("the stream stays open").unwrap();
        if let Some(name) = line.strip_prefix("event: ") {
            event = name.to_string();
        } else if let Some(data) = line.strip_prefix("data: ") {
            let data: Value = serde_json::from_str(data).unwrap();
            if event == "step" && data["job_id"] == id(&job) {
                steps_seen += 1;
                assert_eq!(
                    data["step"], steps_seen,
                    "steps arrive in order, none missing"
                );
            }
            if event == "job" && data["job_id"] == id(&job) && data["status"] == "succeeded" {
                assert_eq!(data["steps"], steps_seen);
                break;
            }
        }
    }
    assert!(steps_seen > 10);

    let (status, _) = server.get("/api/telemetry", None);
    assert_eq!(status, 401, "the stream needs a token too");
}

/// A learned policy's job keeps, at every step, the policy's own proposal and the rules that
/// changed it, stored as streamed; where no rule fired the move made is the proposal, but for
/// the clamp of each translation component to the step limit. The expert proposes nothing of
/// its own.
#[test]
fn a_learned_jobs_steps_keep_its_proposals_and_the_rules_that_changed_them() {
    use assembly_cell::policy::shield::RuleId;
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &QUICK);
    let operator = server.token("operator");
    let stream = ureq::get(format!(
        "{}/api/telemetry?access_token={}",
        server.base, server.admin
    ))
    .call()
    .expect("subscribe");
    let mut lines = std::io::BufReader::new(stream.into_body().into_reader()).lines();

    let learned = server.create_job(
        &operator,
        json!({"controller": "hierarchical-swift-cells", "seed": 5}),
    );
    let started = Instant::now();
    let (mut event, mut streamed) = (String::new(), Vec::new());
    loop {
        assert!(started.elapsed() < Duration::from_secs(60), "no end event");
        let line = lines.next().expect("the stream stays open").unwrap();
        if let Some(name) = line.strip_prefix("event: ") {
            event = name.to_string();
        } else if let Some(data) = line.strip_prefix("data: ") {
            let data: Value = serde_json::from_str(data).unwrap();
            if data["job_id"] != id(&learned) {
                continue;
            }
            match event.as_str() {
                "step" => streamed.push(data),
                "job" if data["status"] != "running" => break,
                _ => {}
            }
        }
    }
    let done = server.wait_final(id(&learned));
    let steps = server.steps(id(&learned));
    assert_eq!(
        steps.len() as i64,
        done["steps"].as_i64().unwrap(),
        "{done}"
    );
    assert!(steps.len() > 5, "{done}");
    assert_eq!(streamed.len(), steps.len(), "every step streamed");

    let numbers = |value: &Value| -> Vec<f64> {
        let items = value.as_array().unwrap_or_else(|| panic!("{value}"));
        items.iter().map(|v| v.as_f64().unwrap()).collect()
    };
    let (mut shaped, mut limits) = (0, Vec::new());
    for (step, live) in steps.iter().zip(&streamed) {
        assert_eq!(
            (&step["proposed"], &step["rules"]),
            (&live["proposed"], &live["rules"]),
            "stored as streamed"
        );
        let proposed = numbers(&step["proposed"]);
        let made = numbers(&step["action"]);
        assert_eq!(proposed.len(), 6, "{step}");
        let rules = step["rules"].as_array().unwrap();
        for rule in rules {
            let name = rule.as_str().unwrap();
            assert!(RuleId::from_name(name).is_some(), "{name} is no rule");
        }
        if !rules.is_empty() {
            shaped += 1;
            continue;
        }
        assert_eq!(made[3..], proposed[3..], "no rule turns: {step}");
        for (m, p) in made[..3].iter().zip(&proposed[..3]) {
            if m != p {
                // Clamped: the limit's sign is the proposal's, the proposal beyond it.
                assert!(m.signum() == p.signum() && p.abs() > m.abs(), "{step}");
                limits.push(m.abs());
            }
        }
    }
    assert!(shaped > 0, "some rule changed some move: {steps:?}");
    assert!(
        limits.windows(2).all(|pair| pair[0] == pair[1]),
        "one step limit clamps every component: {limits:?}"
    );

    let expert = server.create_job(&operator, json!({"controller": "expert", "seed": 5}));
    server.wait_final(id(&expert));
    let steps = server.steps(id(&expert));
    assert!(!steps.is_empty());
    for step in &steps {
        assert_eq!(
            (&step["proposed"], &step["rules"]),
            (&Value::Null, &json!([])),
            "{step}"
        );
    }
}

/// Every operation the served OpenAPI document describes is a route of the running server: asked
/// without a token, none answers "no such route" or "method not allowed" (the protected ones
/// answer 401, the open ones 200).
#[test]
fn every_described_operation_is_served() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &QUICK);
    let (status, document) = server.get("/api/openapi.json", None);
    assert_eq!(status, 200);
    assert_eq!(
        document["openapi"].as_str().unwrap().chars().next(),
        Some('3')
    );
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .http_status_as_error(false)
        .build()
        .into();
    let mut operations = 0;
    for (path, item) in document["paths"].as_object().unwrap() {
        let url = format!("{}{}", server.base, path.replace("{id}", "1"));
        for method in item.as_object().unwrap().keys() {
            let answer = match method.as_str() {
                "get" => agent.get(&url).call(),
                "post" => agent.post(&url).send_empty(),
                "delete" => agent.delete(&url).call(),
                other => panic!("{other} {path}: a method the test does not send"),
            };
            let mut answer = answer.expect("the server answers");
            let status = answer.status().as_u16();
            let body = answer.body_mut().read_to_string().unwrap_or_default();
            operations += 1;
            assert!(
                status != 405 && !body.contains("no such route"),
                "{method} {path}: {status} {body}"
            );
            let public = ["/api/health", "/metrics", "/api/openapi.json"];
            let expected = if public.contains(&path.as_str()) {
                200
            } else {
                401
            };
            assert_eq!(status, expected, "{method} {path}: {body}");
        }
    }
    assert_eq!(
        operations, 42,
        "the document describes {operations} operations"
    );
}

/// With `control.cpu` naming a CPU, the kernel keeps the control thread and camera ingestion
/// (which takes turns with it) on it and every other thread of the server off it (`auto` picks
/// the last CPU the same way on four or more CPUs; unit-tested in `cell::cpu`).
#[cfg(target_os = "linux")]
#[test]
fn control_thread_has_a_cpu_of_its_own() {
    let allowed = |task: &std::path::Path| {
        let status = std::fs::read_to_string(task.join("status")).unwrap_or_default();
        status
            .lines()
            .find_map(|l| l.strip_prefix("Cpus_allowed_list:"))
            .map(|l| l.trim().to_string())
            .unwrap_or_default()
    };
    let mine = cpu_list(&allowed(std::path::Path::new("/proc/thread-self")));
    if mine.len() < 2 {
        eprintln!("one CPU: nothing to place");
        return;
    }
    let last = mine.iter().max().unwrap().to_string();
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(
        dir.path(),
        &[("CELLD_CONTROL_CPU", &last), ("CELLD_STEP_PERIOD_MS", "20")],
    );
    let mut control = Vec::new();
    let mut others = Vec::new();
    for task in std::fs::read_dir(format!("/proc/{}/task", server.pid())).unwrap() {
        let task = task.unwrap().path();
        let name = std::fs::read_to_string(task.join("comm")).unwrap_or_default();
        if ["celld-control", "celld-ingest"].contains(&name.trim()) {
            control.push(allowed(&task));
        } else {
            others.push(allowed(&task));
        }
    }
    assert_eq!(
        control,
        vec![last.clone(), last.clone()],
        "the control and ingestion threads on CPU {last} alone"
    );
    let control_cpu = &control[0];
    for other in &others {
        assert!(
            !cpu_list(other).contains(&control_cpu.parse().unwrap()),
            "a service thread may run on the control CPU {control_cpu}: {other}"
        );
    }
    // A job still runs to the end with the threads placed.
    let operator = server.token("operator");
    let job = server.create_job(&operator, json!({"controller": "expert", "seed": 4}));
    assert_eq!(server.wait_final(id(&job))["status"], "succeeded");
}

/// The CPUs of a kernel list like `0-2,5`.
#[cfg(target_os = "linux")]
fn cpu_list(text: &str) -> Vec<usize> {
    text.split(',')
        .filter(|part| !part.is_empty())
        .flat_map(|part| match part.split_once('-') {
            Some((a, b)) => (a.parse().unwrap()..=b.parse().unwrap()).collect::<Vec<usize>>(),
            None => vec![part.parse().unwrap()],
        })
        .collect()
}
