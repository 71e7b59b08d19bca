//! SQLite storage (sqlx, runtime-checked queries): jobs and their steps, tokens, the audit log
//! and the cell's latched state. Schema in `migrations/`, embedded at build time.
//!
//! One writer connection (every write goes through it, so writes never contend) and a small
//! pool of readers; WAL so readers never wait for the writer; `synchronous = FULL` so a
//! committed step survives a power cut, not only a killed process; foreign keys on.

pub mod audit;
pub mod demonstrations;
pub mod jobs;
pub mod policies;
pub mod recorder;
pub mod steps;
pub mod tokens;
pub mod training;

use sqlx::SqlitePool;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use std::path::Path;
use std::time::Duration;

pub use sqlx::Error as DbError;

/// The database: one writer, several readers.
#[derive(Clone)]
pub struct Db {
    pub writer: SqlitePool,
    pub reader: SqlitePool,
}

#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error("cannot create {path}: {source}")]
    Directory {
        path: String,
        source: std::io::Error,
    },
    #[error("cannot open the database {path}: {source}")]
    Open { path: String, source: sqlx::Error },
    #[error("cannot migrate the database {path}: {source}")]
    Migrate {
        path: String,
        source: sqlx::migrate::MigrateError,
    },
}

impl Db {
    /// Opens (creating if missing) and migrates the database file.
    pub async fn open(path: &Path) -> Result<Db, OpenError> {
        let shown = path.display().to_string();
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|source| OpenError::Directory {
                path: dir.display().to_string(),
                source,
            })?;
        }
        let base = SqliteConnectOptions::new()
            .filename(path)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(5));
        let options = base
            .clone()
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Full);
        let open_error = |source| OpenError::Open {
            path: shown.clone(),
            source,
        };
        let writer = SqlitePoolOptions::new()
            .max_connections(1)
            .connect_with(options)
            .await
            .map_err(open_error)?;
        sqlx::migrate!()
            .run(&writer)
            .await
            .map_err(|source| OpenError::Migrate {
                path: shown.clone(),
                source,
            })?;
        let reader = SqlitePoolOptions::new()
            .max_connections(4)
            .connect_with(base.read_only(true))
            .await
            .map_err(open_error)?;
        Ok(Db { writer, reader })
    }

    /// `PRAGMA integrity_check`'s answer (`ok` when the file is sound).
    pub async fn integrity_check(&self) -> Result<String, DbError> {
        sqlx::query_scalar("PRAGMA integrity_check")
            .fetch_one(&self.reader)
            .await
    }

    /// A latched value that survives restarts (`estop`).
    pub async fn cell_flag(&self, key: &str) -> Result<bool, DbError> {
        let value: Option<String> =
            sqlx::query_scalar("SELECT value FROM cell_state WHERE key = ?")
                .bind(key)
                .fetch_optional(&self.reader)
                .await?;
        Ok(value.as_deref() == Some("true"))
    }
}

/// Sets a latched value (`estop`).
pub async fn set_cell_flag<'e>(
    executor: impl sqlx::SqliteExecutor<'e>,
    key: &str,
    on: bool,
) -> Result<(), DbError> {
    sqlx::query(
        "INSERT INTO cell_state (key, value) VALUES (?, ?)
         ON CONFLICT (key) DO UPDATE SET value = excluded.value",
    )
    .bind(key)
    .bind(if on { "true" } else { "false" })
    .execute(executor)
    .await?;
    Ok(())
}

/// A JSON text column as a value (null when absent or unreadable).
pub(crate) fn json_column(text: Option<String>) -> serde_json::Value {
    text.and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or(serde_json::Value::Null)
}

/// SQLite's current time in the schema's format.
pub const NOW: &str = "strftime('%Y-%m-%dT%H:%M:%fZ', 'now')";
