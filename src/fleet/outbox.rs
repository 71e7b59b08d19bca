//! The cell's side of replication: the `fleet_outbox` its triggers fill while it is in a
//! fleet, read in commit order and emptied once the fleet has what it named.

use super::REPLICATED;
use crate::storage::{Db, DbError};

/// The `cell_state` key whose value `on` makes the triggers fill the outbox.
const IN_FLEET: &str = "fleet";

/// One outbox row: a replicated row's table and key, and when it was written.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct Entry {
    pub seq: i64,
    pub table_name: String,
    pub key1: i64,
    pub key2: Option<i64>,
    /// When the row was committed on the cell, as a Julian day number.
    pub at_julian: f64,
}

/// The `cell_state` key naming the fleet the outbox fills for (its host and database).
const JOINED: &str = "fleet_joined";

/// Starts filling the outbox for the fleet `target` (host and database, no secrets), first
/// with every row the cell holds, unless it already fills it for that fleet: a cell joining a
/// fleet, or moving to another, sends its whole record once. Answers the rows queued.
pub async fn join(db: &Db, target: &str) -> Result<u64, DbError> {
    let mut tx = db.writer.begin().await?;
    let state: Vec<(String, String)> =
        sqlx::query_as("SELECT key, value FROM cell_state WHERE key IN (?, ?)")
            .bind(IN_FLEET)
            .bind(JOINED)
            .fetch_all(&mut *tx)
            .await?;
    let value = |key: &str| {
        state
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    };
    if value(IN_FLEET) == Some("on") && value(JOINED) == Some(target) {
        return Ok(0);
    }
    sqlx::query("DELETE FROM fleet_outbox")
        .execute(&mut *tx)
        .await?;
    let mut queued = 0;
    for table in REPLICATED {
        let key2 = table.key.get(1).copied().unwrap_or("NULL");
        let sql = format!(
            "INSERT INTO fleet_outbox (table_name, key1, key2)
             SELECT '{name}', {key1}, {key2} FROM {name} ORDER BY {key1}",
            name = table.name,
            key1 = table.key[0],
        );
        queued += sqlx::query(&sql).execute(&mut *tx).await?.rows_affected();
    }
    crate::storage::set_cell_value(&mut *tx, IN_FLEET, "on").await?;
    crate::storage::set_cell_value(&mut *tx, JOINED, target).await?;
    db.track(tx.commit().await)?;
    Ok(queued)
}

/// Stops filling the outbox and empties it, if the cell was in a fleet: a cell started
/// without one keeps no queue for it (joining again sends everything). Answers whether it was.
pub async fn leave(db: &Db) -> Result<bool, DbError> {
    let mut tx = db.writer.begin().await?;
    let left = sqlx::query("UPDATE cell_state SET value = 'off' WHERE key = ? AND value = 'on'")
        .bind(IN_FLEET)
        .execute(&mut *tx)
        .await?
        .rows_affected()
        > 0;
    if !left {
        return Ok(false);
    }
    sqlx::query("DELETE FROM fleet_outbox")
        .execute(&mut *tx)
        .await?;
    db.track(tx.commit().await)?;
    Ok(true)
}

/// The oldest `limit` entries, in commit order.
pub async fn oldest(
    reader: &mut sqlx::SqliteConnection,
    limit: i64,
) -> Result<Vec<Entry>, DbError> {
    sqlx::query_as(
        "SELECT seq, table_name, key1, key2, julianday(at) AS at_julian
         FROM fleet_outbox ORDER BY seq LIMIT ?",
    )
    .bind(limit)
    .fetch_all(reader)
    .await
}

/// Entries not yet sent.
pub async fn backlog(db: &Db) -> Result<i64, DbError> {
    sqlx::query_scalar("SELECT count(*) FROM fleet_outbox")
        .fetch_one(&db.reader)
        .await
}

/// Forgets the entries up to `seq`, which the fleet has committed.
pub async fn sent(db: &Db, through_seq: i64) -> Result<(), DbError> {
    let done = sqlx::query("DELETE FROM fleet_outbox WHERE seq <= ?")
        .bind(through_seq)
        .execute(&db.writer)
        .await;
    db.track(done)?;
    Ok(())
}

/// The Julian day number now, comparable with [`Entry::at_julian`].
pub fn julian_now() -> f64 {
    let unix_s = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    unix_s / 86_400.0 + 2_440_587.5
}
