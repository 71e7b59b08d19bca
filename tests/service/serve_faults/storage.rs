//! Storage faults: the database's disk fills during a job and while idle. Nothing answered 2xx
//! is missing from the database afterwards, a job whose steps cannot be stored ends
//! `storage_failed` with the steps that were, health says so while it lasts, and the service
//! recovers by itself once there is room again.
//!
//! The database sits on a small tmpfs of its own (mounting needs root: CI runs as root; without
//! root and without CI the tests say why and pass). `CELLD_STORAGE_FAULT_ROUNDS` sets the
//! rounds of the random-injection test (20 by default; `100` for a longer run).

use super::serve_support::Server;
use assembly_cell::storage::{Db, tokens};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// A tmpfs of its own size, unmounted when dropped (after the server in it: declare it first).
struct SmallDisk {
    dir: tempfile::TempDir,
}

impl SmallDisk {
    fn mount(size: &str) -> Option<SmallDisk> {
        if unsafe { libc::geteuid() } != 0 {
            assert!(
                std::env::var_os("CI").is_none(),
                "CI is set but this is not root: mounting a small tmpfs needs root"
            );
            eprintln!("skipped: mounting a small tmpfs for the database needs root");
            return None;
        }
        let dir = tempfile::tempdir().unwrap();
        let status = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir.path())
            .status()
            .expect("run mount");
        assert!(status.success(), "mount a {size} tmpfs");
        Some(SmallDisk { dir })
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    fn filler(&self) -> PathBuf {
        self.path().join("filler")
    }

    /// Fills the disk to the byte; answers the bytes written.
    fn fill(&self) -> u64 {
        let mut file = std::fs::File::create(self.filler()).unwrap();
        let (mut chunk, mut written) = (1usize << 20, 0u64);
        let block = vec![0xA5u8; chunk];
        while chunk > 0 {
            match file.write(&block[..chunk]) {
                Ok(0) | Err(_) => chunk /= 2,
                Ok(n) => written += n as u64,
            }
        }
        written
    }

    fn free(&self) {
        std::fs::remove_file(self.filler()).unwrap();
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(self.path()).status();
    }
}

/// Opens the server's database file from this process (WAL lets a second process read) and
/// asks it one thing.
fn ask_db<T>(path: &Path, ask: impl AsyncFnOnce(&Db) -> T) -> T {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(async {
            let db = Db::open(path).await.expect("the database opens");
            let answer = ask(&db).await;
            db.writer.close().await;
            db.reader.close().await;
            answer
        })
}

fn health(server: &Server) -> (u16, Value) {
    server.get("/api/health", None)
}

fn wait_health(server: &Server, writable: bool, limit: Duration) -> Value {
    let start = Instant::now();
    loop {
        let (status, body) = health(server);
        if body["storage"]["writable"] == writable {
            assert_eq!(status, if writable { 200 } else { 503 }, "{body}");
            assert_eq!(body["database"], writable, "{body}");
            return body;
        }
        assert!(
            start.elapsed() < limit,
            "health never said writable = {writable}: {body}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// What the service acknowledged (2xx) while the disk was full, to look for afterwards.
#[derive(Default)]
struct Acknowledged {
    tokens: Vec<String>,
    jobs: Vec<i64>,
    refused: u32,
}

impl Acknowledged {
    /// A token asked for: 201 (kept, to check) or 503 `storage_unavailable`, nothing else.
    fn token(&mut self, server: &Server, name: &str) {
        let (status, body) = server.post(
            "/api/tokens",
            Some(&server.admin),
            Some(json!({"role": "viewer", "name": name})),
        );
        match status {
            201 => self
                .tokens
                .push(body["token"].as_str().unwrap().to_string()),
            503 => self.refused(&body),
            _ => panic!("POST /api/tokens answered {status}: {body}"),
        }
    }

    /// A job asked for: 201 (kept, to check), 503 `storage_unavailable`, or 409 while the
    /// cell is latched.
    fn job(&mut self, server: &Server, seed: u64) {
        let (status, body) = server.post(
            "/api/jobs",
            Some(&server.admin),
            Some(json!({"controller": "expert", "seed": seed})),
        );
        match status {
            201 => self.jobs.push(body["id"].as_i64().unwrap()),
            503 => self.refused(&body),
            _ => panic!("POST /api/jobs answered {status}: {body}"),
        }
    }

    fn refused(&mut self, body: &Value) {
        assert_eq!(body["error"]["code"], "storage_unavailable", "{body}");
        let message = body["error"]["message"].as_str().unwrap();
        assert!(
            message.contains("full"),
            "the message names the fault: {message}"
        );
        self.refused += 1;
    }

    /// Every acknowledged write is there, through the API and in the file; answers how many
    /// were checked.
    fn check(&self, server: &Server) -> usize {
        for secret in &self.tokens {
            let (status, body) = server.get("/api/me", Some(secret));
            assert_eq!(
                status, 200,
                "an acknowledged token does not sign in: {body}"
            );
        }
        for &id in &self.jobs {
            let job = server.wait_final(id);
            check_job(server, &job);
        }
        let tokens = self.tokens.clone();
        let jobs = self.jobs.clone();
        let (tokens_found, jobs_found) = ask_db(&server.db, async |db| {
            let mut found = 0;
            for secret in &tokens {
                found += usize::from(
                    tokens::find_by_hash(db, &tokens::hash(secret))
                        .await
                        .unwrap()
                        .is_some(),
                );
            }
            let mut jobs_found = 0;
            for &id in &jobs {
                jobs_found += usize::from(
                    assembly_cell::storage::jobs::get(db, id)
                        .await
                        .unwrap()
                        .is_some(),
                );
            }
            (found, jobs_found)
        });
        assert_eq!(tokens_found, self.tokens.len(), "acknowledged tokens lost");
        assert_eq!(jobs_found, self.jobs.len(), "acknowledged jobs lost");
        self.tokens.len() + self.jobs.len()
    }
}

/// A job that ended: succeeded, or ended `storage_failed`; its stored steps are the count
/// it shows, numbered from 1 without a gap.
fn check_job(server: &Server, job: &Value) -> &'static str {
    let id = job["id"].as_i64().unwrap();
    let outcome = match (job["status"].as_str(), job["failure_reason"].as_str()) {
        (Some("succeeded"), None) => "succeeded",
        (Some("failed" | "cancelled"), Some("storage_failed")) => "storage_failed",
        _ => panic!("job {id} ended neither succeeded nor storage_failed: {job}"),
    };
    let steps = server.steps(id);
    assert_eq!(
        job["steps"].as_i64().unwrap() as usize,
        steps.len(),
        "job {id} shows a count other than its stored steps: {job}"
    );
    for (i, step) in steps.iter().enumerate() {
        assert_eq!(step["step"].as_i64().unwrap() as usize, i + 1, "job {id}");
    }
    outcome
}

fn cell(server: &Server) -> Value {
    let (status, cell) = server.get("/api/cell", Some(&server.admin));
    assert_eq!(status, 200, "{cell}");
    cell
}

#[test]
fn a_disk_that_fills_during_a_job_fails_it_storage_failed_and_loses_nothing() {
    let Some(disk) = SmallDisk::mount("8m") else {
        return;
    };
    let server = Server::start(disk.path(), &[("CELLD_STEP_PERIOD_MS", "100")]);
    let admin = server.admin.clone();
    let job = server.create_job(&admin, json!({"controller": "expert", "seed": 31}));
    let id = job["id"].as_i64().unwrap();
    server.wait_job(id, "stored a step", |job| job["steps"].as_i64() >= Some(2));

    let filled = disk.fill();
    let fault = wait_health(&server, false, Duration::from_secs(10));
    println!(
        "filled {} KiB during job {id}; health: {}",
        filled / 1024,
        fault["storage"]
    );
    assert!(fault["storage"]["fault"]["since"].is_string(), "{fault}");
    // The robot holds at once: the control thread ended the job, whose end waits in memory.
    let start = Instant::now();
    while cell(&server)["current_job"] == id {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "job {id} still runs"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut acknowledged = Acknowledged::default();
    acknowledged.token(&server, "while full");
    acknowledged.job(&server, 32);
    assert!(acknowledged.refused > 0, "a full disk took every write");

    disk.free();
    wait_health(&server, true, Duration::from_secs(30));
    let ended = server.wait_final(id);
    assert_eq!(ended["status"], "failed", "{ended}");
    assert_eq!(ended["failure_reason"], "storage_failed", "{ended}");
    check_job(&server, &ended);
    // In the file too, once there is room: the job's row and its steps agree.
    let (status, reason, count, stored) = ask_db(&server.db, async |db| {
        let row: (String, Option<String>, i64) =
            sqlx::query_as("SELECT status, failure_reason, steps FROM jobs WHERE id = ?")
                .bind(id)
                .fetch_one(&db.reader)
                .await
                .unwrap();
        let stored: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM steps WHERE job_id = ?")
            .bind(id)
            .fetch_one(&db.reader)
            .await
            .unwrap();
        (row.0, row.1, row.2, stored)
    });
    assert_eq!(
        (status.as_str(), reason.as_deref()),
        ("failed", Some("storage_failed"))
    );
    assert_eq!(count, stored, "the job's row counts its stored steps");

    // Writes work again without a restart.
    acknowledged.token(&server, "after");
    let checked = acknowledged.check(&server);
    println!(
        "job {id}: storage_failed with {stored} stored steps; {} refused while full, {checked} \
         acknowledged writes all stored",
        acknowledged.refused
    );
}

#[test]
fn a_full_disk_while_idle_keeps_the_latch_as_stored() {
    let Some(disk) = SmallDisk::mount("8m") else {
        return;
    };
    let server = Server::start(disk.path(), &[]);
    assert_eq!(health(&server).0, 200);

    disk.fill();
    let mut acknowledged = Acknowledged::default();
    acknowledged.token(&server, "while full");
    assert_eq!(acknowledged.refused, 1, "a token was stored on a full disk");
    let fault = wait_health(&server, false, Duration::from_secs(5));
    assert!(
        fault["storage"]["fault"]["error"]
            .as_str()
            .unwrap()
            .contains("full"),
        "{fault}"
    );

    // The e-stop holds and latches whatever storage does, and says the latch is not stored.
    let (status, body) = server.post("/api/cell/estop", Some(&server.admin), None);
    assert_eq!(status, 503, "{body}");
    assert_eq!(body["error"]["code"], "storage_unavailable", "{body}");
    assert!(
        body["error"]["message"]
            .as_str()
            .unwrap()
            .contains("latch could not be stored"),
        "{body}"
    );
    assert_eq!(cell(&server)["estop_latched"], true);
    // A reset that cannot be stored changes nothing.
    let (status, body) = server.post("/api/cell/reset", Some(&server.admin), None);
    assert_eq!(status, 503, "{body}");
    assert_eq!(body["error"]["code"], "storage_unavailable", "{body}");
    assert_eq!(
        cell(&server)["estop_latched"],
        true,
        "a failed reset unlatched"
    );
    let (status, body) = server.post(
        "/api/jobs",
        Some(&server.admin),
        Some(json!({"controller": "expert", "seed": 5})),
    );
    assert_eq!(status, 409, "{body}");

    disk.free();
    wait_health(&server, true, Duration::from_secs(30));
    // The e-stop's latch was stored once the disk took writes again.
    let start = Instant::now();
    while !ask_db(&server.db, async |db| db.cell_flag("estop").await.unwrap()) {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "the e-stop's latch was never stored"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let (status, body) = server.post("/api/cell/reset", Some(&server.admin), None);
    assert_eq!(status, 200, "{body}");
    assert_eq!(cell(&server)["estop_latched"], false);
    assert!(!ask_db(&server.db, async |db| db
        .cell_flag("estop")
        .await
        .unwrap()));
    let token = server.token("viewer");
    assert_eq!(server.get("/api/me", Some(&token)).0, 200);
    acknowledged.check(&server);
}

#[test]
fn random_disk_full_injections_lose_nothing_acknowledged() {
    let rounds: u32 = std::env::var("CELLD_STORAGE_FAULT_ROUNDS")
        .ok()
        .map(|v| {
            v.parse()
                .expect("CELLD_STORAGE_FAULT_ROUNDS is a whole number")
        })
        .unwrap_or(20);
    // Room for the WAL to reach its checkpoint (1000 pages, 4 MiB) and start over.
    let Some(disk) = SmallDisk::mount("16m") else {
        return;
    };
    let server = Server::start(disk.path(), &[("CELLD_STEP_PERIOD_MS", "20")]);
    let mut rng = ChaCha8Rng::seed_from_u64(20261207);
    let mut acknowledged = Acknowledged::default();
    let (mut faults_seen, mut jobs) = (0u32, Vec::new());
    for round in 0..rounds {
        let id = server.create_job(
            &server.admin,
            json!({"controller": "expert", "seed": 1000 + u64::from(round)}),
        )["id"]
            .as_i64()
            .unwrap();
        jobs.push(id);
        // Anywhere from before the job's first step to after its end (a job takes ~1 s).
        std::thread::sleep(Duration::from_millis(rng.random_range(0..1500)));
        disk.fill();
        if rng.random_bool(0.5) {
            acknowledged.token(&server, &format!("round {round}"));
        }
        if rng.random_bool(0.5) {
            acknowledged.job(&server, 2000 + u64::from(round));
        }
        std::thread::sleep(Duration::from_millis(rng.random_range(0..400)));
        faults_seen += u32::from(health(&server).1["storage"]["writable"] == false);
        disk.free();
        // No restart: the service takes writes again by itself.
        wait_health(&server, true, Duration::from_secs(30));
        server.wait_final(id);
    }
    let mut outcomes = std::collections::BTreeMap::new();
    for &id in jobs.iter().chain(&acknowledged.jobs) {
        let job = server.wait_final(id);
        *outcomes.entry(check_job(&server, &job)).or_insert(0u32) += 1;
    }
    let checked = acknowledged.check(&server);
    println!(
        "{rounds} disk-full injections: health unwritable at {faults_seen}; {} writes refused \
         (503), {checked} acknowledged while full and 0 of them lost; 0 restarts; jobs {outcomes:?}",
        acknowledged.refused
    );
    assert!(faults_seen > 0, "no injection made a write fail");
}
