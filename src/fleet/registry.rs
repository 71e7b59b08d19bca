//! The fleet's shared parts: the policy registry (a file uploaded on one cell, pulled by every
//! other), activation requests and their per-cell results, each cell's heartbeat, and the
//! tokens every cell accepts.

use super::{Fleet, FleetError, ISO};
use crate::storage::{Db, DbError};
use serde::Serialize;

/// Puts the files of the cell's policies `ids` into the registry, those it lacks (inside the
/// replication batch that carries their rows).
pub async fn publish(
    cell: &mut sqlx::SqliteConnection,
    tx: &mut sqlx::PgConnection,
    cell_id: &str,
    ids: &[i64],
) -> Result<(), super::replicate::ReplicationError> {
    type PolicyRow = (String, String, Vec<u8>, Option<String>, String);
    for id in ids {
        let row: Option<PolicyRow> = sqlx::query_as(
            "SELECT sha256, name, file, uploaded_by, created_at FROM policies WHERE id = ?",
        )
        .bind(id)
        .fetch_optional(&mut *cell)
        .await?;
        let Some((sha256, name, file, uploaded_by, created_at)) = row else {
            continue;
        };
        let known: bool = sqlx::query_scalar(
            "SELECT EXISTS (SELECT 1 FROM fleet_policy_files WHERE sha256 = $1)",
        )
        .bind(&sha256)
        .fetch_one(&mut *tx)
        .await
        .map_err(FleetError::from)?;
        if known {
            continue;
        }
        sqlx::query(
            "INSERT INTO fleet_policy_files (sha256, name, file, uploaded_by, created_at, first_cell)
             VALUES ($1, $2, $3, $4, $5, $6) ON CONFLICT (sha256) DO NOTHING",
        )
        .bind(&sha256)
        .bind(&name)
        .bind(&file)
        .bind(&uploaded_by)
        .bind(&created_at)
        .bind(cell_id)
        .execute(&mut *tx)
        .await
        .map_err(FleetError::from)?;
    }
    Ok(())
}

/// A policy file in the registry.
#[derive(Debug, Clone, sqlx::FromRow)]
pub struct PolicyFile {
    pub sha256: String,
    pub name: String,
    pub file: Vec<u8>,
    pub uploaded_by: Option<String>,
    pub first_cell: String,
}

/// The registry's policies whose sha256 is not among `held` (the cell's own).
pub async fn missing(fleet: &Fleet, held: &[String]) -> Result<Vec<PolicyFile>, FleetError> {
    Ok(sqlx::query_as(
        "SELECT sha256, name, file, uploaded_by, first_cell FROM fleet_policy_files
         WHERE NOT (sha256 = ANY($1)) ORDER BY created_at",
    )
    .bind(held)
    .fetch_all(&fleet.pool)
    .await?)
}

/// The sha256 of every policy the cell holds.
pub async fn held(db: &Db) -> Result<Vec<String>, DbError> {
    sqlx::query_scalar("SELECT sha256 FROM policies")
        .fetch_all(&db.reader)
        .await
}

/// "Activate on every cell where it passed", and what each cell made of it.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct Activation {
    pub id: i64,
    pub sha256: String,
    pub requested_by: String,
    /// UTC, ISO 8601.
    pub requested_at: String,
    pub results: Vec<ActivationResult>,
}

/// One cell's answer to an [`Activation`].
#[derive(Debug, Clone, PartialEq, Serialize, sqlx::FromRow, utoipa::ToSchema)]
pub struct ActivationResult {
    pub cell_id: String,
    /// `activated`, `already_active`, `not_passed` (its evaluation on this cell did not pass
    /// the gate, or there is none) or `missing` (the cell does not hold the policy).
    pub outcome: String,
    pub detail: String,
    pub at: String,
}

/// Stores a request for every cell.
pub async fn request_activation(
    fleet: &Fleet,
    sha256: &str,
    by: &str,
) -> Result<Activation, FleetError> {
    let id: i64 = sqlx::query_scalar(
        "INSERT INTO fleet_activations (sha256, requested_by) VALUES ($1, $2) RETURNING id",
    )
    .bind(sha256)
    .bind(by)
    .fetch_one(&fleet.pool)
    .await?;
    activation(fleet, id)
        .await?
        .ok_or(FleetError::Refused(sqlx::Error::RowNotFound))
}

/// A request and the results so far.
pub async fn activation(fleet: &Fleet, id: i64) -> Result<Option<Activation>, FleetError> {
    let request: Option<(i64, String, String, String)> = sqlx::query_as(&format!(
        "SELECT id, sha256, requested_by, to_char(requested_at AT TIME ZONE 'UTC', {ISO})
         FROM fleet_activations WHERE id = $1"
    ))
    .bind(id)
    .fetch_optional(&fleet.pool)
    .await?;
    let Some((id, sha256, requested_by, requested_at)) = request else {
        return Ok(None);
    };
    let results = sqlx::query_as(&format!(
        "SELECT cell_id, outcome, detail, to_char(at AT TIME ZONE 'UTC', {ISO}) AS at
         FROM fleet_activation_results WHERE activation_id = $1 ORDER BY cell_id"
    ))
    .bind(id)
    .fetch_all(&fleet.pool)
    .await?;
    Ok(Some(Activation {
        id,
        sha256,
        requested_by,
        requested_at,
        results,
    }))
}

/// Requests this cell has not answered, oldest first.
pub async fn unanswered(fleet: &Fleet) -> Result<Vec<(i64, String, String)>, FleetError> {
    Ok(sqlx::query_as(
        "SELECT a.id, a.sha256, a.requested_by FROM fleet_activations a
         WHERE NOT EXISTS (SELECT 1 FROM fleet_activation_results r
                           WHERE r.activation_id = a.id AND r.cell_id = $1)
         ORDER BY a.id",
    )
    .bind(&fleet.cell_id)
    .fetch_all(&fleet.pool)
    .await?)
}

/// Stores this cell's answer to request `id` (once: a second answer changes nothing).
pub async fn answer(fleet: &Fleet, id: i64, outcome: &str, detail: &str) -> Result<(), FleetError> {
    sqlx::query(
        "INSERT INTO fleet_activation_results (activation_id, cell_id, outcome, detail)
         VALUES ($1, $2, $3, $4) ON CONFLICT DO NOTHING",
    )
    .bind(id)
    .bind(&fleet.cell_id)
    .bind(outcome)
    .bind(detail)
    .execute(&fleet.pool)
    .await?;
    Ok(())
}

/// What a cell tells the fleet about itself, about every second.
#[derive(Debug, Clone)]
pub struct Heartbeat {
    pub state: String,
    pub stop_reason: Option<String>,
    pub estop_latched: bool,
    /// JSON `{id, name, sha256}`.
    pub active_policy: Option<String>,
    /// JSON: the PackML counters.
    pub counters: String,
    pub config_hash: String,
    pub backlog: i64,
    pub lag_s: Option<f64>,
}

pub async fn beat(fleet: &Fleet, beat: &Heartbeat) -> Result<(), FleetError> {
    sqlx::query(
        "INSERT INTO fleet_cells (cell_id, last_heard_at, state, stop_reason, estop_latched,
             active_policy, counters, config_hash, backlog, lag_s)
         VALUES ($1, now(), $2, $3, $4, $5, $6, $7, $8, $9)
         ON CONFLICT (cell_id) DO UPDATE SET last_heard_at = now(), state = EXCLUDED.state,
             stop_reason = EXCLUDED.stop_reason, estop_latched = EXCLUDED.estop_latched,
             active_policy = EXCLUDED.active_policy, counters = EXCLUDED.counters,
             config_hash = EXCLUDED.config_hash, backlog = EXCLUDED.backlog,
             lag_s = EXCLUDED.lag_s",
    )
    .bind(&fleet.cell_id)
    .bind(&beat.state)
    .bind(&beat.stop_reason)
    .bind(beat.estop_latched)
    .bind(&beat.active_policy)
    .bind(&beat.counters)
    .bind(&beat.config_hash)
    .bind(beat.backlog)
    .bind(beat.lag_s)
    .execute(&fleet.pool)
    .await?;
    Ok(())
}

/// A token as the fleet holds it (replicated from the cell that made it).
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct FleetToken {
    pub token_hash: String,
    pub cell_id: String,
    pub name: String,
    pub role: String,
    pub expires_at: Option<String>,
    /// `expires_at` as milliseconds since the Unix epoch, for comparing with the clock.
    pub expires_unix_ms: Option<i64>,
    pub revoked_at: Option<String>,
}

/// Every cell's tokens.
pub async fn tokens(fleet: &Fleet) -> Result<Vec<FleetToken>, FleetError> {
    Ok(sqlx::query_as(
        "SELECT token_hash, cell_id, name, role, expires_at,
                    (EXTRACT(EPOCH FROM expires_at::timestamptz) * 1000)::bigint
                        AS expires_unix_ms,
                    revoked_at
             FROM tokens",
    )
    .fetch_all(&fleet.pool)
    .await?)
}
