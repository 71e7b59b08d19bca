//! `celld serve`'s OPC UA server as a plant's client meets it: asyncua (PyPI) runs
//! tests/service/opcua_client.py against the real service. Start runs a job through Execute to
//! its end and ProdProcessedCount rises; a viewer's Start, a bad password and an anonymous user
//! are refused; an e-stop over HTTP shows as Aborted with EmergencyStop true; Clear then Reset
//! bring the cell to Idle; Sign & Encrypt works once the client's certificate is trusted.

use crate::drivers_support::python_has;
use crate::serve_support::Server;
use std::path::PathBuf;
use std::process::Command;

#[test]
fn a_plants_client_runs_the_cell_through_its_packml_states() {
    if !python_has("asyncua", "asyncua") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(
        dir.path(),
        &[
            ("CELLD_OPCUA_LISTEN", "127.0.0.1:0"),
            ("CELLD_STEP_PERIOD_MS", "20"),
        ],
    );
    let url = server
        .opcua_url
        .clone()
        .expect("celld serve prints its OPC UA endpoint");
    let operator = server.token("operator");
    let viewer = server.token("viewer");
    let before = server.get("/api/cell/machine", Some(&server.admin)).1;
    let pki = dir.path().join("opcua-pki");
    let stdout = run_client(
        "opcua_client.py",
        &[
            "--url",
            &url,
            "--http",
            &server.base,
            "--operator-user",
            "test operator",
            "--operator-token",
            &operator,
            "--viewer-user",
            "test viewer",
            "--viewer-token",
            &viewer,
            "--pki",
            pki.to_str().unwrap(),
            "--initial-state",
            "Idle",
        ],
    );
    for check in [
        "the subscription sees Aborted and EmergencyStop true",
        "Clear: Stopped and EmergencyStop false",
        "Reset: Idle again",
        "Sign & Encrypt (Basic256Sha256) reads StateCurrent",
    ] {
        assert!(
            stdout.contains(check),
            "the client did not check {check}:\n{stdout}"
        );
    }

    // What the client did is what the HTTP API and the audit log show.
    let after = server.get("/api/cell/machine", Some(&server.admin)).1;
    assert_eq!(after["state"], "Idle");
    let processed = |m: &serde_json::Value| m["counters"]["processed"].as_u64().unwrap();
    assert_eq!(processed(&after), processed(&before) + 1);
    assert_eq!(after["counters"]["estops"], 1);
    let (status, jobs) = server.get("/api/jobs?limit=5", Some(&server.admin));
    assert_eq!(status, 200);
    let items = jobs["items"].as_array().unwrap();
    assert_eq!(
        items.len(),
        1,
        "only the operator's Start made a job: {jobs}"
    );
    assert_eq!(items[0]["created_by"], "test operator");
}

/// A session keeps no more than its token: revoked while the session is open, the token's
/// next call is refused.
#[test]
fn a_revoked_tokens_open_session_calls_nothing_more() {
    if !python_has("asyncua", "asyncua") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[("CELLD_OPCUA_LISTEN", "127.0.0.1:0")]);
    let url = server
        .opcua_url
        .clone()
        .expect("celld serve prints its OPC UA endpoint");
    let (status, token) = server.post(
        "/api/tokens",
        Some(&server.admin),
        Some(serde_json::json!({"role": "operator", "name": "plc"})),
    );
    assert_eq!(status, 201, "{token}");
    run_client(
        "opcua_revoked.py",
        &[
            "--url",
            &url,
            "--http",
            &server.base,
            "--admin-token",
            &server.admin,
            "--operator-token",
            token["token"].as_str().unwrap(),
            "--token-id",
            &token["id"].to_string(),
        ],
    );
    let machine = server.get("/api/cell/machine", Some(&server.admin)).1;
    assert_eq!(
        machine["state"], "Stopped",
        "the refused Reset changed nothing"
    );
}

/// Runs the asyncua script `name` (in tests/service) with `args`; answers its output once it
/// ended well, saying `ok` last.
pub fn run_client(name: &str, args: &[&str]) -> String {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/service")
        .join(name);
    let output = Command::new("python3")
        .arg(script)
        .args(args)
        .output()
        .expect("run python3");
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success() && stdout.trim_end().ends_with("\nok"),
        "the OPC UA client found problems:\n{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    stdout
}
