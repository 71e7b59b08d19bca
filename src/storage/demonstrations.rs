//! Demonstrations: JSON Lines bodies (the `learning::demos` format) with their source and cell.

use super::{Db, DbError};
use crate::learning::demos::{self, DemoEpisode};
use serde::Serialize;

/// A demonstration as listed (the steps are exported separately); read as a row of
/// [`COLUMNS`].
#[derive(Debug, Clone, PartialEq, Serialize, sqlx::FromRow, utoipa::ToSchema)]
pub struct Demonstration {
    pub id: i64,
    pub name: String,
    pub source: String,
    pub cell_hash: String,
    pub job_id: Option<i64>,
    pub episodes: i64,
    pub steps: i64,
    /// What the recorded states are: `absolute` (the paper's state), `cell-relative` or
    /// `cell-scaled` (the inputs of a policy for any cell); a training run learns only from its
    /// own kind.
    pub inputs: String,
    pub created_by: Option<String>,
    pub created_at: String,
}

const COLUMNS: &str =
    "id, name, source, cell_hash, job_id, episodes, steps, inputs, created_by, created_at";

/// What a new demonstration is.
pub struct NewDemonstration<'a> {
    pub name: &'a str,
    pub source: &'a str,
    pub cell_hash: &'a str,
    pub job_id: Option<i64>,
    /// A `PolicyInputs` name: what the recorded states are.
    pub inputs: &'a str,
    pub created_by: &'a str,
}

/// Canonical JSON Lines of the episodes.
pub fn body_of(episodes: &[DemoEpisode]) -> String {
    let mut out = Vec::new();
    demos::write_jsonl(episodes, &mut out).expect("writing to memory cannot fail");
    String::from_utf8(out).expect("JSON is UTF-8")
}

pub async fn insert<'e>(
    executor: impl sqlx::SqliteExecutor<'e>,
    new: &NewDemonstration<'_>,
    episodes: &[DemoEpisode],
) -> Result<i64, DbError> {
    let steps: usize = episodes.iter().map(|e| e.steps.len()).sum();
    sqlx::query_scalar(
        "INSERT INTO demonstrations
             (name, source, cell_hash, job_id, episodes, steps, inputs, body, created_by)
         VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?) RETURNING id",
    )
    .bind(new.name)
    .bind(new.source)
    .bind(new.cell_hash)
    .bind(new.job_id)
    .bind(episodes.len() as i64)
    .bind(steps as i64)
    .bind(new.inputs)
    .bind(body_of(episodes))
    .bind(new.created_by)
    .fetch_all(executor)
    .await
    .and_then(super::only_row)
}

pub async fn get(db: &Db, id: i64) -> Result<Option<Demonstration>, DbError> {
    sqlx::query_as(&format!(
        "SELECT {COLUMNS} FROM demonstrations WHERE id = ?"
    ))
    .bind(id)
    .fetch_optional(&db.reader)
    .await
}

/// Newest first.
pub async fn list(db: &Db) -> Result<Vec<Demonstration>, DbError> {
    sqlx::query_as(&format!(
        "SELECT {COLUMNS} FROM demonstrations ORDER BY id DESC"
    ))
    .fetch_all(&db.reader)
    .await
}

pub async fn body(db: &Db, id: i64) -> Result<Option<String>, DbError> {
    sqlx::query_scalar("SELECT body FROM demonstrations WHERE id = ?")
        .bind(id)
        .fetch_optional(&db.reader)
        .await
}

/// Deletes one; false when there was none.
pub async fn delete(db: &Db, id: i64) -> Result<bool, DbError> {
    let done = sqlx::query("DELETE FROM demonstrations WHERE id = ?")
        .bind(id)
        .execute(&db.writer)
        .await?;
    Ok(done.rows_affected() > 0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use sqlx::sqlite::{SqliteConnectOptions, SqlitePoolOptions};

    const INSERT: &str = "INSERT INTO demonstrations \
        (name, source, cell_hash, job_id, episodes, steps, body, created_by, inputs) \
        VALUES ('kept', 'scripted', 'c0ffee', NULL, 2, 30, '{}', 'admin', ?)";

    /// A database made before demonstrations could hold cell-scaled inputs keeps every row,
    /// field for field, when it is opened by this build, which then stores the new kind.
    #[tokio::test]
    async fn demonstrations_stored_before_cell_scaled_inputs_are_kept_field_for_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cell.db");
        let options = SqliteConnectOptions::new()
            .filename(&path)
            .create_if_missing(true)
            .foreign_keys(true);
        let old = SqlitePoolOptions::new()
            .max_connections(1)
            .connect_with(options)
            .await
            .unwrap();
        let mut before = sqlx::migrate!();
        before.migrations = before
            .migrations
            .iter()
            .filter(|m| m.version <= 7)
            .cloned()
            .collect::<Vec<_>>()
            .into();
        before.run(&old).await.unwrap();
        for inputs in ["absolute", "cell-relative"] {
            sqlx::query(INSERT)
                .bind(inputs)
                .execute(&old)
                .await
                .unwrap();
        }
        let refused = sqlx::query(INSERT).bind("cell-scaled").execute(&old).await;
        assert!(refused.is_err(), "the old table takes cell-scaled inputs");
        let rows: Vec<Demonstration> =
            sqlx::query_as(&format!("SELECT {COLUMNS} FROM demonstrations ORDER BY id"))
                .fetch_all(&old)
                .await
                .unwrap();
        old.close().await;

        let db = Db::open(&path).await.unwrap();
        let mut listed = list(&db).await.unwrap();
        listed.sort_by_key(|d| d.id);
        assert_eq!(listed, rows);
        assert_eq!(body(&db, rows[1].id).await.unwrap().as_deref(), Some("{}"));
        let id = insert(
            &db.writer,
            &NewDemonstration {
                name: "scaled",
                source: "scripted",
                cell_hash: "c0ffee",
                job_id: None,
                inputs: "cell-scaled",
                created_by: "admin",
            },
            &[],
        )
        .await
        .unwrap();
        assert_eq!(get(&db, id).await.unwrap().unwrap().inputs, "cell-scaled");
        assert_eq!(db.integrity_check().await.unwrap(), "ok");
    }
}
