//! Training runs: settings, the demonstrations used, progress and curve, the policy made.

use super::{Db, DbError, NOW, json_column};
use serde::Serialize;
use serde_json::Value;

#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct TrainingRun {
    pub id: i64,
    /// `queued` (waiting its turn in the work queue), `running`, `succeeded`, `failed` or
    /// `cancelled`.
    #[schema(pattern = "^(queued|running|succeeded|failed|cancelled)$")]
    pub status: String,
    /// While `queued`: its place in the work queue, shared with evaluations (1 = next to
    /// start); otherwise null.
    #[schema(minimum = 1)]
    pub queue_position: Option<usize>,
    pub settings: Value,
    pub demonstration_ids: Value,
    pub stage: Option<String>,
    pub progress: f64,
    pub curve: Value,
    pub figures: Value,
    pub policy_id: Option<i64>,
    pub error: Option<String>,
    pub created_by: String,
    /// When it was asked for, then when it left the queue and started.
    pub started_at: String,
    pub finished_at: Option<String>,
}

/// A row of `training_runs` as stored (the JSON columns as text).
#[derive(sqlx::FromRow)]
struct TrainingRunRow {
    id: i64,
    status: String,
    settings: Option<String>,
    demonstration_ids: Option<String>,
    stage: Option<String>,
    progress: f64,
    curve: Option<String>,
    figures: Option<String>,
    policy_id: Option<i64>,
    error: Option<String>,
    created_by: String,
    started_at: String,
    finished_at: Option<String>,
}

impl From<TrainingRunRow> for TrainingRun {
    fn from(row: TrainingRunRow) -> Self {
        TrainingRun {
            id: row.id,
            status: row.status,
            // The queue's to say (`workflows::queue`); storage knows only that it waits.
            queue_position: None,
            settings: json_column(row.settings),
            demonstration_ids: json_column(row.demonstration_ids),
            stage: row.stage,
            progress: row.progress,
            curve: json_column(row.curve),
            figures: json_column(row.figures),
            policy_id: row.policy_id,
            error: row.error,
            created_by: row.created_by,
            started_at: row.started_at,
            finished_at: row.finished_at,
        }
    }
}

/// Records a run as it is asked for: `queued`, or `running` when it starts at once.
pub async fn start(
    db: &Db,
    queued: bool,
    settings: &Value,
    demonstration_ids: &[i64],
    created_by: &str,
) -> Result<TrainingRun, DbError> {
    let rows = sqlx::query_as::<_, TrainingRunRow>(
        "INSERT INTO training_runs (status, settings, demonstration_ids, stage, created_by)
         VALUES (?, ?, ?, 'demonstrations', ?) RETURNING *",
    )
    .bind(if queued { "queued" } else { "running" })
    .bind(settings.to_string())
    .bind(serde_json::json!(demonstration_ids).to_string())
    .bind(created_by)
    .fetch_all(&db.writer)
    .await;
    let row = db.track(rows.and_then(super::only_row))?;
    Ok(TrainingRun::from(row))
}

/// A queued run leaves the queue: `running` from now.
pub async fn run(db: &Db, id: i64) -> Result<(), DbError> {
    sqlx::query(&format!(
        "UPDATE training_runs SET status = 'running', started_at = {NOW}
         WHERE id = ? AND status = 'queued'"
    ))
    .bind(id)
    .execute(&db.writer)
    .await?;
    Ok(())
}

/// Records the demonstrations a run uses once it has them (a run may record its own).
pub async fn set_demonstrations(db: &Db, id: i64, ids: &[i64]) -> Result<(), DbError> {
    sqlx::query("UPDATE training_runs SET demonstration_ids = ? WHERE id = ?")
        .bind(serde_json::json!(ids).to_string())
        .bind(id)
        .execute(&db.writer)
        .await?;
    Ok(())
}

/// Stores the progress and curve so far.
pub async fn update(
    db: &Db,
    id: i64,
    stage: &str,
    progress: f64,
    curve: &Value,
) -> Result<(), DbError> {
    sqlx::query("UPDATE training_runs SET stage = ?, progress = ?, curve = ? WHERE id = ?")
        .bind(stage)
        .bind(progress)
        .bind(curve.to_string())
        .bind(id)
        .execute(&db.writer)
        .await?;
    Ok(())
}

/// Ends a run: `succeeded` with its policy and figures, or `failed` / `cancelled` with why;
/// unless it has ended already (at shutdown, [`fail_unfinished`] may come first).
pub async fn finish(
    db: &Db,
    id: i64,
    status: &str,
    policy_id: Option<i64>,
    figures: Option<&Value>,
    error: Option<&str>,
) -> Result<(), DbError> {
    let mut tx = db.writer.begin().await?;
    sqlx::query(&format!(
        "UPDATE training_runs SET status = ?, policy_id = ?, figures = ?, error = ?,
                progress = CASE WHEN ? = 'succeeded' THEN 1 ELSE progress END,
                finished_at = {NOW} WHERE id = ? AND status IN ('queued', 'running')"
    ))
    .bind(status)
    .bind(policy_id)
    .bind(figures.map(Value::to_string))
    // Stored for people to read: no backtrace a library put in its message.
    .bind(error.map(crate::error_text::without_backtrace))
    .bind(status)
    .bind(id)
    .execute(&mut *tx)
    .await?;
    if let Some(policy_id) = policy_id {
        sqlx::query(
            "UPDATE policies SET training_run_id = ? WHERE id = ? AND training_run_id IS NULL",
        )
        .bind(id)
        .bind(policy_id)
        .execute(&mut *tx)
        .await?;
    }
    tx.commit().await
}

pub async fn get(db: &Db, id: i64) -> Result<Option<TrainingRun>, DbError> {
    let row: Option<TrainingRunRow> = sqlx::query_as("SELECT * FROM training_runs WHERE id = ?")
        .bind(id)
        .fetch_optional(&db.reader)
        .await?;
    Ok(row.map(TrainingRun::from))
}

/// Newest first, without their curves (read one run for that).
pub async fn list(db: &Db) -> Result<Vec<TrainingRun>, DbError> {
    let rows: Vec<TrainingRunRow> = sqlx::query_as("SELECT * FROM training_runs ORDER BY id DESC")
        .fetch_all(&db.reader)
        .await?;
    Ok(rows
        .into_iter()
        .map(|row| TrainingRun {
            curve: Value::Null,
            ..TrainingRun::from(row)
        })
        .collect())
}

/// At start: a run the last process left queued or running cannot go on.
pub async fn fail_leftovers(db: &Db) -> Result<u64, DbError> {
    fail_unfinished(db, "the service stopped").await
}

/// Every `queued` or `running` run becomes `failed`, its error saying that `why` happened before
/// it started or during it (at shutdown, and for what a previous run left). Returns how many.
pub async fn fail_unfinished(db: &Db, why: &str) -> Result<u64, DbError> {
    let done = sqlx::query(&format!(
        "UPDATE training_runs SET
                error = ? || CASE status WHEN 'queued' THEN ' before the run started'
                                         ELSE ' during the run' END,
                status = 'failed', finished_at = {NOW}
         WHERE status IN ('queued', 'running')"
    ))
    .bind(why)
    .execute(&db.writer)
    .await?;
    Ok(done.rows_affected())
}

#[cfg(test)]
mod tests {
    use super::*;
    use sqlx::sqlite::{SqliteConnectOptions, SqlitePoolOptions};

    /// The migration that lets runs and evaluations be `queued` makes both tables again: every
    /// row and every link (policy → run, run → policy) comes through, and the new status holds.
    #[tokio::test]
    async fn queued_work_migration_keeps_rows_and_lineage() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cell.db");
        let options = SqliteConnectOptions::new()
            .filename(&path)
            .foreign_keys(true)
            .create_if_missing(true);
        let before = SqlitePoolOptions::new()
            .max_connections(1)
            .connect_with(options)
            .await
            .unwrap();
        let mut migrator = sqlx::migrate!();
        migrator.migrations = migrator
            .migrations
            .iter()
            .filter(|m| m.version < 11)
            .cloned()
            .collect::<Vec<_>>()
            .into();
        migrator.run(&before).await.unwrap();
        for statement in [
            "INSERT INTO policies (id, name, sha256, file, metadata, shapes, uploaded_by)
             VALUES (7, 'p', 'abc', x'00', '{}', '{}', 't')",
            "INSERT INTO training_runs (id, status, settings, demonstration_ids, policy_id,
                    created_by) VALUES (3, 'succeeded', '{}', '[1]', 7, 't')",
            "UPDATE policies SET training_run_id = 3 WHERE id = 7",
            "INSERT INTO policy_evaluations (id, policy_id, status, episodes, seed, cell_hash,
                    requested_by, noise_scale, fault) VALUES (5, 7, 'done', 10, 1, 'h', 't', 2, 'occlusion')",
        ] {
            sqlx::query(statement).execute(&before).await.unwrap();
        }
        before.close().await;

        let db = Db::open(&path).await.unwrap();
        let kept = get(&db, 3).await.unwrap().unwrap();
        assert_eq!(
            (kept.status.as_str(), kept.policy_id),
            ("succeeded", Some(7))
        );
        let policy = crate::storage::policies::get(&db, 7)
            .await
            .unwrap()
            .unwrap();
        assert_eq!(policy.training_run_id, Some(3));
        let evaluation = policy.evaluation.unwrap();
        assert_eq!((evaluation.id, evaluation.noise_scale), (5, 2.0));
        assert_eq!(evaluation.fault.as_deref(), Some("occlusion"));
        let fk: Vec<(String,)> = sqlx::query_as("SELECT \"table\" FROM pragma_foreign_key_check")
            .fetch_all(&db.reader)
            .await
            .unwrap();
        assert!(fk.is_empty(), "{fk:?}");

        let queued = start(&db, true, &serde_json::json!({}), &[], "t")
            .await
            .unwrap();
        assert_eq!(queued.status, "queued");
        run(&db, queued.id).await.unwrap();
        assert_eq!(
            get(&db, queued.id).await.unwrap().unwrap().status,
            "running"
        );
        let waiting = start(&db, true, &serde_json::json!({}), &[], "t")
            .await
            .unwrap();
        assert_eq!(fail_unfinished(&db, "stopped").await.unwrap(), 2);
        let read = get(&db, waiting.id).await.unwrap().unwrap();
        assert_eq!(
            read.error.as_deref(),
            Some("stopped before the run started")
        );
        finish(&db, waiting.id, "cancelled", None, None, Some("late"))
            .await
            .unwrap();
        let read = get(&db, waiting.id).await.unwrap().unwrap();
        assert_eq!(read.status, "failed", "an ended run stays as it ended");
    }
}
