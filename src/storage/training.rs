//! Training runs: settings, the demonstrations used, progress and curve, the policy made.

use super::{Db, DbError, NOW, json_column};
use serde::Serialize;
use serde_json::Value;
use sqlx::Row;
use sqlx::sqlite::SqliteRow;

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

fn from_row(row: &SqliteRow) -> TrainingRun {
    TrainingRun {
        id: row.get("id"),
        status: row.get("status"),
        settings: json_column(row.get("settings")),
        demonstration_ids: json_column(row.get("demonstration_ids")),
        stage: row.get("stage"),
        progress: row.get("progress"),
        curve: json_column(row.get("curve")),
        figures: json_column(row.get("figures")),
        policy_id: row.get("policy_id"),
        error: row.get("error"),
        created_by: row.get("created_by"),
        started_at: row.get("started_at"),
        finished_at: row.get("finished_at"),
    }
}

pub async fn start(
    db: &Db,
    settings: &Value,
    demonstration_ids: &[i64],
    created_by: &str,
) -> Result<TrainingRun, DbError> {
    let row = sqlx::query(
        "INSERT INTO training_runs (status, settings, demonstration_ids, stage, created_by)
         VALUES ('running', ?, ?, 'demonstrations', ?) RETURNING *",
    )
    .bind(settings.to_string())
    .bind(serde_json::json!(demonstration_ids).to_string())
    .bind(created_by)
    .fetch_one(&db.writer)
    .await?;
    Ok(from_row(&row))
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
    .bind(error)
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
    let row = sqlx::query("SELECT * FROM training_runs WHERE id = ?")
        .bind(id)
        .fetch_optional(&db.reader)
        .await?;
    Ok(row.as_ref().map(from_row))
}

/// Newest first, without their curves (read one run for that).
pub async fn list(db: &Db) -> Result<Vec<TrainingRun>, DbError> {
    let rows = sqlx::query("SELECT * FROM training_runs ORDER BY id DESC")
        .fetch_all(&db.reader)
        .await?;
    Ok(rows
        .iter()
        .map(|row| TrainingRun {
            curve: Value::Null,
            ..from_row(row)
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
