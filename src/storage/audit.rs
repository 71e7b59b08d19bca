//! The audit log: who did what, when.

use super::{Db, DbError};
use serde::Serialize;
use serde_json::Value;
use sqlx::Row;

pub async fn record(db: &Db, actor: &str, action: &str, detail: Value) -> Result<(), DbError> {
    sqlx::query("INSERT INTO audit (actor, action, detail) VALUES (?, ?, ?)")
        .bind(actor)
        .bind(action)
        .bind(detail.to_string())
        .execute(&db.writer)
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

/// Newest first.
pub async fn list(db: &Db, limit: i64, offset: i64) -> Result<Vec<AuditEntry>, DbError> {
    let rows = sqlx::query("SELECT * FROM audit ORDER BY id DESC LIMIT ? OFFSET ?")
        .bind(limit)
        .bind(offset)
        .fetch_all(&db.reader)
        .await?;
    Ok(rows
        .iter()
        .map(|row| AuditEntry {
            id: row.get("id"),
            at: row.get("at"),
            actor: row.get("actor"),
            action: row.get("action"),
            detail: serde_json::from_str(row.get("detail")).unwrap_or(Value::Null),
        })
        .collect())
}
