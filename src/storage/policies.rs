//! The policy registry: files with their sha256, metadata and shapes; status `candidate`,
//! `active` or `retired`; evaluations in the twin, which the activation gate reads.

use super::{Db, DbError, NOW, json_column};
use crate::sim::{Fault, Mismatch};
use serde::Serialize;
use serde_json::Value;

/// A registered policy as served (the file itself is served separately).
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct Policy {
    pub id: i64,
    pub name: String,
    pub sha256: String,
    pub size_bytes: i64,
    pub status: String,
    pub metadata: Value,
    pub shapes: Value,
    pub uploaded_by: Option<String>,
    pub created_at: String,
    /// The training run that made it, when it was trained here (lineage).
    pub training_run_id: Option<i64>,
    /// The newest evaluation, if any.
    pub evaluation: Option<Evaluation>,
}

#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct Evaluation {
    pub id: i64,
    pub policy_id: i64,
    /// `queued` (waiting its turn in the work queue), `running`, `done` or `failed`.
    #[schema(pattern = "^(queued|running|done|failed)$")]
    pub status: String,
    /// While `queued`: its place in the work queue, shared with training runs (1 = next to
    /// start); otherwise null.
    #[schema(minimum = 1)]
    pub queue_position: Option<usize>,
    pub episodes: i64,
    pub seed: u64,
    pub cell_hash: String,
    /// The camera's point noise × the spec's (1: as the cell file says).
    pub noise_scale: f64,
    /// The robot's calibration error × the cell file's (1: as the cell file says).
    pub calibration_scale: f64,
    /// The fault injected in every episode, if any.
    #[schema(value_type = Option<crate::sim::Fault>)]
    pub fault: Option<String>,
    /// Run on cells drawn around this cell (each kept robot on its own, its noise and
    /// calibration drawn too) rather than on the cell itself.
    pub randomise_cells: bool,
    /// The rules the policy ran with: `all` (the cell file's), `none`, or the names of those
    /// that ran, comma-separated (docs/policy-rules.md).
    pub rules: String,
    pub success_rate: Option<f64>,
    pub avg_steps: Option<f64>,
    pub failures: Value,
    pub error: Option<String>,
    pub requested_by: String,
    /// When it was asked for, then when it left the queue and started.
    pub started_at: String,
    pub finished_at: Option<String>,
}

/// What an evaluation runs on: this cell's twin under a mismatch, or cells drawn around it over
/// the ranges the product is specified for (their noise and calibration drawn too; a fault may
/// still be injected).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum EvaluatedOn {
    Cell(Mismatch),
    DrawnCells { fault: Option<Fault> },
}

impl EvaluatedOn {
    /// The twin's departure from the cell file; on drawn cells only the fault, their camera
    /// noise and calibration error being drawn.
    pub fn mismatch(&self) -> Mismatch {
        match *self {
            EvaluatedOn::Cell(mismatch) => mismatch,
            EvaluatedOn::DrawnCells { fault } => Mismatch {
                fault,
                ..Mismatch::NONE
            },
        }
    }

    pub fn is_drawn(&self) -> bool {
        matches!(self, EvaluatedOn::DrawnCells { .. })
    }
}

/// What an upload stores.
pub struct NewPolicy<'a> {
    pub name: &'a str,
    pub sha256: &'a str,
    pub file: &'a [u8],
    pub metadata: Value,
    pub shapes: Value,
    pub uploaded_by: &'a str,
}

/// A row of `policy_evaluations` as stored.
#[derive(sqlx::FromRow)]
struct EvaluationRow {
    id: i64,
    policy_id: i64,
    status: String,
    episodes: i64,
    seed: i64,
    cell_hash: String,
    noise_scale: f64,
    calibration_scale: f64,
    fault: Option<String>,
    randomise_cells: bool,
    rules: String,
    success_rate: Option<f64>,
    avg_steps: Option<f64>,
    failures: Option<String>,
    error: Option<String>,
    requested_by: String,
    started_at: String,
    finished_at: Option<String>,
}

impl From<EvaluationRow> for Evaluation {
    fn from(row: EvaluationRow) -> Self {
        Evaluation {
            id: row.id,
            policy_id: row.policy_id,
            status: row.status,
            // The queue's to say (`workflows::queue`); storage knows only that it waits.
            queue_position: None,
            episodes: row.episodes,
            // Stored as the same 64 bits in SQLite's signed integer.
            seed: row.seed as u64,
            cell_hash: row.cell_hash,
            noise_scale: row.noise_scale,
            calibration_scale: row.calibration_scale,
            fault: row.fault,
            randomise_cells: row.randomise_cells,
            rules: row.rules,
            success_rate: row.success_rate,
            avg_steps: row.avg_steps,
            failures: json_column(row.failures),
            error: row.error,
            requested_by: row.requested_by,
            started_at: row.started_at,
            finished_at: row.finished_at,
        }
    }
}

const POLICY_COLUMNS: &str = "id, name, sha256, length(file) AS size_bytes, status, metadata, shapes, uploaded_by, created_at, training_run_id";

/// A row of [`POLICY_COLUMNS`].
#[derive(sqlx::FromRow)]
struct PolicyRow {
    id: i64,
    name: String,
    sha256: String,
    size_bytes: i64,
    status: String,
    metadata: Option<String>,
    shapes: Option<String>,
    uploaded_by: Option<String>,
    created_at: String,
    training_run_id: Option<i64>,
}

async fn with_evaluation(db: &Db, row: PolicyRow) -> Result<Policy, DbError> {
    Ok(Policy {
        evaluation: latest_evaluation(db, row.id).await?,
        id: row.id,
        name: row.name,
        sha256: row.sha256,
        size_bytes: row.size_bytes,
        status: row.status,
        metadata: json_column(row.metadata),
        shapes: json_column(row.shapes),
        uploaded_by: row.uploaded_by,
        created_at: row.created_at,
        training_run_id: row.training_run_id,
    })
}

/// Stores a policy, or finds the one with the same bytes. The flag says whether it is new.
pub async fn insert_or_find(db: &Db, new: &NewPolicy<'_>) -> Result<(Policy, bool), DbError> {
    let inserted = sqlx::query_scalar::<_, i64>(
        "INSERT INTO policies (name, sha256, file, metadata, shapes, uploaded_by)
         VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT (sha256) DO NOTHING RETURNING id",
    )
    .bind(new.name)
    .bind(new.sha256)
    .bind(new.file)
    .bind(new.metadata.to_string())
    .bind(new.shapes.to_string())
    .bind(new.uploaded_by)
    .fetch_all(&db.writer)
    .await;
    let inserted = db.track(inserted)?.into_iter().next();
    let id = match inserted {
        Some(id) => id,
        None => {
            sqlx::query_scalar("SELECT id FROM policies WHERE sha256 = ?")
                .bind(new.sha256)
                .fetch_one(&db.writer)
                .await?
        }
    };
    let policy = get(db, id).await?.ok_or(DbError::RowNotFound)?;
    Ok((policy, inserted.is_some()))
}

pub async fn get(db: &Db, id: i64) -> Result<Option<Policy>, DbError> {
    let row: Option<PolicyRow> = sqlx::query_as(&format!(
        "SELECT {POLICY_COLUMNS} FROM policies WHERE id = ?"
    ))
    .bind(id)
    .fetch_optional(&db.reader)
    .await?;
    match row {
        Some(row) => Ok(Some(with_evaluation(db, row).await?)),
        None => Ok(None),
    }
}

/// Newest first.
pub async fn list(db: &Db) -> Result<Vec<Policy>, DbError> {
    let rows: Vec<PolicyRow> = sqlx::query_as(&format!(
        "SELECT {POLICY_COLUMNS} FROM policies ORDER BY id DESC"
    ))
    .fetch_all(&db.reader)
    .await?;
    let mut policies = Vec::with_capacity(rows.len());
    for row in rows {
        policies.push(with_evaluation(db, row).await?);
    }
    Ok(policies)
}

pub async fn file(db: &Db, id: i64) -> Result<Option<Vec<u8>>, DbError> {
    sqlx::query_scalar("SELECT file FROM policies WHERE id = ?")
        .bind(id)
        .fetch_optional(&db.reader)
        .await
}

/// The active policy's id and file, if one is active.
pub async fn active(db: &Db) -> Result<Option<(i64, Vec<u8>)>, DbError> {
    sqlx::query_as("SELECT id, file FROM policies WHERE status = 'active'")
        .fetch_optional(&db.reader)
        .await
}

/// Makes `id` the active policy and retires the one before it, in one transaction. Returns the
/// retired policy's id.
pub async fn activate(db: &Db, id: i64) -> Result<Option<i64>, DbError> {
    let mut tx = db.writer.begin().await?;
    let previous: Option<i64> =
        sqlx::query_scalar("SELECT id FROM policies WHERE status = 'active' AND id != ?")
            .bind(id)
            .fetch_optional(&mut *tx)
            .await?;
    sqlx::query("UPDATE policies SET status = 'retired' WHERE status = 'active' AND id != ?")
        .bind(id)
        .execute(&mut *tx)
        .await?;
    sqlx::query("UPDATE policies SET status = 'active' WHERE id = ?")
        .bind(id)
        .execute(&mut *tx)
        .await?;
    tx.commit().await?;
    Ok(previous)
}

/// Makes `id` active only if no policy is active, in one statement, so an operator's activation
/// that lands between a check and this write is never retired by it. Returns whether it did.
pub async fn activate_if_none_active(db: &Db, id: i64) -> Result<bool, DbError> {
    let done = sqlx::query(
        "UPDATE policies SET status = 'active'
         WHERE id = ? AND NOT EXISTS (SELECT 1 FROM policies WHERE status = 'active')",
    )
    .bind(id)
    .execute(&db.writer)
    .await?;
    Ok(done.rows_affected() == 1)
}

/// Records an evaluation as it is asked for (`queued`, or `running` when it starts at once):
/// `episodes` under `seed` on the cell with `cell_hash`, its twin departing from the cell file
/// by `mismatch`.
#[allow(clippy::too_many_arguments)]
pub async fn start_evaluation(
    db: &Db,
    queued: bool,
    policy_id: i64,
    episodes: i64,
    seed: u64,
    cell_hash: &str,
    on: &EvaluatedOn,
    rules: &str,
    requested_by: &str,
) -> Result<Evaluation, DbError> {
    let mismatch = on.mismatch();
    let rows = sqlx::query_as::<_, EvaluationRow>(
        "INSERT INTO policy_evaluations (policy_id, status, episodes, seed, cell_hash, noise_scale,
                calibration_scale, fault, randomise_cells, rules, requested_by)
         VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?) RETURNING *",
    )
    .bind(policy_id)
    .bind(if queued { "queued" } else { "running" })
    .bind(episodes)
    .bind(seed as i64)
    .bind(cell_hash)
    .bind(mismatch.noise_scale)
    .bind(mismatch.calibration_scale)
    .bind(mismatch.fault.map(|f| f.code()))
    .bind(on.is_drawn())
    .bind(rules)
    .bind(requested_by)
    .fetch_all(&db.writer)
    .await;
    let row = db.track(rows.and_then(super::only_row))?;
    Ok(Evaluation::from(row))
}

/// A queued evaluation leaves the queue: `running` from now.
pub async fn run_evaluation(db: &Db, id: i64) -> Result<(), DbError> {
    sqlx::query(&format!(
        "UPDATE policy_evaluations SET status = 'running', started_at = {NOW}
         WHERE id = ? AND status = 'queued'"
    ))
    .bind(id)
    .execute(&db.writer)
    .await?;
    Ok(())
}

/// Stores an evaluation's result (`Ok`: success rate, avg steps, failures) or its error, unless
/// it has ended already (at shutdown, [`fail_unfinished_evaluations`] may come first).
pub async fn finish_evaluation(
    db: &Db,
    id: i64,
    result: Result<(f64, Option<f64>, Value), String>,
) -> Result<(), DbError> {
    let (status, success, steps, failures, error) = match result {
        Ok((success, steps, failures)) => (
            "done",
            Some(success),
            steps,
            Some(failures.to_string()),
            None,
        ),
        // Stored for people to read: no backtrace a library put in its message.
        Err(error) => (
            "failed",
            None,
            None,
            None,
            Some(crate::error_text::without_backtrace(&error)),
        ),
    };
    sqlx::query(&format!(
        "UPDATE policy_evaluations SET status = ?, success_rate = ?, avg_steps = ?, failures = ?,
                error = ?, finished_at = {NOW} WHERE id = ? AND status IN ('queued', 'running')"
    ))
    .bind(status)
    .bind(success)
    .bind(steps)
    .bind(failures)
    .bind(error)
    .bind(id)
    .execute(&db.writer)
    .await?;
    Ok(())
}

pub async fn latest_evaluation(db: &Db, policy_id: i64) -> Result<Option<Evaluation>, DbError> {
    let row: Option<EvaluationRow> = sqlx::query_as(
        "SELECT * FROM policy_evaluations WHERE policy_id = ? ORDER BY id DESC LIMIT 1",
    )
    .bind(policy_id)
    .fetch_optional(&db.reader)
    .await?;
    Ok(row.map(Evaluation::from))
}

/// At start: every evaluation a previous run left `queued` or `running` becomes `failed`, so that
/// none reads as waiting or running forever. Returns how many.
pub async fn fail_leftover_evaluations(db: &Db) -> Result<u64, DbError> {
    fail_unfinished_evaluations(db, "the service stopped").await
}

/// Every `queued` or `running` evaluation becomes `failed`, its error saying that `why` happened
/// before it started or during it (at shutdown, and for what a previous run left). Returns how
/// many.
pub async fn fail_unfinished_evaluations(db: &Db, why: &str) -> Result<u64, DbError> {
    let done = sqlx::query(&format!(
        "UPDATE policy_evaluations SET
                error = ? || CASE status WHEN 'queued' THEN ' before the evaluation started'
                                         ELSE ' during the evaluation' END,
                status = 'failed', finished_at = {NOW}
         WHERE status IN ('queued', 'running')"
    ))
    .bind(why)
    .execute(&db.writer)
    .await?;
    Ok(done.rows_affected())
}

/// The latest finished evaluation of `policy_id` on the cell with `cell_hash`, under the twin as
/// the cell file describes it (noise and calibration scale 1, no fault) and with the cell's
/// rules: what the activation gate reads.
pub async fn latest_evaluation_on(
    db: &Db,
    policy_id: i64,
    cell_hash: &str,
) -> Result<Option<Evaluation>, DbError> {
    let row: Option<EvaluationRow> = sqlx::query_as(
        "SELECT * FROM policy_evaluations WHERE policy_id = ? AND cell_hash = ? AND status = 'done'
                AND noise_scale = 1 AND calibration_scale = 1 AND fault IS NULL
                AND randomise_cells = 0 AND rules = 'all'
         ORDER BY id DESC LIMIT 1",
    )
    .bind(policy_id)
    .bind(cell_hash)
    .fetch_optional(&db.reader)
    .await?;
    Ok(row.map(Evaluation::from))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    async fn store(db: &Db, name: &str) -> i64 {
        let new = NewPolicy {
            name,
            sha256: name,
            file: name.as_bytes(),
            metadata: json!({}),
            shapes: json!({}),
            uploaded_by: "test",
        };
        insert_or_find(db, &new).await.unwrap().0.id
    }

    async fn status(db: &Db, id: i64) -> String {
        get(db, id).await.unwrap().unwrap().status
    }

    /// The bundled default's first-start activation must never retire a policy an operator
    /// activated while the default was being evaluated (it raced once on a slow CI machine).
    #[tokio::test]
    async fn activating_only_when_none_is_active_leaves_an_operators_choice_alone() {
        let dir = tempfile::tempdir().unwrap();
        let db = Db::open(&dir.path().join("cell.db")).await.unwrap();
        let (bundled, chosen) = (store(&db, "bundled").await, store(&db, "chosen").await);
        assert_eq!(activate(&db, chosen).await.unwrap(), None);
        assert!(!activate_if_none_active(&db, bundled).await.unwrap());
        assert_eq!(status(&db, chosen).await, "active");
        assert_eq!(status(&db, bundled).await, "candidate");

        assert_eq!(activate(&db, bundled).await.unwrap(), Some(chosen));
        assert_eq!(status(&db, chosen).await, "retired");
        let fresh = store(&db, "fresh").await;
        assert!(!activate_if_none_active(&db, fresh).await.unwrap());

        let empty = Db::open(&dir.path().join("empty.db")).await.unwrap();
        let only = store(&empty, "only").await;
        assert!(activate_if_none_active(&empty, only).await.unwrap());
        assert_eq!(status(&empty, only).await, "active");
    }

    /// The activation gate reads only evaluations on the cell's own twin as its file says: none
    /// under a mismatch, none on drawn cells.
    #[tokio::test]
    async fn the_gate_reads_no_evaluation_under_a_mismatch() {
        let dir = tempfile::tempdir().unwrap();
        let db = Db::open(&dir.path().join("cell.db")).await.unwrap();
        let id = store(&db, "policy").await;
        let nominal = start_evaluation(
            &db,
            false,
            id,
            10,
            1,
            "cell",
            &EvaluatedOn::Cell(Mismatch::NONE),
            "all",
            "test",
        )
        .await
        .unwrap();
        assert_eq!(nominal.noise_scale, 1.0);
        assert_eq!(nominal.fault, None);
        finish_evaluation(&db, nominal.id, Ok((0.99, Some(40.0), json!({}))))
            .await
            .unwrap();
        let faulty = Mismatch {
            noise_scale: 2.0,
            calibration_scale: 3.0,
            fault: Some(crate::sim::Fault::FrozenCamera),
        };
        let mismatched = start_evaluation(
            &db,
            false,
            id,
            10,
            1,
            "cell",
            &EvaluatedOn::Cell(faulty),
            "all",
            "test",
        )
        .await
        .unwrap();
        finish_evaluation(&db, mismatched.id, Ok((0.5, None, json!({}))))
            .await
            .unwrap();
        let latest = latest_evaluation(&db, id).await.unwrap().unwrap();
        assert_eq!(latest.id, mismatched.id);
        assert_eq!((latest.noise_scale, latest.calibration_scale), (2.0, 3.0));
        assert_eq!(latest.fault.as_deref(), Some("frozen_camera"));
        assert!(!latest.randomise_cells);
        let drawn = EvaluatedOn::DrawnCells { fault: None };
        let across = start_evaluation(&db, false, id, 10, 1, "cell", &drawn, "all", "test")
            .await
            .unwrap();
        finish_evaluation(&db, across.id, Ok((1.0, Some(30.0), json!({}))))
            .await
            .unwrap();
        let latest = latest_evaluation(&db, id).await.unwrap().unwrap();
        assert_eq!(latest.id, across.id);
        assert!(latest.randomise_cells);
        let gate = latest_evaluation_on(&db, id, "cell")
            .await
            .unwrap()
            .unwrap();
        assert_eq!(gate.id, nominal.id);
    }

    /// Queued, then running, then ended once: at shutdown what waits and what runs fail with
    /// what happened to each, and a result arriving after that changes nothing.
    #[tokio::test]
    async fn unfinished_evaluations_fail_once_saying_whether_they_had_started() {
        let dir = tempfile::tempdir().unwrap();
        let db = Db::open(&dir.path().join("cell.db")).await.unwrap();
        let id = store(&db, "policy").await;
        let on = EvaluatedOn::Cell(Mismatch::NONE);
        let mut ids = Vec::new();
        for queued in [true, true, false] {
            let e = start_evaluation(&db, queued, id, 10, 1, "cell", &on, "all", "test")
                .await
                .unwrap();
            assert_eq!(e.status, if queued { "queued" } else { "running" });
            ids.push(e.id);
        }
        run_evaluation(&db, ids[1]).await.unwrap();
        let failed = fail_unfinished_evaluations(&db, "the service was stopped")
            .await
            .unwrap();
        assert_eq!(failed, 3);
        finish_evaluation(&db, ids[2], Ok((1.0, Some(30.0), json!({}))))
            .await
            .unwrap();
        let read = |e: i64| {
            let db = db.clone();
            async move {
                let row: (String, Option<String>) =
                    sqlx::query_as("SELECT status, error FROM policy_evaluations WHERE id = ?")
                        .bind(e)
                        .fetch_one(&db.reader)
                        .await
                        .unwrap();
                row
            }
        };
        let before = "the service was stopped before the evaluation started";
        let during = "the service was stopped during the evaluation";
        assert_eq!(read(ids[0]).await, ("failed".into(), Some(before.into())));
        assert_eq!(read(ids[1]).await, ("failed".into(), Some(during.into())));
        assert_eq!(read(ids[2]).await, ("failed".into(), Some(during.into())));
        assert_eq!(fail_leftover_evaluations(&db).await.unwrap(), 0);
    }
}
