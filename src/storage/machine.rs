//! The machine state's record: the PackML transitions in order, and the production counters
//! (kept across restarts in `cell_state`).

use super::{Db, DbError};
use crate::cell::MachineUpdate;
use crate::cell::packml::Counters;
use serde::Serialize;

const COUNTERS_KEY: &str = "counters";

/// Stores an update's transitions and its counters, in the caller's transaction.
pub async fn record(
    tx: &mut sqlx::SqliteConnection,
    update: &MachineUpdate,
) -> Result<(), DbError> {
    for transition in &update.transitions {
        sqlx::query(
            "INSERT INTO machine_transitions (from_state, to_state, cause) VALUES (?, ?, ?)",
        )
        .bind(transition.from.name())
        .bind(transition.to.name())
        .bind(&transition.cause)
        .execute(&mut *tx)
        .await?;
    }
    let counters = serde_json::to_string(&update.machine.counters)
        .map_err(|e| DbError::Protocol(format!("counters: {e}")))?;
    super::set_cell_value(&mut *tx, COUNTERS_KEY, &counters).await
}

/// The counters as last stored (zero on a new database). Counters that cannot be read are
/// an error, not zeros: a plant's part count must not silently restart.
pub async fn counters(db: &Db) -> Result<Counters, DbError> {
    match db.cell_value(COUNTERS_KEY).await? {
        None => Ok(Counters::default()),
        Some(text) => serde_json::from_str(&text)
            .map_err(|e| DbError::Protocol(format!("the stored counters do not parse: {e}"))),
    }
}

/// One stored transition.
#[derive(Debug, Clone, PartialEq, Serialize, sqlx::FromRow, utoipa::ToSchema)]
pub struct StoredTransition {
    pub id: i64,
    pub at: String,
    pub from_state: String,
    pub to_state: String,
    pub cause: String,
}

/// The latest `limit` transitions, newest first.
pub async fn transitions(db: &Db, limit: i64) -> Result<Vec<StoredTransition>, DbError> {
    sqlx::query_as(
        "SELECT id, at, from_state, to_state, cause FROM machine_transitions
         ORDER BY id DESC LIMIT ?",
    )
    .bind(limit)
    .fetch_all(&db.reader)
    .await
}

/// Cycle times of the latest `limit` good parts, s, newest first, from their jobs' start and
/// end as stored.
pub async fn recent_cycle_times(db: &Db, limit: i64) -> Result<Vec<CycleTime>, DbError> {
    sqlx::query_as(
        "SELECT id AS job_id, finished_at,
                (julianday(finished_at) - julianday(started_at)) * 86400.0 AS cycle_time_s
         FROM jobs WHERE status = 'succeeded' AND started_at IS NOT NULL
         ORDER BY id DESC LIMIT ?",
    )
    .bind(limit)
    .fetch_all(&db.reader)
    .await
}

/// A good part's cycle time.
#[derive(Debug, Clone, PartialEq, Serialize, sqlx::FromRow, utoipa::ToSchema)]
pub struct CycleTime {
    pub job_id: i64,
    pub finished_at: String,
    pub cycle_time_s: f64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cell::packml::{MachineStatus, PackMlState, Transition};

    /// Counters and transitions written are read back as they were.
    #[tokio::test]
    async fn counters_and_transitions_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let db = Db::open(&dir.path().join("celld.db")).await.unwrap();
        assert_eq!(counters(&db).await.unwrap(), Counters::default());
        let mut stored = Counters {
            processed: 3,
            good: 2,
            defective: 1,
            estops: 1,
            last_cycle_time_s: Some(2.25),
            total_cycle_time_s: 4.5,
            min_cycle_time_s: Some(2.0),
            max_cycle_time_s: Some(2.5),
            ..Counters::default()
        };
        stored.defective_by_reason.insert("contact".into(), 1);
        let update = MachineUpdate {
            transitions: vec![Transition {
                from: PackMlState::Idle,
                to: PackMlState::Starting,
                cause: "a job was queued".into(),
            }],
            machine: MachineStatus {
                state: PackMlState::Starting,
                state_number: 3,
                unit_mode: "Production",
                stop_reason: None,
                counters: stored.clone(),
            },
        };
        let mut tx = db.writer.begin().await.unwrap();
        record(&mut tx, &update).await.unwrap();
        tx.commit().await.unwrap();
        assert_eq!(counters(&db).await.unwrap(), stored);
        let read = transitions(&db, 10).await.unwrap();
        assert_eq!(read.len(), 1);
        assert_eq!(
            (read[0].from_state.as_str(), read[0].to_state.as_str()),
            ("Idle", "Starting")
        );
    }
}
