//! Jobs: created queued, started, ended; listed with filters; summarised for `/api/stats`.

use super::{Db, DbError, NOW};
use crate::cell::{JobEnd, JobStatus};
use serde::Serialize;
use std::collections::BTreeMap;

/// A new job as the HTTP layer asks for it.
#[derive(Debug, Clone)]
pub struct NewJob {
    pub controller: String,
    pub policy_id: Option<i64>,
    pub seed: u64,
    pub initial_pos_mm: f64,
    pub initial_ori_deg: f64,
    pub demonstration: bool,
    pub created_by: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct Initial {
    pub pos_mm: f64,
    pub ori_deg: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct FinalErrors {
    pub lateral_mm: f64,
    pub depth_error_mm: f64,
    pub tilt_deg: f64,
    pub hole_arc_mm: f64,
}

/// A job as stored and served.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct Job {
    pub id: i64,
    pub status: String,
    pub controller: String,
    pub policy_id: Option<i64>,
    pub seed: u64,
    pub initial: Initial,
    pub demonstration: bool,
    pub created_by: Option<String>,
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    pub steps: i64,
    pub failure_reason: Option<String>,
    pub reward: Option<f64>,
    pub final_errors: Option<FinalErrors>,
}

/// A row of `jobs` as stored (on the cell, and in the fleet's copy).
#[derive(sqlx::FromRow)]
pub(crate) struct JobRow {
    id: i64,
    status: String,
    controller: String,
    policy_id: Option<i64>,
    seed: i64,
    initial_pos_mm: f64,
    initial_ori_deg: f64,
    demonstration: bool,
    created_by: Option<String>,
    created_at: String,
    started_at: Option<String>,
    finished_at: Option<String>,
    steps: i64,
    failure_reason: Option<String>,
    reward: Option<f64>,
    lateral_mm: Option<f64>,
    depth_error_mm: Option<f64>,
    tilt_deg: Option<f64>,
    hole_arc_mm: Option<f64>,
}

impl From<JobRow> for Job {
    fn from(row: JobRow) -> Self {
        // The final errors are written together: one there means all are.
        let final_errors = match (
            row.lateral_mm,
            row.depth_error_mm,
            row.tilt_deg,
            row.hole_arc_mm,
        ) {
            (Some(lateral_mm), Some(depth_error_mm), Some(tilt_deg), Some(hole_arc_mm)) => {
                Some(FinalErrors {
                    lateral_mm,
                    depth_error_mm,
                    tilt_deg,
                    hole_arc_mm,
                })
            }
            _ => None,
        };
        Job {
            id: row.id,
            status: row.status,
            controller: row.controller,
            policy_id: row.policy_id,
            // Stored as the same 64 bits in SQLite's signed integer.
            seed: row.seed as u64,
            initial: Initial {
                pos_mm: row.initial_pos_mm,
                ori_deg: row.initial_ori_deg,
            },
            demonstration: row.demonstration,
            created_by: row.created_by,
            created_at: row.created_at,
            started_at: row.started_at,
            finished_at: row.finished_at,
            steps: row.steps,
            failure_reason: row.failure_reason,
            reward: row.reward,
            final_errors,
        }
    }
}

pub async fn insert(db: &Db, job: &NewJob) -> Result<Job, DbError> {
    let id = sqlx::query_scalar::<_, i64>(
        "INSERT INTO jobs (status, controller, policy_id, seed, initial_pos_mm, initial_ori_deg,
                           demonstration, created_by)
         VALUES ('queued', ?, ?, ?, ?, ?, ?, ?) RETURNING id",
    )
    .bind(&job.controller)
    .bind(job.policy_id)
    .bind(job.seed as i64)
    .bind(job.initial_pos_mm)
    .bind(job.initial_ori_deg)
    .bind(job.demonstration)
    .bind(&job.created_by)
    .fetch_all(&db.writer)
    .await;
    let id = db.track(id.and_then(super::only_row))?;
    get_from(&db.writer, id).await?.ok_or(DbError::RowNotFound)
}

pub async fn get(db: &Db, id: i64) -> Result<Option<Job>, DbError> {
    get_from(&db.reader, id).await
}

/// A job's columns; a running job's `steps` counts the steps stored so far (its row gets the
/// total when it ends).
const JOB_COLUMNS: &str = "id, status, controller, policy_id, seed, initial_pos_mm,
    initial_ori_deg, demonstration, created_by, created_at, started_at, finished_at,
    CASE WHEN status = 'running'
         THEN (SELECT COUNT(*) FROM steps WHERE steps.job_id = jobs.id)
         ELSE steps END AS steps,
    failure_reason, reward, lateral_mm, depth_error_mm, tilt_deg, hole_arc_mm";

async fn get_from(pool: &sqlx::SqlitePool, id: i64) -> Result<Option<Job>, DbError> {
    let row: Option<JobRow> =
        sqlx::query_as(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?"))
            .bind(id)
            .fetch_optional(pool)
            .await?;
    Ok(row.map(Job::from))
}

/// Filters of `GET /api/jobs`.
#[derive(Debug, Clone, Default)]
pub struct JobFilter {
    pub status: Option<JobStatus>,
    pub controller: Option<String>,
    pub policy_id: Option<i64>,
    /// Created at or after (ISO 8601 text, compared as text like the stored times).
    pub since: Option<String>,
    /// Created before.
    pub until: Option<String>,
    pub limit: i64,
    pub offset: i64,
}

/// Newest first, and the total that matches the filter.
pub async fn list(db: &Db, filter: &JobFilter) -> Result<(Vec<Job>, i64), DbError> {
    let condition = "(?1 IS NULL OR status = ?1) AND (?2 IS NULL OR controller = ?2)
        AND (?3 IS NULL OR policy_id = ?3) AND (?4 IS NULL OR created_at >= ?4)
        AND (?5 IS NULL OR created_at < ?5)";
    let status = filter.status.map(|s| s.as_str());
    let rows: Vec<JobRow> = sqlx::query_as(&format!(
        "SELECT {JOB_COLUMNS} FROM jobs WHERE {condition} ORDER BY id DESC LIMIT ?6 OFFSET ?7"
    ))
    .bind(status)
    .bind(&filter.controller)
    .bind(filter.policy_id)
    .bind(&filter.since)
    .bind(&filter.until)
    .bind(filter.limit)
    .bind(filter.offset)
    .fetch_all(&db.reader)
    .await?;
    let total: i64 = sqlx::query_scalar(&format!("SELECT COUNT(*) FROM jobs WHERE {condition}"))
        .bind(status)
        .bind(&filter.controller)
        .bind(filter.policy_id)
        .bind(&filter.since)
        .bind(&filter.until)
        .fetch_one(&db.reader)
        .await?;
    Ok((rows.into_iter().map(Job::from).collect(), total))
}

/// Marks a queued job running (the writer's side of `JobStarted`).
pub async fn mark_started<'e>(
    executor: impl sqlx::SqliteExecutor<'e>,
    id: i64,
) -> Result<(), DbError> {
    sqlx::query(&format!(
        "UPDATE jobs SET status = 'running', started_at = {NOW} WHERE id = ? AND status = 'queued'"
    ))
    .bind(id)
    .execute(executor)
    .await?;
    Ok(())
}

/// Writes a job's end (the writer's side of `JobEnded`).
pub async fn mark_ended<'e>(
    executor: impl sqlx::SqliteExecutor<'e>,
    id: i64,
    end: &JobEnd,
) -> Result<(), DbError> {
    let errors = end.final_errors;
    sqlx::query(&format!(
        "UPDATE jobs SET status = ?, failure_reason = ?, steps = ?, reward = ?,
                lateral_mm = ?, depth_error_mm = ?, tilt_deg = ?, hole_arc_mm = ?,
                finished_at = {NOW}
         WHERE id = ?"
    ))
    .bind(end.status.as_str())
    .bind(&end.failure_reason)
    .bind(i64::from(end.steps))
    .bind((end.steps > 0).then_some(end.reward))
    .bind(errors.map(|e| e.lateral_mm))
    .bind(errors.map(|e| e.depth_error_mm))
    .bind(errors.map(|e| e.tilt_deg))
    .bind(errors.map(|e| e.hole_arc_mm))
    .bind(id)
    .execute(executor)
    .await?;
    Ok(())
}

/// At start: every job a previous run left `running` or `queued` becomes `interrupted`, with
/// its steps counted from what was committed. Returns how many.
pub async fn interrupt_leftovers(db: &Db) -> Result<u64, DbError> {
    let done = sqlx::query(&format!(
        "UPDATE jobs SET status = 'interrupted',
                failure_reason = CASE status WHEN 'running' THEN 'service_stopped'
                                             ELSE 'service_stopped_before_start' END,
                steps = (SELECT COUNT(*) FROM steps WHERE steps.job_id = jobs.id),
                reward = (SELECT SUM(reward_total) FROM steps WHERE steps.job_id = jobs.id),
                finished_at = {NOW}
         WHERE status IN ('running', 'queued')"
    ))
    .execute(&db.writer)
    .await?;
    Ok(done.rows_affected())
}

/// How `/api/stats` groups jobs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GroupBy {
    Day,
    Controller,
}

/// One group's figures.
#[derive(Debug, Clone, PartialEq, Default, Serialize, utoipa::ToSchema)]
pub struct JobStats {
    pub key: String,
    pub jobs: u64,
    pub finished: u64,
    pub succeeded: u64,
    /// Succeeded over finished (null before any job finished).
    pub success_rate: Option<f64>,
    /// Average steps of the succeeded jobs (null when none succeeded).
    pub avg_steps: Option<f64>,
    pub failure_reasons: BTreeMap<String, u64>,
}

impl JobStats {
    fn add(&mut self, status: &str, steps: i64, reason: Option<String>) {
        self.jobs += 1;
        let Some(status) = JobStatus::parse(status).filter(JobStatus::is_final) else {
            return;
        };
        self.finished += 1;
        if status == JobStatus::Succeeded {
            let total = self.avg_steps.unwrap_or(0.0) * self.succeeded as f64 + steps as f64;
            self.succeeded += 1;
            self.avg_steps = Some(total / self.succeeded as f64);
        } else {
            let reason = reason.unwrap_or_else(|| status.as_str().to_string());
            *self.failure_reasons.entry(reason).or_default() += 1;
        }
        self.success_rate = Some(self.succeeded as f64 / self.finished as f64);
    }
}

/// What [`stats`] reads of each job.
#[derive(sqlx::FromRow)]
pub(crate) struct StatsRow {
    status: String,
    steps: i64,
    failure_reason: Option<String>,
    controller: String,
    day: String,
}

/// Jobs created in `[since, until)` (ISO 8601 text, either end open), overall and by group.
pub async fn stats(
    db: &Db,
    since: Option<&str>,
    until: Option<&str>,
    by: GroupBy,
) -> Result<(JobStats, Vec<JobStats>), DbError> {
    let rows: Vec<StatsRow> = sqlx::query_as(
        "SELECT status, steps, failure_reason, controller, substr(created_at, 1, 10) AS day
         FROM jobs WHERE (?1 IS NULL OR created_at >= ?1) AND (?2 IS NULL OR created_at < ?2)
         ORDER BY id",
    )
    .bind(since)
    .bind(until)
    .fetch_all(&db.reader)
    .await?;
    Ok(summarise(rows, by))
}

/// The figures of `rows` (in creation order), overall and by group.
pub(crate) fn summarise(rows: Vec<StatsRow>, by: GroupBy) -> (JobStats, Vec<JobStats>) {
    let mut total = JobStats {
        key: "all".into(),
        ..JobStats::default()
    };
    let mut groups: BTreeMap<String, JobStats> = BTreeMap::new();
    for row in rows {
        let key = match by {
            GroupBy::Day => row.day,
            GroupBy::Controller => row.controller,
        };
        let (status, steps, reason) = (row.status, row.steps, row.failure_reason);
        total.add(&status, steps, reason.clone());
        groups
            .entry(key.clone())
            .or_insert_with(|| JobStats {
                key,
                ..JobStats::default()
            })
            .add(&status, steps, reason);
    }
    (total, groups.into_values().collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_count_success_over_finished_and_steps_over_successes() {
        let mut stats = JobStats::default();
        stats.add("succeeded", 40, None);
        stats.add("succeeded", 50, None);
        stats.add("failed", 12, Some("contact".into()));
        stats.add("cancelled", 3, Some("cancelled".into()));
        stats.add("queued", 0, None);
        assert_eq!(stats.jobs, 5);
        assert_eq!(stats.finished, 4);
        assert_eq!(stats.success_rate, Some(0.5));
        assert_eq!(stats.avg_steps, Some(45.0));
        assert_eq!(stats.failure_reasons["contact"], 1);
        assert_eq!(stats.failure_reasons["cancelled"], 1);
    }
}
