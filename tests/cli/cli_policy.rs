//! `celld policy run` and `celld eval --controller FILE` end to end on the PyTorch-layout fixture.

use crate::common;

use common::{celld, last_json};

#[test]
fn policy_run_reproduces_the_numpy_reference() {
    let output = celld(&[
        "policy",
        "run",
        "--policy",
        "tests/fixtures/policy_small.safetensors",
        "--states",
        "tests/fixtures/policy_small_states.jsonl",
    ]);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let ours = String::from_utf8(output.stdout).unwrap();
    let expected = std::fs::read_to_string("tests/fixtures/policy_small_expected.jsonl").unwrap();
    let (ours, expected): (Vec<&str>, Vec<&str>) =
        (ours.lines().collect(), expected.lines().collect());
    assert_eq!(ours.len(), expected.len());
    for (line, (a, b)) in ours.iter().zip(&expected).enumerate() {
        let a: serde_json::Value = serde_json::from_str(a).unwrap();
        let b: serde_json::Value = serde_json::from_str(b).unwrap();
        assert_eq!(a["actor"], b["actor"], "line {}", line + 1);
        for key in ["omega", "action"] {
            for (x, y) in a[key]
                .as_array()
                .unwrap()
                .iter()
                .zip(b[key].as_array().unwrap())
            {
                let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
                assert!((x - y).abs() <= 1e-5, "line {} {key}: {x} vs {y}", line + 1);
            }
        }
        let (x, y) = (a["scale"].as_f64().unwrap(), b["scale"].as_f64().unwrap());
        assert!((x - y).abs() <= 1e-5, "line {} scale", line + 1);
    }
}

#[test]
fn a_policy_file_runs_as_a_controller_and_bad_files_are_refused() {
    let output = celld(&[
        "eval",
        "--controller",
        "tests/fixtures/policy_small.safetensors",
        "--episodes",
        "4",
        "--json",
    ]);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let summary = last_json(&output);
    assert_eq!(summary["episodes"], 4);
    assert_eq!(summary["controller"], "policy_small");

    let output = celld(&[
        "eval",
        "--controller",
        "cells/phi170.toml",
        "--episodes",
        "1",
    ]);
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("cells/phi170.toml"));
    let output = celld(&[
        "policy",
        "run",
        "--policy",
        "nope.safetensors",
        "--states",
        "x.jsonl",
    ]);
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("nope.safetensors"));
}
