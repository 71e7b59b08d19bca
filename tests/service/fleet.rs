//! Cells in a fleet: each `celld serve` keeps its SQLite and replicates it to one PostgreSQL
//! (a throwaway cluster, or a fresh database on CI's). Every row arrives as the cell holds it,
//! once, through restarts, kills and outages; the fleet's reads, registry and tokens span the
//! cells.

use crate::fleet_support;
use crate::postgres_support as postgres;
use crate::serve_support::Server;
use serde_json::{Value, json};
use std::path::Path;
use std::time::Duration;

mod crash;
mod outage;
mod reads;
mod registry;
mod settings;
mod tls;

/// Long enough for a busy two-core machine to replicate what a test made.
const CATCH_UP: Duration = Duration::from_secs(120);

/// A cell `cell_id` on `dir/celld.db` in the fleet at `url`, running its twin as fast as it
/// can.
fn cell(dir: &Path, url: &str, cell_id: &str) -> Server {
    Server::start(
        dir,
        &[
            ("CELLD_FLEET_URL", url),
            ("CELLD_CELL_ID", cell_id),
            ("CELLD_FAST", "true"),
        ],
    )
}

/// Posts `count` expert jobs and waits for each to end; answers their ids.
fn run_jobs(server: &Server, count: u64) -> Vec<i64> {
    let ids: Vec<i64> = (0..count)
        .map(|seed| {
            server.create_job(&server.admin, json!({"controller": "expert", "seed": seed}))["id"]
                .as_i64()
                .unwrap()
        })
        .collect();
    for id in &ids {
        let job = server.wait_final(*id);
        assert_eq!(job["status"], "succeeded", "{job}");
    }
    ids
}

/// Waits until the cell has sent everything and the fleet holds its record exactly; answers
/// the rows compared. (A cell still at work, its bundled policy's first evaluation say, may
/// change a row between the two reads: they are read again until they agree.)
fn assert_replicated(url: &str, server: &Server, cell_id: &str) -> usize {
    let deadline = std::time::Instant::now() + CATCH_UP;
    loop {
        fleet_support::wait_caught_up(&server.db, CATCH_UP);
        match fleet_support::compare(url, &server.db, cell_id) {
            Ok(rows) => return rows,
            Err(differences) if std::time::Instant::now() > deadline => {
                panic!("the fleet's copy of {cell_id} differs:\n{differences}")
            }
            Err(_) => std::thread::sleep(Duration::from_millis(200)),
        }
    }
}

/// GETs `path` as `token` until `done` holds (any status); fails naming `what` after a while.
fn poll(
    server: &Server,
    path: &str,
    token: &str,
    what: &str,
    done: impl Fn(u16, &Value) -> bool,
) -> Value {
    let deadline = std::time::Instant::now() + CATCH_UP;
    loop {
        let (status, body) = server.get(path, Some(token));
        if done(status, &body) {
            return body;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "{path} never {what}: last {status} {body}"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}
