//! The audit log: who did what, when.

use super::{Db, DbError};
use serde::Serialize;
use serde_json::Value;

pub async fn record(db: &Db, actor: &str, action: &str, detail: Value) -> Result<(), DbError> {
    let done = record_with(&db.writer, actor, action, &detail).await;
    db.track(done)
}

/// [`record`] with whatever executor the caller holds (a transaction that writes what is
/// audited with it).
pub async fn record_with<'e>(
    executor: impl sqlx::SqliteExecutor<'e>,
    actor: &str,
    action: &str,
    detail: &Value,
) -> Result<(), DbError> {
    sqlx::query("INSERT INTO audit (actor, action, detail) VALUES (?, ?, ?)")
        .bind(actor)
        .bind(action)
        .bind(detail.to_string())
        .execute(executor)
        .await?;
    Ok(())
}

#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct AuditEntry {
    pub id: i64,
    pub at: String,
    pub actor: String,
    pub action: String,
    pub detail: Value,
}

/// A row of `audit` as stored (`detail` is JSON text).
#[derive(sqlx::FromRow)]
struct AuditRow {
    id: i64,
    at: String,
    actor: String,
    action: String,
    detail: String,
}

impl From<AuditRow> for AuditEntry {
    fn from(row: AuditRow) -> Self {
        AuditEntry {
            id: row.id,
            at: row.at,
            actor: row.actor,
            action: row.action,
            detail: serde_json::from_str(&row.detail).unwrap_or(Value::Null),
        }
    }
}

/// Newest first.
pub async fn list(db: &Db, limit: i64, offset: i64) -> Result<Vec<AuditEntry>, DbError> {
    let rows: Vec<AuditRow> = sqlx::query_as(
        "SELECT id, at, actor, action, detail FROM audit ORDER BY id DESC LIMIT ? OFFSET ?",
    )
    .bind(limit)
    .bind(offset)
    .fetch_all(&db.reader)
    .await?;
    Ok(rows.into_iter().map(AuditEntry::from).collect())
}
