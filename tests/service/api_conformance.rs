//! The API does what its description says: schemathesis (PyPI, an independent fuzzer) reads
//! `/api/openapi.json` from a running `celld serve` and sends it schema-valid and schema-invalid
//! requests, with every check it has and at least 200 examples per operation
//! (`tests/conformance/schemathesis.toml`); it must find nothing.
//!
//! `.ci/run` installs schemathesis. Elsewhere, without it, this test says so and passes; with
//! `CI` set, a missing schemathesis fails it.

use crate::serve_support;

use serve_support::Server;
use std::path::Path;
use std::process::Command;

fn schemathesis_installed() -> bool {
    Command::new("schemathesis")
        .arg("--version")
        .output()
        .is_ok_and(|output| output.status.success())
}

#[test]
fn schemathesis_finds_nothing_against_the_described_api() {
    if !schemathesis_installed() {
        assert!(
            std::env::var_os("CI").is_none(),
            "schemathesis is not installed (pip install schemathesis); CI needs it"
        );
        eprintln!("schemathesis is not installed: the API conformance test is skipped");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // Jobs run as fast as the twin can, so the queue drains while requests arrive. The work
    // queue holds every evaluation and training run the run asks for (its 429 when full is
    // `tests/serve_faults/work.rs`'s to check), so each schema-valid request is accepted.
    // Its checks send many refused tokens from one address: no 429 may stand in for the 401s
    // and the admin's answers it expects.
    // In a fleet, so that the fleet's reads answer as they do in one.
    let (fleet, _cluster) = crate::postgres_support::fleet_database("conformance");
    let server = Server::start(
        dir.path(),
        &[
            ("CELLD_FLEET_URL", &fleet),
            ("CELLD_FAST", "true"),
            ("CELLD_WORK_QUEUE_LENGTH", "10000"),
            ("CELLD_AUTH_FAILURE_LIMIT", "1000000"),
        ],
    );
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/conformance/schemathesis.toml");
    let output = Command::new("schemathesis")
        .arg("--config-file")
        .arg(&config)
        .args(["run", &format!("{}/api/openapi.json", server.base)])
        .args(["--checks", "all", "--seed", "1", "--no-color"])
        .args(["-H", &format!("Authorization: Bearer {}", server.admin)])
        .output()
        .expect("run schemathesis");
    let report = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "schemathesis found problems:\n{report}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    // The run covered every described operation.
    assert!(
        report.contains("Tested: 41"),
        "not every operation was tested:\n{report}"
    );
}
