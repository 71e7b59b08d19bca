//! Two cells in one fleet: each one's record arrives whole, and every cell reads the fleet's
//! cells, jobs and figures, and accepts the tokens any cell made.

use super::{assert_replicated, cell, poll, postgres, run_jobs};
use serde_json::json;

#[test]
fn two_cells_replicate_their_records_and_read_the_fleet() {
    let (url, _cluster) = postgres::fleet_database("fleet_reads");
    let (dir_a, dir_b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let a = cell(dir_a.path(), &url, "cell-a");
    let b = cell(dir_b.path(), &url, "cell-b");
    let jobs_a = run_jobs(&a, 3);
    let jobs_b = run_jobs(&b, 2);

    // Every row of each cell's record, as it holds it, once.
    assert!(assert_replicated(&url, &a, "cell-a") > 0);
    assert!(assert_replicated(&url, &b, "cell-b") > 0);

    // Both cells are listed on each, with the state and counters they reported.
    let cells = poll(
        &b,
        "/api/fleet/cells",
        &b.admin,
        "listed both cells",
        |status, body| status == 200 && body["items"].as_array().is_some_and(|c| c.len() == 2),
    );
    let listed = cells["items"].as_array().unwrap();
    assert_eq!(listed[0]["cell_id"], "cell-a");
    assert_eq!(listed[0]["this_cell"], false);
    assert_eq!(listed[1]["this_cell"], true);
    let counted = poll(
        &a,
        "/api/fleet/cells",
        &a.admin,
        "counted cell-a's parts",
        |_, body| body["items"][0]["counters"]["good"] == json!(jobs_a.len()),
    );
    assert_eq!(
        counted["items"][0]["counters"]["processed"],
        json!(jobs_a.len())
    );
    assert_eq!(counted["items"][0]["backlog"], 0);

    // The fleet's jobs: all of them, or one cell's, filtered as the local list is.
    let (status, all) = a.get("/api/fleet/jobs", Some(&a.admin));
    assert_eq!(status, 200, "{all}");
    assert_eq!(all["total"], json!(jobs_a.len() + jobs_b.len()));
    let (_, only_b) = a.get(
        "/api/fleet/jobs?cell=cell-b&status=succeeded",
        Some(&a.admin),
    );
    let ids: Vec<i64> = only_b["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| {
            assert_eq!(j["cell_id"], "cell-b");
            j["id"].as_i64().unwrap()
        })
        .collect();
    assert_eq!(ids, jobs_b.iter().rev().copied().collect::<Vec<_>>());
    let (status, refused) = a.get("/api/fleet/jobs?status=lost", Some(&a.admin));
    assert_eq!(
        (status, &refused["error"]["code"]),
        (400, &json!("bad_request"))
    );

    // The fleet's figures agree with each cell's own.
    let (_, stats_a) = a.get("/api/stats", Some(&a.admin));
    let (_, fleet_a) = b.get("/api/fleet/stats?cell=cell-a", Some(&b.admin));
    assert_eq!(fleet_a["total"], stats_a["total"]);
    let (_, fleet) = b.get("/api/fleet/stats", Some(&b.admin));
    assert_eq!(fleet["total"]["jobs"], json!(jobs_a.len() + jobs_b.len()));
    assert_eq!(fleet["total"]["success_rate"], 1.0);
}

#[test]
fn a_token_made_on_one_cell_works_on_every_cell_until_revoked() {
    let (url, _cluster) = postgres::fleet_database("fleet_tokens");
    let (dir_a, dir_b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let a = cell(dir_a.path(), &url, "cell-a");
    let b = cell(dir_b.path(), &url, "cell-b");
    let (status, made) = a.post(
        "/api/tokens",
        Some(&a.admin),
        Some(json!({"role": "operator", "name": "line lead"})),
    );
    assert_eq!(status, 201, "{made}");
    let (token, id) = (
        made["token"].as_str().unwrap(),
        made["id"].as_i64().unwrap(),
    );

    // Unknown on cell-b until the fleet has it, then accepted with its role.
    let me = poll(
        &b,
        "/api/me",
        token,
        "accepted cell-a's token",
        |status, _| status == 200,
    );
    assert_eq!(me["role"], "operator", "{me}");
    assert!(me["name"].as_str().unwrap().contains("cell-a"), "{me}");
    let (status, job) = b.post(
        "/api/jobs",
        Some(token),
        Some(json!({"controller": "expert", "seed": 3})),
    );
    assert_eq!(status, 201, "{job}");

    // One with an expiry is accepted too (the fleet reads its expiry as the cell does).
    let (status, expiring) = a.post(
        "/api/tokens",
        Some(&a.admin),
        Some(json!({"role": "viewer", "name": "visitor", "expires_in_s": 3600})),
    );
    assert_eq!(status, 201, "{expiring}");
    let visitor = expiring["token"].as_str().unwrap();
    let me = poll(
        &b,
        "/api/me",
        visitor,
        "accepted the expiring token",
        |status, _| status == 200,
    );
    assert_eq!(me["role"], "viewer", "{me}");

    // Revoked on its cell: refused on every cell.
    let (status, revoked) = a.delete(&format!("/api/tokens/{id}"), &a.admin);
    assert_eq!(status, 200, "{revoked}");
    let refused = poll(
        &b,
        "/api/me",
        token,
        "refused the revoked token",
        |status, _| status == 401,
    );
    assert!(refused.to_string().contains("revoked"), "{refused}");
}

#[test]
fn a_cell_in_no_fleet_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let server = crate::serve_support::Server::start(dir.path(), &[]);
    for path in [
        "/api/fleet/cells",
        "/api/fleet/jobs",
        "/api/fleet/stats",
        "/api/fleet/policies",
    ] {
        let (status, body) = server.get(path, Some(&server.admin));
        assert_eq!(
            (status, &body["error"]["code"]),
            (404, &json!("no_fleet")),
            "{path}"
        );
        assert!(
            body["error"]["message"]
                .as_str()
                .unwrap()
                .contains("--fleet")
        );
    }
}
