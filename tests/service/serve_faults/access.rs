//! Access: nobody gets in where they do not belong. The evaluation gate on every job, tokens
//! listed, revoked and expiring (over HTTP and on the command line), failed authentication
//! limited per address, and no secret in the log at any level.

use crate::serve_support::Server;
use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const SWIFT_BC: &[u8] = include_bytes!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/policies/swift-bc.safetensors"
));

/// A policy no one has evaluated: the swift-bc file with its `seed` metadata changed to `seed`
/// (four digits, so the header keeps its length), which makes other bytes, hence a policy of
/// its own and no bundled one.
fn candidate(seed: &str) -> Vec<u8> {
    assert_eq!(seed.len(), 4);
    let needle = br#""seed":"2027""#;
    let at = SWIFT_BC
        .windows(needle.len())
        .position(|w| w == needle)
        .expect("the bundled file names its seed");
    let mut bytes = SWIFT_BC.to_vec();
    bytes[at + 8..at + 12].copy_from_slice(seed.as_bytes());
    bytes
}

fn upload(server: &Server, bytes: &[u8], name: &str) -> i64 {
    let (status, policy) = server.post_raw(
        &format!("/api/policies?name={name}"),
        &server.admin,
        "application/octet-stream",
        bytes,
    );
    assert_eq!(status, 201, "{policy}");
    assert_eq!(policy["status"], "candidate");
    policy["id"].as_i64().unwrap()
}

/// `DELETE path` with `token`: the status and the JSON answer.
fn delete(server: &Server, path: &str, token: &str) -> (u16, Value) {
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .http_status_as_error(false)
        .build()
        .into();
    let mut response = agent
        .delete(format!("{}{path}", server.base))
        .header("Authorization", format!("Bearer {token}"))
        .call()
        .expect("the server answers");
    let text = response.body_mut().read_to_string().unwrap_or_default();
    let body = serde_json::from_str(&text).unwrap_or(Value::String(text));
    (response.status().as_u16(), body)
}

fn message(answer: &Value) -> &str {
    answer["error"]["message"].as_str().unwrap_or_default()
}

/// The newest audit entry with `action`.
fn audited(server: &Server, action: &str) -> Option<Value> {
    let (status, audit) = server.get("/api/audit", Some(&server.admin));
    assert_eq!(status, 200, "{audit}");
    audit["items"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["action"] == action)
        .cloned()
}

#[test]
fn the_gate_governs_every_job_and_only_an_admin_overrides_it_on_the_record() {
    let dir = tempfile::tempdir().unwrap();
    // A threshold of 0 lets any finished evaluation pass; what shuts the gate then is no
    // evaluation, or one still running.
    let server = Server::start(
        dir.path(),
        &[
            ("CELLD_STEP_PERIOD_MS", "5"),
            ("CELLD_ACTIVATION_THRESHOLD", "0"),
        ],
    );
    let operator = server.token("operator");
    let unevaluated = upload(&server, &candidate("2028"), "unevaluated");
    let evaluated = upload(&server, &candidate("2029"), "evaluated");
    let evaluating = upload(&server, &candidate("2030"), "evaluating");
    let job = |token: &str, body: Value| server.post("/api/jobs", Some(token), Some(body));

    // Uploaded seconds ago, never evaluated: refused, for the operator and the admin alike.
    let controller = format!("policy:{unevaluated}");
    for token in [&operator, &server.admin] {
        let (status, refused) = job(token, json!({"controller": controller}));
        assert_eq!(status, 409, "{refused}");
        let why = message(&refused);
        assert!(
            why.contains("no finished evaluation on this cell") && why.contains("override_gate"),
            "{why}"
        );
    }
    // The override is the admin's: an operator asking for it is refused whatever the reason.
    let override_body = json!({
        "controller": controller,
        "seed": 7,
        "override_gate": {"reason": "bench trial before its evaluation"}
    });
    let (status, forbidden) = job(&operator, override_body.clone());
    assert_eq!(status, 403, "{forbidden}");
    assert!(message(&forbidden).contains("admin"), "{forbidden}");
    let (status, blank) = job(
        &server.admin,
        json!({"controller": controller, "override_gate": {"reason": "  "}}),
    );
    assert_eq!(status, 422, "{blank}");
    assert!(message(&blank).contains("override_gate.reason"), "{blank}");
    let (_, before) = server.get("/api/jobs", Some(&server.admin));
    let overridden = server.create_job(&server.admin, override_body);
    assert_eq!(overridden["policy_id"], unevaluated);
    let (_, after) = server.get("/api/jobs", Some(&server.admin));
    assert_eq!(
        after["total"].as_i64().unwrap(),
        before["total"].as_i64().unwrap() + 1,
        "the refused requests stored no job"
    );
    let entry = audited(&server, "job.override_gate").expect("the override is audited");
    assert_eq!(entry["actor"], "admin");
    assert_eq!(entry["detail"]["job_id"], overridden["id"]);
    assert_eq!(entry["detail"]["policy_id"], unevaluated);
    assert_eq!(
        entry["detail"]["reason"],
        "bench trial before its evaluation"
    );
    assert!(
        entry["detail"]["gate"]
            .as_str()
            .unwrap()
            .contains("no finished evaluation"),
        "{entry}"
    );

    // The bundled policies: by name, and as the bundled default registered at first start.
    let (_, policies) = server.get("/api/policies", Some(&operator));
    let bundled = policies["items"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "bundled-default")
        .expect("the bundled default is registered")["id"]
        .as_i64()
        .unwrap();
    let by_id = server.create_job(
        &operator,
        json!({"controller": format!("policy:{bundled}")}),
    );
    assert_eq!(by_id["policy_id"], bundled);
    server.create_job(&operator, json!({"controller": "hierarchical-reference"}));
    // A bundled policy's earlier name is refused, naming the new one and the default.
    let (status, renamed) = job(&operator, json!({"controller": "hierarchical"}));
    assert_eq!(status, 422, "{renamed}");
    assert!(
        message(&renamed).contains("renamed `hierarchical-reference`")
            && message(&renamed).contains("`hierarchical-swift-cells`"),
        "{renamed}"
    );

    // Evaluated on this cell and through the gate: the operator's job runs it.
    let (status, started) = server.post(
        &format!("/api/policies/{evaluated}/evaluate"),
        Some(&server.admin),
        Some(json!({"episodes": 3, "seed": 2})),
    );
    assert_eq!(status, 202, "{started}");
    let done = server.wait_evaluated(evaluated, Duration::from_secs(120));
    assert_eq!(done["evaluation"]["status"], "done", "{done}");
    let passed = server.create_job(
        &operator,
        json!({"controller": format!("policy:{evaluated}")}),
    );
    assert_eq!(passed["policy_id"], evaluated);

    // Still being evaluated: refused, saying so (5000 episodes take far longer than a request).
    let (status, started) = server.post(
        &format!("/api/policies/{evaluating}/evaluate"),
        Some(&server.admin),
        Some(json!({"episodes": 5000})),
    );
    assert_eq!(status, 202, "{started}");
    let (status, waiting) = job(
        &operator,
        json!({"controller": format!("policy:{evaluating}")}),
    );
    assert_eq!(status, 409, "{waiting}");
    assert!(
        message(&waiting).contains(&format!(
            "evaluation {} (5000 episodes) is still running",
            started["id"]
        )),
        "{waiting}"
    );
    // Only the one override is on the record.
    let (_, audit) = server.get("/api/audit?limit=1000", Some(&server.admin));
    let overrides = audit["items"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["action"] == "job.override_gate")
        .count();
    assert_eq!(overrides, 1);
}

/// `celld token ARGS --db DB`: its stdout, which must succeed.
fn celld_token(db: &Path, args: &[&str]) -> String {
    let output = Command::new(env!("CARGO_BIN_EXE_celld"))
        .arg("token")
        .args(args)
        .arg("--db")
        .arg(db)
        .output()
        .expect("run celld token");
    assert!(
        output.status.success(),
        "celld token {args:?}: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout).unwrap()
}

/// Polls `GET /api/me` with `token` until it answers 401 (up to 10 s); the refusal.
fn refused_soon(server: &Server, token: &str) -> Value {
    let start = Instant::now();
    loop {
        let (status, answer) = server.get("/api/me", Some(token));
        if status == 401 {
            return answer;
        }
        assert_eq!(status, 200, "{answer}");
        assert!(start.elapsed() < Duration::from_secs(10), "still accepted");
        std::thread::sleep(Duration::from_millis(500));
    }
}

#[test]
fn tokens_are_listed_without_secrets_revoked_at_once_and_expire() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[]);
    let admin = server.admin.clone();
    let (status, made) = server.post(
        "/api/tokens",
        Some(&admin),
        Some(json!({"role": "operator", "name": "line 2"})),
    );
    assert_eq!(status, 201, "{made}");
    assert_eq!(made["expires_at"], Value::Null);
    let operator = made["token"].as_str().unwrap().to_string();
    let operator_id = made["id"].as_i64().unwrap();

    // The list: admin only, every token, no secret and no hash of one.
    let (status, _) = server.get("/api/tokens", Some(&operator));
    assert_eq!(status, 403);
    let (status, listed) = server.get("/api/tokens", Some(&admin));
    assert_eq!(status, 200, "{listed}");
    let items = listed["items"].as_array().unwrap();
    assert_eq!(items.len(), 2);
    assert_eq!(items[0]["role"], "admin");
    assert_eq!(items[1]["name"], "line 2");
    assert_eq!(items[1]["state"], "active");
    assert_eq!(items[1]["created_by"], "admin");
    let text = listed.to_string();
    for secret in [&admin, &operator] {
        let hash = assembly_cell::storage::tokens::hash(secret);
        assert!(
            !text.contains(secret.as_str()) && !text.contains(&hash),
            "{text}"
        );
    }

    // Used (so cached), revoked, refused at its next request, naming why.
    assert_eq!(server.get("/api/me", Some(&operator)).0, 200);
    let (status, revoked) = delete(&server, &format!("/api/tokens/{operator_id}"), &admin);
    assert_eq!(status, 200, "{revoked}");
    assert_eq!(revoked["state"], "revoked");
    assert_eq!(revoked["revoked_by"], "admin");
    let (status, refused) = server.get("/api/me", Some(&operator));
    assert_eq!(status, 401, "{refused}");
    assert!(
        message(&refused).contains("`line 2` was revoked at"),
        "{refused}"
    );
    let entry = audited(&server, "token.revoke").expect("the revocation is audited");
    assert_eq!(entry["detail"]["token_id"], operator_id);
    // Again: answered as it is, not audited twice.
    let (status, again) = delete(&server, &format!("/api/tokens/{operator_id}"), &admin);
    assert_eq!(
        (status, &again["revoked_at"]),
        (200, &revoked["revoked_at"])
    );
    let (status, unknown) = delete(&server, "/api/tokens/999", &admin);
    assert_eq!(status, 404, "{unknown}");
    // The admin's own token is not revoked by itself.
    let (status, own) = delete(&server, "/api/tokens/1", &admin);
    assert_eq!(status, 409, "{own}");
    assert_eq!(server.get("/api/me", Some(&admin)).0, 200);

    // Expiry: made for a second, accepted, then refused saying it expired.
    let (status, brief) = server.post(
        "/api/tokens",
        Some(&admin),
        Some(json!({"role": "viewer", "name": "brief", "expires_in_s": 1})),
    );
    assert_eq!(status, 201, "{brief}");
    assert!(brief["expires_at"].is_string(), "{brief}");
    let brief_token = brief["token"].as_str().unwrap();
    assert_eq!(server.get("/api/me", Some(brief_token)).0, 200);
    let expired = refused_soon(&server, brief_token);
    assert!(
        message(&expired).contains(&format!(
            "`brief` expired at {}",
            brief["expires_at"].as_str().unwrap()
        )),
        "{expired}"
    );
    let (_, listed) = server.get("/api/tokens", Some(&admin));
    assert_eq!(listed["items"][2]["state"], "expired");
    let (status, never) = server.post(
        "/api/tokens",
        Some(&admin),
        Some(json!({"role": "viewer", "name": "zero", "expires_in_s": 0})),
    );
    assert_eq!(status, 422, "{never}");

    // The command line: made with an expiry, listed without its secret, revoked; the running
    // service refuses it soon after.
    let secret = celld_token(
        &server.db,
        &[
            "create",
            "--role",
            "operator",
            "--name",
            "cli op",
            "--expires-in",
            "1h",
        ],
    );
    let secret = secret.trim();
    assert!(secret.starts_with("celld_"), "{secret}");
    assert_eq!(server.get("/api/me", Some(secret)).0, 200);
    let list = celld_token(&server.db, &["list"]);
    let line = list
        .lines()
        .find(|l| l.ends_with("cli op"))
        .unwrap_or_else(|| panic!("{list}"));
    assert!(
        line.contains("operator") && line.contains("active"),
        "{line}"
    );
    assert!(!list.contains(secret) && !list.contains(&admin), "{list}");
    let id = line.split_whitespace().next().unwrap();
    let said = celld_token(&server.db, &["revoke", id]);
    assert!(said.contains("revoked"), "{said}");
    let refused = refused_soon(&server, secret);
    assert!(
        message(&refused).contains("`cli op` was revoked"),
        "{refused}"
    );
    assert!(celld_token(&server.db, &["list"]).contains("revoked"));
}

/// A request's status, `Retry-After` and JSON body.
fn call(base: &str, path: &str, token: Option<&str>) -> (u16, Option<u64>, Value) {
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(30)))
        .build()
        .into();
    let mut request = agent.get(format!("{base}{path}"));
    if let Some(token) = token {
        request = request.header("Authorization", format!("Bearer {token}"));
    }
    let mut response = request.call().expect("the server answers");
    let retry = response
        .headers()
        .get("retry-after")
        .map(|v| v.to_str().unwrap().parse().unwrap());
    let text = response.body_mut().read_to_string().unwrap_or_default();
    let body = serde_json::from_str(&text).unwrap_or(Value::String(text));
    (response.status().as_u16(), retry, body)
}

#[test]
fn refused_tokens_from_one_address_are_answered_429_until_the_window_ends() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(
        dir.path(),
        &[
            ("CELLD_AUTH_FAILURE_LIMIT", "5"),
            ("CELLD_AUTH_FAILURE_WINDOW_S", "3"),
        ],
    );
    let base = server.base.as_str();
    let guess = |n: u32| format!("celld_{n:064x}");
    // A good token before: neither counted nor limited.
    assert_eq!(call(base, "/api/me", Some(&server.admin)).0, 200);
    for n in 0..5 {
        let (status, retry, body) = call(base, "/api/me", Some(&guess(n)));
        assert_eq!((status, retry), (401, None), "guess {n}: {body}");
    }
    let (status, retry, body) = call(base, "/api/me", Some(&guess(5)));
    assert_eq!(status, 429, "{body}");
    assert_eq!(body["error"]["code"], "too_many_requests");
    let retry = retry.expect("Retry-After");
    assert!((1..=3).contains(&retry), "Retry-After: {retry}");
    // While limited no token is looked at: the admin's good one is refused too, on any route
    // and on the stream's query.
    let (status, _, _) = call(base, "/api/me", Some(&server.admin));
    assert_eq!(status, 429);
    let (status, _, _) = call(
        base,
        &format!("/api/telemetry?access_token={}", server.admin),
        None,
    );
    assert_eq!(status, 429);
    // Without a token: the ordinary 401, and the open routes answer.
    assert_eq!(call(base, "/api/me", None).0, 401);
    assert_eq!(call(base, "/api/health", None).0, 200);

    // Once the window has passed, the good token is served again, and a wrong one is merely
    // refused.
    std::thread::sleep(Duration::from_secs(retry) + Duration::from_millis(200));
    let (status, _, me) = call(base, "/api/me", Some(&server.admin));
    assert_eq!(status, 200, "{me}");
    assert_eq!(call(base, "/api/me", Some(&guess(6))).0, 401);
}

/// `celld serve` at `CELLD_LOG=trace` with its stderr in a file (serve_support's server
/// inherits stderr): the process, its address and the first admin token.
fn serve_logging(dir: &Path, log: &Path) -> (Child, String, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_celld"))
        .args(["serve", "--listen", "127.0.0.1:0", "--db"])
        .arg(dir.join("celld.db"))
        .env("CELLD_CONTROL_CPU", "off")
        .env("CELLD_OPCUA_LISTEN", "off")
        .env("CELLD_EVALUATION_EPISODES", "20")
        .env("CELLD_DEADLINE_MS", "5000")
        .env("CELLD_STEP_PERIOD_MS", "5")
        .env("CELLD_LOG", "trace")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .expect("start celld serve");
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let base = loop {
        let line = lines.next().expect("celld serve exited").unwrap();
        if let Some(address) = line.strip_prefix("celld: listening on ") {
            break address.trim().to_string();
        }
    };
    std::thread::spawn(move || for _ in lines.by_ref() {});
    let admin = std::fs::read_to_string(dir.join("admin.token"))
        .unwrap()
        .trim()
        .to_string();
    (child, base, admin)
}

#[test]
fn no_secret_reaches_the_log_even_at_trace() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("stderr.log");
    let (mut child, base, admin) = serve_logging(dir.path(), &log);
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(30)))
        .build()
        .into();
    let bearer = format!("Bearer {admin}");
    let mut made = agent
        .post(format!("{base}/api/tokens"))
        .header("Authorization", &bearer)
        .send_json(json!({"role": "viewer", "name": "watcher"}))
        .unwrap();
    assert_eq!(made.status().as_u16(), 201);
    let viewer: Value = made.body_mut().read_json().unwrap();
    let viewer = viewer["token"].as_str().unwrap().to_string();
    let job = agent
        .post(format!("{base}/api/jobs"))
        .header("Authorization", &bearer)
        .send_json(json!({"controller": "expert", "seed": 1}))
        .unwrap();
    assert_eq!(job.status().as_u16(), 201);
    // The stream, with the token in the query as a browser sends it: its first event.
    let stream = agent
        .get(format!("{base}/api/telemetry?access_token={viewer}&x=1"))
        .call()
        .unwrap();
    assert_eq!(stream.status().as_u16(), 200);
    let mut first = [0u8; 12];
    stream
        .into_body()
        .into_reader()
        .read_exact(&mut first)
        .unwrap();
    assert_eq!(&first, b"event: cell\n");
    let wrong = format!("celld_{:064x}", 42);
    for (path, token) in [
        ("/api/me", viewer.as_str()),
        ("/api/me", wrong.as_str()),
        ("/api/jobs", admin.as_str()),
    ] {
        agent
            .get(format!("{base}{path}"))
            .header("Authorization", format!("Bearer {token}"))
            .call()
            .unwrap();
    }
    let refused = agent
        .get(format!("{base}/api/telemetry?access_token={wrong}"))
        .call()
        .unwrap();
    assert_eq!(refused.status().as_u16(), 401);
    // Let the spans of the last requests close, then stop the server.
    std::thread::sleep(Duration::from_millis(300));
    let _ = child.kill();
    let _ = child.wait();

    let text = std::fs::read_to_string(&log).unwrap();
    // The log holds the requests (so the test reads a real trace) with the query redacted...
    assert!(
        text.contains("/api/telemetry") && text.contains("access_token=[redacted]&x=1"),
        "the request spans are missing from the trace:\n{}",
        &text[..text.len().min(4000)]
    );
    // ...and no secret, whole or its random part.
    for secret in [&admin, &viewer, &wrong] {
        let random = secret.trim_start_matches("celld_");
        assert!(!text.contains(random), "a token is in the log");
    }
}
