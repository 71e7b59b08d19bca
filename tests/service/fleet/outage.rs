//! PostgreSQL stopped while jobs run: the cell runs on, its rows wait in its outbox, the
//! fleet's reads say the fleet is unavailable, and everything arrives once it is back. (The
//! ten-minute outage and the time to catch up are measured by `cargo bench --bench fleet`.)

use super::{assert_replicated, cell, postgres, run_jobs};
use crate::fleet_support;
use serde_json::json;

#[test]
fn jobs_complete_while_the_fleet_is_down_and_their_rows_arrive_when_it_is_back() {
    let cluster = postgres::Postgres::start();
    let url = cluster.url();
    let dir = tempfile::tempdir().unwrap();
    let server = cell(dir.path(), &url, "cell-outage");
    run_jobs(&server, 2);
    assert_replicated(&url, &server, "cell-outage");

    cluster.stop();
    let during = run_jobs(&server, 3);
    let (status, body) = server.get("/api/fleet/cells", Some(&server.admin));
    assert_eq!(
        (status, &body["error"]["code"]),
        (503, &json!("fleet_unavailable")),
        "{body}"
    );
    assert!(
        fleet_support::backlog(&server.db) > 0,
        "the rows wait on the cell"
    );
    let (status, job) = server.get(&format!("/api/jobs/{}", during[2]), Some(&server.admin));
    assert_eq!((status, &job["status"]), (200, &json!("succeeded")));

    cluster.start_again();
    assert_replicated(&url, &server, "cell-outage");
}

#[test]
fn a_cell_starts_and_runs_while_its_fleet_is_down() {
    let cluster = postgres::Postgres::start();
    let url = cluster.url();
    cluster.stop();
    let dir = tempfile::tempdir().unwrap();
    let server = cell(dir.path(), &url, "cell-late");
    run_jobs(&server, 2);
    cluster.start_again();
    assert_replicated(&url, &server, "cell-late");
}
