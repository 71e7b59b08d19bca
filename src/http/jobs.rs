//! `/api/jobs`: create (operator), list and read (viewer), cancel (operator), and each job's
//! stored steps as JSON or CSV.

use super::Context;
use super::auth::Auth;
use super::error::{ApiError, ApiResult, Json, Path, Query};
use super::stats::check_time_range;
use crate::cell::{CellCommand, ControllerSource, JobEnd, JobSpec, JobStatus};
use crate::policy;
use crate::sim::InitialConditions;
use crate::storage::jobs::{self, Job, JobFilter, NewJob};
use crate::storage::tokens::Role;
use crate::storage::{policies, steps};
use axum::Router;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use rand::Rng;
use serde::Deserialize;
use serde_json::{Value, json};
use std::time::Duration;

pub fn router() -> Router<Context> {
    Router::new()
        .route("/api/jobs", post(create).get(list))
        .route("/api/jobs/{id}", get(read))
        .route("/api/jobs/{id}/cancel", post(cancel))
        .route("/api/jobs/{id}/steps", get(read_steps))
}

/// Largest initial offset and orientation error a job may ask for (the workspace the twin's
/// protocol covers; Table 2's widest is 50 mm and 9 deg).
const MAX_INITIAL_POS_MM: f64 = 200.0;
const MAX_INITIAL_ORI_DEG: f64 = 20.0;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateJob {
    controller: String,
    seed: Option<u64>,
    initial: Option<InitialBody>,
    demonstration: Option<bool>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InitialBody {
    pos_mm: f64,
    ori_deg: f64,
}

/// Jobs waiting at most: each holds its controller (a policy's weights) in memory until it runs.
const MAX_QUEUED_JOBS: usize = 100;

async fn create(
    State(context): State<Context>,
    auth: Auth,
    Json(body): Json<CreateJob>,
) -> ApiResult<(StatusCode, Json<Job>)> {
    let caller = auth.require(Role::Operator)?;
    if !context.accepting_jobs() {
        return Err(ApiError::unavailable("the service is shutting down"));
    }
    if context.cell.status().estop_latched {
        return Err(ApiError::conflict(
            "the e-stop is latched: reset the cell (POST /api/cell/reset) first",
        ));
    }
    let queued = context.cell.status().queue.len();
    if queued >= MAX_QUEUED_JOBS {
        return Err(ApiError::conflict(format!(
            "{queued} jobs are waiting already (at most {MAX_QUEUED_JOBS}): wait or cancel some"
        )));
    }
    let (name, source, policy_id) = resolve_controller(&context, &body.controller).await?;
    let defaults = InitialConditions::from_cell(&context.cell_config);
    let initial = match body.initial {
        None => defaults,
        Some(InitialBody { pos_mm, ori_deg }) => {
            check_range("initial.pos_mm", pos_mm, MAX_INITIAL_POS_MM)?;
            check_range("initial.ori_deg", ori_deg, MAX_INITIAL_ORI_DEG)?;
            InitialConditions {
                offset_mm: pos_mm,
                orientation_deg: ori_deg,
            }
        }
    };
    let seed = body.seed.unwrap_or_else(|| rand::rng().random());
    let job = jobs::insert(
        &context.db,
        &NewJob {
            controller: name,
            policy_id,
            seed,
            initial_pos_mm: initial.offset_mm,
            initial_ori_deg: initial.orientation_deg,
            demonstration: body.demonstration.unwrap_or(false),
            created_by: caller.name.clone(),
        },
    )
    .await?;
    let sent = context.cell.send(CellCommand::Enqueue(JobSpec {
        id: job.id,
        controller: source,
        seed,
        initial,
        demonstration: job.demonstration,
    }));
    if let Err(stopped) = sent {
        // No thread will ever run it: close it now rather than leave it `queued`.
        let end = JobEnd::unstarted(JobStatus::Failed, "control_stopped");
        jobs::mark_ended(&context.db.writer, job.id, &end).await?;
        return Err(stopped.into());
    }
    Ok((StatusCode::CREATED, Json(job)))
}

fn check_range(field: &str, value: f64, max: f64) -> ApiResult<()> {
    if value.is_finite() && (0.0..=max).contains(&value) {
        Ok(())
    } else {
        Err(ApiError::unprocessable(format!(
            "{field} = {value} is outside 0..={max}"
        )))
    }
}

/// The controller a job names, as the name stored with the job, the source the control
/// thread builds it from, and the policy id when it is a registered policy.
async fn resolve_controller(
    context: &Context,
    requested: &str,
) -> ApiResult<(String, ControllerSource, Option<i64>)> {
    let name = if requested == "active" {
        match policies::active(&context.db).await? {
            Some((id, bytes)) => {
                return Ok((
                    format!("policy:{id}"),
                    ControllerSource::Policy { id, bytes },
                    Some(id),
                ));
            }
            None => context.settings.control.active_controller.clone(),
        }
    } else {
        requested.to_string()
    };
    if let Some(id) = name.strip_prefix("policy:") {
        let id: i64 = id.parse().map_err(|_| {
            ApiError::unprocessable(format!("controller `{name}`: `policy:` takes a policy id"))
        })?;
        let bytes = policies::file(&context.db, id).await?;
        let bytes = bytes.ok_or_else(|| ApiError::not_found(format!("no policy with id {id}")))?;
        return Ok((name, ControllerSource::Policy { id, bytes }, Some(id)));
    }
    policy::check_known(&name).map_err(|e| ApiError::unprocessable(e.to_string()))?;
    Ok((name.clone(), ControllerSource::Builtin(name), None))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListQuery {
    status: Option<String>,
    controller: Option<String>,
    policy_id: Option<i64>,
    since: Option<String>,
    until: Option<String>,
    limit: Option<i64>,
    offset: Option<i64>,
}

const MAX_PAGE: i64 = 1000;

async fn list(
    State(context): State<Context>,
    auth: Auth,
    Query(query): Query<ListQuery>,
) -> ApiResult<Json<Value>> {
    auth.require(Role::Viewer)?;
    let status = match query.status.as_deref() {
        None => None,
        Some(text) => Some(JobStatus::parse(text).ok_or_else(|| {
            let known: Vec<&str> = JobStatus::ALL.iter().map(|s| s.as_str()).collect();
            ApiError::bad_request(format!(
                "status `{text}` is not one of {}",
                known.join(", ")
            ))
        })?),
    };
    let limit = query.limit.unwrap_or(50);
    if !(1..=MAX_PAGE).contains(&limit) {
        return Err(ApiError::bad_request(format!(
            "limit = {limit} is outside 1..={MAX_PAGE}"
        )));
    }
    let offset = query.offset.unwrap_or(0);
    if offset < 0 {
        return Err(ApiError::bad_request(format!(
            "offset = {offset} is negative"
        )));
    }
    check_time_range(&query.since, &query.until)?;
    let filter = JobFilter {
        status,
        controller: query.controller,
        policy_id: query.policy_id,
        since: query.since,
        until: query.until,
        limit,
        offset,
    };
    let (items, total) = jobs::list(&context.db, &filter).await?;
    Ok(Json(json!({"items": items, "total": total})))
}

async fn find(context: &Context, id: i64) -> ApiResult<Job> {
    jobs::get(&context.db, id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("no job with id {id}")))
}

async fn read(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
) -> ApiResult<Json<Job>> {
    auth.require(Role::Viewer)?;
    Ok(Json(find(&context, id).await?))
}

async fn cancel(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
) -> ApiResult<Json<Job>> {
    auth.require(Role::Operator)?;
    let job = find(&context, id).await?;
    let found = context
        .cell
        .ask(|reply| CellCommand::Cancel { job_id: id, reply })
        .await?;
    if !found {
        return Err(ApiError::conflict(format!(
            "job {id} is {} and can no longer be cancelled",
            job.status
        )));
    }
    Ok(Json(wait_until_final(&context, id).await?))
}

/// The job once the storage writer has recorded its end (it does so within milliseconds of
/// the control thread's answer), or as it stands after two seconds.
pub async fn wait_until_final(context: &Context, id: i64) -> ApiResult<Job> {
    for _ in 0..200 {
        let job = find(context, id).await?;
        if JobStatus::parse(&job.status).is_some_and(|s| s.is_final()) {
            return Ok(job);
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    find(context, id).await
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepsQuery {
    format: Option<String>,
}

async fn read_steps(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
    Query(query): Query<StepsQuery>,
) -> ApiResult<Response> {
    auth.require(Role::Viewer)?;
    find(&context, id).await?;
    let rows = steps::list(&context.db, id).await?;
    match query.format.as_deref() {
        None | Some("json") => Ok(Json(json!({"items": rows})).into_response()),
        Some("csv") => Ok((
            [(header::CONTENT_TYPE, "text/csv; charset=utf-8")],
            steps::to_csv(&rows),
        )
            .into_response()),
        Some(other) => Err(ApiError::bad_request(format!(
            "format `{other}` is not json or csv"
        ))),
    }
}
