//! kill -9 of a cell at random points while it replicates: after a clean start the fleet holds
//! its record exactly, no row lost, none twice. `CELLD_FLEET_KILLS` sets the number of kills
//! (default 100).

use super::{assert_replicated, cell, postgres};
use crate::fleet_support;
use crate::serve_support::Server;
use rand::{Rng, SeedableRng};
use serde_json::json;
use std::time::Duration;

/// Enough for the twin at a 5 ms control period (about 150 ms a job) to run past the latest
/// kill, 1.5 s after the start.
const JOBS_PER_START: usize = 12;

#[test]
fn kills_during_replication_lose_and_duplicate_nothing() {
    let kills: usize = std::env::var("CELLD_FLEET_KILLS")
        .ok()
        .and_then(|k| k.parse().ok())
        .unwrap_or(100);
    let (url, _cluster) = postgres::fleet_database("fleet_crash");
    let dir = tempfile::tempdir().unwrap();
    let mut random = rand_chacha::ChaCha8Rng::seed_from_u64(87);
    // Kills that left rows waiting to be sent: those that struck while the cell replicated.
    let mut mid_replication = 0;
    for kill in 0..kills {
        let mut server = Server::start(
            dir.path(),
            &[
                ("CELLD_FLEET_URL", &url),
                ("CELLD_CELL_ID", "cell-crash"),
                ("CELLD_STEP_PERIOD_MS", "5"),
            ],
        );
        // Jobs that write steps, back to back, while the rows before them replicate.
        for seed in 0..JOBS_PER_START {
            let body = json!({"controller": "expert", "seed": kill * JOBS_PER_START + seed});
            let (status, job) = server.post("/api/jobs", Some(&server.admin), Some(body));
            assert_eq!(status, 201, "{job}");
        }
        std::thread::sleep(Duration::from_millis(random.random_range(0..1500)));
        server.kill9();
        mid_replication += usize::from(fleet_support::backlog(&server.db) > 0);
    }
    eprintln!("{mid_replication} of {kills} kills left rows waiting to be sent");
    // Most kills strike while rows wait; the rest, before the first job's first step.
    assert!(
        mid_replication * 2 >= kills,
        "only {mid_replication} of {kills} kills left rows waiting to be sent"
    );
    let server = cell(dir.path(), &url, "cell-crash");
    let rows = assert_replicated(&url, &server, "cell-crash");
    assert!(rows > kills, "{rows} rows after {kills} kills");
}
