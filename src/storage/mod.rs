//! SQLite storage (sqlx, runtime-checked queries): jobs and their steps, tokens, the audit log
//! and the cell's latched state. Schema in `migrations/`, embedded at build time.
//!
//! One writer connection (every write goes through it, so writes never contend) and a small
//! pool of readers; WAL so readers never wait for the writer; `synchronous = FULL` so a
//! committed step survives a power cut, not only a killed process; foreign keys on.
//!
//! A write that fails (a full disk, an I/O error) must leave nothing behind that makes a later
//! write look stored when it is not. sqlx counts a connection's open transactions itself, and
//! a failed `COMMIT` or a `ROLLBACK` after SQLite already rolled back leaves that count at one:
//! every later `begin()` is then a `SAVEPOINT` inside a transaction no one commits. So the
//! writer checks its connection each time it is handed back ([`connection_is_clean`]) and drops
//! one that is, or believes it is, inside a transaction; the next write opens a fresh one.
//! And a write that returns rows is stepped to its end ([`only_row`]): outside a transaction
//! SQLite commits when the statement ends, and sqlx drops the error of a statement it stops
//! early. [`health::WriteHealth`] keeps the last write fault for `/api/health`.

pub mod audit;
pub mod demonstrations;
pub mod health;
pub mod jobs;
pub mod machine;
pub mod policies;
pub mod recorder;
pub mod steps;
pub mod tokens;
pub mod training;

use sqlx::sqlite::{
    SqliteConnectOptions, SqliteConnection, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous,
};
use sqlx::{Connection, SqlitePool};
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

pub use sqlx::Error as DbError;

/// The database: one writer, several readers.
#[derive(Clone)]
pub struct Db {
    pub writer: SqlitePool,
    pub reader: SqlitePool,
    /// Whether writes commit: the last write fault, until a write commits again.
    pub health: Arc<health::WriteHealth>,
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
    /// A URL where a file path belongs (`postgres://…`, `sqlite://…`): opened as a path it
    /// would make a directory named after the scheme and a SQLite file in it.
    #[error(
        "the database `{path}` is a URL; the database is a SQLite file path (such as \
         data/celld.db), and celld does not connect to a {scheme} server"
    )]
    NotAPath { path: String, scheme: String },
}

/// The scheme of `path` when it is a URL (`scheme://...`).
fn url_scheme(path: &Path) -> Option<String> {
    let text = path.to_str()?;
    let (scheme, _) = text.split_once("://")?;
    let is_scheme = !scheme.is_empty()
        && scheme.starts_with(|c: char| c.is_ascii_alphabetic())
        && scheme
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c));
    is_scheme.then(|| scheme.to_string())
}

impl Db {
    /// Opens (creating if missing) and migrates the database file.
    pub async fn open(path: &Path) -> Result<Db, OpenError> {
        let shown = path.display().to_string();
        if let Some(scheme) = url_scheme(path) {
            return Err(OpenError::NotAPath {
                path: shown,
                scheme,
            });
        }
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
            .after_release(|connection, _| {
                Box::pin(async move { Ok(connection_is_clean(connection).await) })
            })
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
        Ok(Db {
            writer,
            reader,
            health: Default::default(),
        })
    }

    /// Notes a write's outcome for [`health::WriteHealth`] and passes it on: a commit clears
    /// the fault, a storage fault ([`is_fault`]) sets it; a refused row says nothing of the disk.
    pub fn track<T>(&self, result: Result<T, DbError>) -> Result<T, DbError> {
        match &result {
            Ok(_) => self.health.succeeded(),
            Err(error) if is_fault(error) => self.health.failed(error),
            Err(_) => {}
        }
        result
    }

    /// `PRAGMA integrity_check`'s answer (`ok` when the file is sound).
    pub async fn integrity_check(&self) -> Result<String, DbError> {
        sqlx::query_scalar("PRAGMA integrity_check")
            .fetch_one(&self.reader)
            .await
    }

    /// A latched value that survives restarts (`estop`).
    pub async fn cell_flag(&self, key: &str) -> Result<bool, DbError> {
        Ok(self.cell_value(key).await?.as_deref() == Some("true"))
    }

    /// A value of the cell's that survives restarts (a flag, the counters' JSON), if stored.
    pub async fn cell_value(&self, key: &str) -> Result<Option<String>, DbError> {
        sqlx::query_scalar("SELECT value FROM cell_state WHERE key = ?")
            .bind(key)
            .fetch_optional(&self.reader)
            .await
    }
}

/// Whether the writer's connection may be handed out again: SQLite is in autocommit mode
/// (a `BEGIN` succeeds) and sqlx counts no open transaction. A connection that fails either
/// is closed by the pool, which rolls back whatever it held.
async fn connection_is_clean(connection: &mut SqliteConnection) -> bool {
    // Queued behind the rollback sqlx started for a dropped transaction, so that has run.
    let begun = sqlx::Executor::execute(&mut *connection, "BEGIN; ROLLBACK").await;
    if begun.is_err() {
        tracing::warn!("the database writer was left inside a transaction; reconnecting");
        return false;
    }
    if connection.is_in_transaction() {
        tracing::warn!("the database writer lost count of its transactions; reconnecting");
        return false;
    }
    true
}

/// Whether an error is the storage failing (a full disk, an I/O error, a busy or read-only
/// database, the writer unreachable) rather than the rows being refused or not found: the
/// same write may pass once the fault clears.
pub fn is_fault(error: &DbError) -> bool {
    match error {
        DbError::Database(e) => {
            let primary = e
                .code()
                .and_then(|code| code.parse::<i32>().ok())
                .map(|code| code & 0xff);
            // SQLITE_BUSY, LOCKED, NOMEM, READONLY, IOERR, CORRUPT, FULL, CANTOPEN, PROTOCOL.
            matches!(primary, Some(5 | 6 | 7 | 8 | 10 | 11 | 13 | 14 | 15))
        }
        DbError::Io(_)
        | DbError::PoolTimedOut
        | DbError::PoolClosed
        | DbError::WorkerCrashed
        | DbError::Protocol(_) => true,
        _ => false,
    }
}

/// What a request that met a storage fault ([`is_fault`]) answers.
pub fn unavailable_message(error: &DbError) -> String {
    format!("storage unavailable, nothing was stored: {error}")
}

/// The one row an `INSERT … RETURNING` answers, from all its rows (`fetch_all`). `fetch_one`
/// stops after the first row and resets the statement; outside a transaction SQLite commits
/// at that reset, and sqlx drops its error: a write that could not commit would look stored.
pub fn only_row<T>(rows: Vec<T>) -> Result<T, DbError> {
    rows.into_iter().next().ok_or(DbError::RowNotFound)
}

/// Sets a latched value (`estop`).
pub async fn set_cell_flag<'e>(
    executor: impl sqlx::SqliteExecutor<'e>,
    key: &str,
    on: bool,
) -> Result<(), DbError> {
    set_cell_value(executor, key, if on { "true" } else { "false" }).await
}

/// Sets a value of the cell's that survives restarts ([`Db::cell_value`]).
pub async fn set_cell_value<'e>(
    executor: impl sqlx::SqliteExecutor<'e>,
    key: &str,
    value: &str,
) -> Result<(), DbError> {
    sqlx::query(
        "INSERT INTO cell_state (key, value) VALUES (?, ?)
         ON CONFLICT (key) DO UPDATE SET value = excluded.value",
    )
    .bind(key)
    .bind(value)
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

#[cfg(test)]
mod full_disk;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_are_told_from_paths() {
        let scheme = |text: &str| url_scheme(Path::new(text));
        assert_eq!(
            scheme("postgres://cell@db/celld").as_deref(),
            Some("postgres")
        );
        assert_eq!(scheme("sqlite://celld.db").as_deref(), Some("sqlite"));
        for path in [
            "data/celld.db",
            "/var/lib/celld/celld.db",
            "a:b/c.db",
            "://x",
            "1x://y",
        ] {
            assert_eq!(scheme(path), None, "{path}");
        }
    }
}
