//! What every cell can read of the fleet: the cells, their jobs, the figures over them, and
//! the registry's policies as each cell holds them.

use super::{Fleet, FleetError, ISO};
use crate::storage::jobs::{GroupBy, Job, JobFilter, JobRow, JobStats, StatsRow, summarise};
use serde::Serialize;
use serde_json::Value;

/// A cell as its last heartbeat told the fleet.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct FleetCell {
    pub cell_id: String,
    /// UTC, ISO 8601.
    pub last_heard_at: String,
    /// Seconds since then, by the fleet database's clock.
    pub heard_s_ago: f64,
    /// The PackML state.
    pub state: String,
    pub stop_reason: Option<String>,
    pub estop_latched: bool,
    /// `{id, name, sha256}` of its active policy.
    #[schema(value_type = Option<Object>)]
    pub active_policy: Option<Value>,
    #[schema(value_type = Object)]
    pub counters: Value,
    pub config_hash: String,
    /// Rows it has not replicated yet.
    pub backlog: i64,
    /// The wait of the oldest row in its last batch, s.
    pub lag_s: Option<f64>,
    /// Whether this is the cell answering.
    pub this_cell: bool,
}

pub async fn cells(fleet: &Fleet) -> Result<Vec<FleetCell>, FleetError> {
    type Row = (
        String,
        String,
        f64,
        String,
        Option<String>,
        bool,
        Option<String>,
        String,
        String,
        i64,
        Option<f64>,
    );
    let rows: Vec<Row> = sqlx::query_as(&format!(
        "SELECT cell_id, to_char(last_heard_at AT TIME ZONE 'UTC', {ISO}),
                EXTRACT(EPOCH FROM now() - last_heard_at)::float8,
                state, stop_reason, estop_latched, active_policy, counters, config_hash,
                backlog, lag_s
         FROM fleet_cells ORDER BY cell_id"
    ))
    .fetch_all(&fleet.pool)
    .await?;
    let json = |text: &str| serde_json::from_str(text).unwrap_or(Value::Null);
    Ok(rows
        .into_iter()
        .map(|row| FleetCell {
            this_cell: row.0 == fleet.cell_id,
            cell_id: row.0,
            last_heard_at: row.1,
            heard_s_ago: row.2,
            state: row.3,
            stop_reason: row.4,
            estop_latched: row.5,
            active_policy: row.6.as_deref().map(json),
            counters: json(&row.7),
            config_hash: row.8,
            backlog: row.9,
            lag_s: row.10,
        })
        .collect())
}

/// A job of some cell's.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct FleetJob {
    pub cell_id: String,
    #[serde(flatten)]
    pub job: Job,
}

/// Which jobs of the fleet: the local filter, plus one cell.
#[derive(Debug, Clone)]
pub struct FleetJobFilter {
    pub cell: Option<String>,
    pub jobs: JobFilter,
}

const CONDITION: &str = "($1::text IS NULL OR cell_id = $1) AND ($2::text IS NULL OR status = $2)
    AND ($3::text IS NULL OR controller = $3) AND ($4::bigint IS NULL OR policy_id = $4)
    AND ($5::text IS NULL OR created_at >= $5) AND ($6::text IS NULL OR created_at < $6)";

/// Newest first (by creation time), and the total that matches.
pub async fn jobs(
    fleet: &Fleet,
    filter: &FleetJobFilter,
) -> Result<(Vec<FleetJob>, i64), FleetError> {
    fn bind<'q>(
        sql: &'q str,
        filter: &FleetJobFilter,
    ) -> sqlx::query::Query<'q, sqlx::Postgres, sqlx::postgres::PgArguments> {
        let jobs = &filter.jobs;
        sqlx::query(sql)
            .bind(filter.cell.clone())
            .bind(jobs.status.map(|s| s.as_str()))
            .bind(jobs.controller.clone())
            .bind(jobs.policy_id)
            .bind(jobs.since.clone())
            .bind(jobs.until.clone())
    }
    let select = format!(
        "SELECT cell_id, id, status, controller, policy_id, seed, initial_pos_mm,
             initial_ori_deg, demonstration <> 0 AS demonstration, created_by, created_at,
             started_at, finished_at,
             CASE WHEN status = 'running'
                  THEN (SELECT count(*) FROM steps s
                        WHERE s.cell_id = jobs.cell_id AND s.job_id = jobs.id)
                  ELSE steps END AS steps,
             failure_reason, reward, lateral_mm, depth_error_mm, tilt_deg, hole_arc_mm
         FROM jobs WHERE {CONDITION}
         ORDER BY created_at DESC, cell_id, id DESC LIMIT $7 OFFSET $8"
    );
    let rows = bind(&select, filter)
        .bind(filter.jobs.limit)
        .bind(filter.jobs.offset)
        .fetch_all(&fleet.pool)
        .await?;
    let mut jobs = Vec::with_capacity(rows.len());
    for row in &rows {
        use sqlx::{FromRow, Row};
        let cell_id: String = row.try_get("cell_id")?;
        jobs.push(FleetJob {
            cell_id,
            job: Job::from(JobRow::from_row(row)?),
        });
    }
    let total: i64 = sqlx::Row::try_get(
        &bind(
            &format!("SELECT count(*) FROM jobs WHERE {CONDITION}"),
            filter,
        )
        .fetch_one(&fleet.pool)
        .await?,
        0,
    )?;
    Ok((jobs, total))
}

/// Jobs created in `[since, until)` on one cell or all, overall and by group.
pub async fn stats(
    fleet: &Fleet,
    cell: Option<&str>,
    since: Option<&str>,
    until: Option<&str>,
    by: GroupBy,
) -> Result<(JobStats, Vec<JobStats>), FleetError> {
    let rows: Vec<StatsRow> = sqlx::query_as(
        "SELECT status, steps, failure_reason, controller, substr(created_at, 1, 10) AS day
         FROM jobs WHERE ($1::text IS NULL OR cell_id = $1)
             AND ($2::text IS NULL OR created_at >= $2) AND ($3::text IS NULL OR created_at < $3)
         ORDER BY created_at, cell_id, id",
    )
    .bind(cell)
    .bind(since)
    .bind(until)
    .fetch_all(&fleet.pool)
    .await?;
    Ok(summarise(rows, by))
}

/// A policy of the registry and how each cell holds it.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct FleetPolicy {
    pub sha256: String,
    pub name: String,
    pub uploaded_by: Option<String>,
    pub created_at: String,
    /// The cell it was first uploaded to.
    pub first_cell: String,
    pub cells: Vec<PolicyOnCell>,
}

/// A registry policy on one cell: its id there, its status, its latest evaluation there.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct PolicyOnCell {
    pub cell_id: String,
    pub policy_id: i64,
    pub status: String,
    pub evaluation: Option<CellEvaluation>,
}

#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct CellEvaluation {
    pub status: String,
    pub success_rate: Option<f64>,
    pub cell_hash: String,
}

pub async fn policies(fleet: &Fleet) -> Result<Vec<FleetPolicy>, FleetError> {
    let files: Vec<(String, String, Option<String>, String, String)> = sqlx::query_as(
        "SELECT sha256, name, uploaded_by, created_at, first_cell FROM fleet_policy_files
         ORDER BY created_at DESC, sha256",
    )
    .fetch_all(&fleet.pool)
    .await?;
    type Held = (
        String,
        String,
        i64,
        String,
        Option<String>,
        Option<f64>,
        Option<String>,
    );
    let held: Vec<Held> = sqlx::query_as(
        "SELECT p.sha256, p.cell_id, p.id, p.status, e.status, e.success_rate, e.cell_hash
         FROM policies p
         LEFT JOIN LATERAL (SELECT status, success_rate, cell_hash FROM policy_evaluations e
                            WHERE e.cell_id = p.cell_id AND e.policy_id = p.id
                            ORDER BY e.id DESC LIMIT 1) e ON true
         ORDER BY p.cell_id",
    )
    .fetch_all(&fleet.pool)
    .await?;
    Ok(files
        .into_iter()
        .map(|(sha256, name, uploaded_by, created_at, first_cell)| {
            let cells = held
                .iter()
                .filter(|h| h.0 == sha256)
                .map(|h| PolicyOnCell {
                    cell_id: h.1.clone(),
                    policy_id: h.2,
                    status: h.3.clone(),
                    evaluation: h.4.clone().map(|status| CellEvaluation {
                        status,
                        success_rate: h.5,
                        cell_hash: h.6.clone().unwrap_or_default(),
                    }),
                })
                .collect();
            FleetPolicy {
                sha256,
                name,
                uploaded_by,
                created_at,
                first_cell,
                cells,
            }
        })
        .collect())
}
