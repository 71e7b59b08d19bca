//! kill -9 of a cell at random points while it replicates: after a clean start the fleet holds
//! its record exactly, no row lost, none twice. `CELLD_FLEET_KILLS` sets the number of kills
//! (default 100).

use super::{assert_replicated, cell, postgres};
use rand::{Rng, SeedableRng};
use serde_json::json;
use std::time::Duration;

#[test]
fn kills_during_replication_lose_and_duplicate_nothing() {
    let kills: usize = std::env::var("CELLD_FLEET_KILLS")
        .ok()
        .and_then(|k| k.parse().ok())
        .unwrap_or(100);
    let (url, _cluster) = postgres::fleet_database("fleet_crash");
    let dir = tempfile::tempdir().unwrap();
    let mut random = rand_chacha::ChaCha8Rng::seed_from_u64(87);
    for kill in 0..kills {
        let mut server = cell(dir.path(), &url, "cell-crash");
        // Jobs that write steps while the rows before them replicate.
        for seed in 0..3 {
            let body = json!({"controller": "expert", "seed": kill * 3 + seed});
            let (status, job) = server.post("/api/jobs", Some(&server.admin), Some(body));
            assert_eq!(status, 201, "{job}");
        }
        std::thread::sleep(Duration::from_millis(random.random_range(0..1500)));
        server.kill9();
    }
    let server = cell(dir.path(), &url, "cell-crash");
    let rows = assert_replicated(&url, &server, "cell-crash");
    assert!(rows > kills * 3, "{rows} rows after {kills} kills");
}
