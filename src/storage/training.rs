//! Training runs: settings, the demonstrations used, progress and curve, the policy made.

use super::{Db, DbError, NOW, json_column};
use serde::Serialize;
use serde_json::Value;

#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct TrainingRun {
    pub id: i64,
    pub status: String,
    pub settings: Value,
    pub demonstration_ids: Value,
    pub stage: Option<String>,
    pub progress: f64,
    pub curve: Value,
    pub figures: Value,
    pub policy_id: Option<i64>,
    pub error: Option<String>,
    pub created_by: String,
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

pub async fn start(
    db: &Db,
    settings: &Value,
    demonstration_ids: &[i64],
    created_by: &str,
) -> Result<TrainingRun, DbError> {
    let row: TrainingRunRow = sqlx::query_as(
        "INSERT INTO training_runs (status, settings, demonstration_ids, stage, created_by)
         VALUES ('running', ?, ?, 'demonstrations', ?) RETURNING *",
    )
    .bind(settings.to_string())
    .bind(serde_json::json!(demonstration_ids).to_string())
    .bind(created_by)
    .fetch_one(&db.writer)
    .await?;
    Ok(TrainingRun::from(row))
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

/// Ends a run: `succeeded` with its policy and figures, or `failed` / `cancelled` with why.
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
                finished_at = {NOW} WHERE id = ?"
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

/// At start: a run the last process left running cannot go on.
pub async fn fail_leftovers(db: &Db) -> Result<u64, DbError> {
    let done = sqlx::query(&format!(
        "UPDATE training_runs SET status = 'failed', error = 'the service stopped during the run',
                finished_at = {NOW} WHERE status = 'running'"
    ))
    .execute(&db.writer)
    .await?;
    Ok(done.rows_affected())
}
