//! One registry for the fleet: a policy uploaded on one cell reaches every cell, is evaluated
//! on each against its own configuration, and one admin action activates it on every cell
//! where that evaluation passed the gate.

use super::{cell, poll, postgres};
use serde_json::Value;

/// `hierarchical-reference`, not one of the bundled policies a cell registers itself.
const REFERENCE: &[u8] = include_bytes!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/policies/default.safetensors"
));

#[test]
fn a_policy_uploaded_once_reaches_every_cell_and_activates_where_it_passed() {
    let (url, _cluster) = postgres::fleet_database("fleet_registry");
    let (dir_a, dir_b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let a = cell(dir_a.path(), &url, "cell-a");
    let b = cell(dir_b.path(), &url, "cell-b");
    let (status, uploaded) = a.post_raw(
        "/api/policies?name=reference",
        &a.admin,
        "application/octet-stream",
        REFERENCE,
    );
    assert_eq!(status, 201, "{uploaded}");
    let sha256 = uploaded["sha256"].as_str().unwrap().to_string();

    // cell-b pulls it and evaluates it on its own configuration.
    let on_b = |policies: &Value| -> Option<Value> {
        policies["items"]
            .as_array()?
            .iter()
            .find(|p| p["sha256"] == sha256.as_str())
            .cloned()
    };
    let policies = poll(
        &b,
        "/api/policies",
        &b.admin,
        "pulled the upload",
        |_, body| {
            on_b(body).is_some_and(|p| {
                matches!(p["evaluation"]["status"].as_str(), Some("done" | "failed"))
            })
        },
    );
    let pulled = on_b(&policies).unwrap();
    assert_eq!(pulled["name"], "reference");
    assert_eq!(pulled["status"], "candidate");
    let evaluation = &pulled["evaluation"];
    assert_eq!(evaluation["status"], "done", "{evaluation}");
    // `policies.activation_threshold` as the cells run (the default).
    let passed_on_b = evaluation["success_rate"].as_f64().unwrap() >= 0.95;

    // The registry lists it with both cells, each with its own policy id and status.
    let registry = poll(
        &a,
        "/api/fleet/policies",
        &a.admin,
        "listed it on both cells",
        |_, body| {
            body["items"].as_array().is_some_and(|items| {
                items.iter().any(|p| {
                    p["sha256"] == sha256.as_str()
                        && p["cells"].as_array().is_some_and(|c| c.len() == 2)
                })
            })
        },
    );
    let listed = registry["items"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["sha256"] == sha256.as_str())
        .unwrap();
    assert_eq!(listed["first_cell"], "cell-a");

    // One admin action; each cell answers from its own evaluation: cell-a never evaluated it.
    let viewer = a.token("viewer");
    let (status, _) = a.post(
        &format!("/api/fleet/policies/{sha256}/activate"),
        Some(&viewer),
        None,
    );
    assert_eq!(status, 403);
    let (status, unknown) = a.post("/api/fleet/policies/00ff/activate", Some(&a.admin), None);
    assert_eq!(status, 404, "{unknown}");
    let (status, request) = a.post(
        &format!("/api/fleet/policies/{sha256}/activate"),
        Some(&a.admin),
        None,
    );
    assert_eq!(status, 202, "{request}");
    let path = format!("/api/fleet/activations/{}", request["id"]);
    let answered = poll(
        &b,
        &path,
        &b.admin,
        "was answered by both cells",
        |_, body| body["results"].as_array().is_some_and(|r| r.len() == 2),
    );
    let outcome = |cell: &str| {
        answered["results"]
            .as_array()
            .unwrap()
            .iter()
            .find(|r| r["cell_id"] == cell)
            .map(|r| r["outcome"].clone())
            .unwrap()
    };
    assert_eq!(outcome("cell-a"), "not_passed", "{answered}");
    let expected_b = if passed_on_b {
        "activated"
    } else {
        "not_passed"
    };
    assert_eq!(outcome("cell-b"), expected_b, "{answered}");
    let (_, here) = b.get(&format!("/api/policies/{}", pulled["id"]), Some(&b.admin));
    assert_eq!(
        here["status"],
        if passed_on_b { "active" } else { "candidate" }
    );
    let (_, there) = a.get(&format!("/api/policies/{}", uploaded["id"]), Some(&a.admin));
    assert_eq!(there["status"], "candidate");
}
