//! The writer on a disk that fills: a write that fails is an error, never a silent loss, and
//! the writer takes writes again once there is room (before, a failed commit left the writer's
//! connection inside a transaction that nothing committed, and every later write "passed").

use super::{Db, jobs, steps, tokens};
use crate::cell::StepRecord;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A tmpfs of `size` mounted on a fresh directory, unmounted when dropped. None (and says
/// why) where mounting needs root and this is not root, unless `CI` is set: then it fails.
struct SmallDisk(tempfile::TempDir);

impl SmallDisk {
    fn mount(size: &str) -> Option<SmallDisk> {
        let dir = tempfile::tempdir().unwrap();
        if unsafe { libc::geteuid() } != 0 {
            assert!(
                std::env::var_os("CI").is_none(),
                "mounting a small tmpfs needs root"
            );
            eprintln!("skipped: mounting a small tmpfs needs root");
            return None;
        }
        let status = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir.path())
            .status()
            .unwrap();
        assert!(status.success(), "mount a {size} tmpfs");
        Some(SmallDisk(dir))
    }

    /// Writes a file until the disk is full, down to the byte.
    fn fill(&self) -> PathBuf {
        let path = self.0.path().join("filler");
        let mut file = std::fs::File::create(&path).unwrap();
        let mut chunk = 1 << 20;
        while chunk > 0 {
            if file.write_all(&vec![1u8; chunk]).is_err() {
                chunk /= 2;
            }
        }
        path
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(self.0.path()).status();
    }
}

fn steps_of(job_id: i64, from: u32, count: u32) -> Vec<StepRecord> {
    (from..from + count)
        .map(|step| StepRecord {
            job_id,
            step,
            t_s: 0.1 * f64::from(step),
            state: [0.5; 12],
            action: [0.25; 6],
            proposed: None,
            rules: Default::default(),
            actor: None,
            scale: None,
            legs_mm: [100.0; 6],
            verdict: "allowed",
            veto_reason: None,
            reward: Default::default(),
            compute_us: 1.0,
            uncertainty: Default::default(),
            detected: None,
        })
        .collect()
}

async fn stored_steps(path: &Path, job_id: i64) -> i64 {
    let db = Db::open(path).await.unwrap();
    let count = sqlx::query_scalar("SELECT COUNT(*) FROM steps WHERE job_id = ?")
        .bind(job_id)
        .fetch_one(&db.reader)
        .await
        .unwrap();
    db.writer.close().await;
    db.reader.close().await;
    count
}

#[tokio::test]
async fn a_write_on_a_full_disk_fails_and_the_writer_recovers_when_there_is_room() {
    let Some(disk) = SmallDisk::mount("4m") else {
        return;
    };
    let path = disk.0.path().join("celld.db");
    let db = Db::open(&path).await.unwrap();
    let job = jobs::NewJob {
        controller: "expert".into(),
        policy_id: None,
        seed: 1,
        initial_pos_mm: 1.0,
        initial_ori_deg: 1.0,
        demonstration: false,
        created_by: "test".into(),
    };
    let id = jobs::insert(&db, &job).await.unwrap().id;
    let filler = disk.fill();
    // Writes until two have failed; each one that answered Ok must be there in the end.
    let (mut acknowledged, mut failures, mut next) = (0i64, 0, 1u32);
    let mut tokens_made = Vec::new();
    for _ in 0..200 {
        match steps::insert_batch(&db, &steps_of(id, next, 200)).await {
            Ok(()) => acknowledged += 200,
            Err(error) => {
                assert!(super::is_fault(&error), "{error}");
                failures += 1;
            }
        }
        next += 200;
        if let Ok(token) = tokens::create(&db, tokens::Role::Viewer, "full", "test", None).await {
            tokens_made.push(token.token);
        }
        if failures >= 2 {
            break;
        }
    }
    assert!(failures >= 2, "the full disk took every write");
    assert!(db.health.fault().is_some(), "the fault is not noted");
    std::fs::remove_file(filler).unwrap();
    steps::insert_batch(&db, &steps_of(id, next, 10))
        .await
        .unwrap();
    acknowledged += 10;
    assert_eq!(
        db.health.fault(),
        None,
        "a write committed: the fault clears"
    );
    let after = tokens::create(&db, tokens::Role::Viewer, "after", "test", None)
        .await
        .unwrap();
    tokens_made.push(after.token);
    // Seen by the readers now, and by a fresh process's connections later.
    for secret in &tokens_made {
        assert!(
            tokens::find_by_hash(&db, &tokens::hash(secret))
                .await
                .unwrap()
                .is_some()
        );
    }
    db.writer.close().await;
    db.reader.close().await;
    assert_eq!(stored_steps(&path, id).await, acknowledged);
    let reopened = Db::open(&path).await.unwrap();
    for secret in &tokens_made {
        let found = tokens::find_by_hash(&reopened, &tokens::hash(secret)).await;
        assert!(found.unwrap().is_some(), "an acknowledged token was lost");
    }
    reopened.writer.close().await;
    reopened.reader.close().await;
}
