//! `/api/jobs`: create (operator), list and read (viewer), cancel (operator), and each job's
//! stored steps as JSON or CSV.

use super::Context;
use super::auth::Auth;
use super::error::{ApiError, ApiResult, Items, Json, Path, Query};
use super::stats::check_time_range;
use crate::cell::{CellCommand, ControllerSource, JobEnd, JobSpec, JobStatus};
use crate::policy;
use crate::sim::InitialConditions;
use crate::storage::jobs::{self, Job, JobFilter, NewJob};
use crate::storage::policies;
use crate::storage::steps::{self, StoredStep};
use crate::storage::tokens::Role;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use rand::Rng;
use serde::{Deserialize, Serialize};
use std::time::Duration;
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<Context> {
    OpenApiRouter::new()
        .routes(routes!(create, list))
        .routes(routes!(read))
        .routes(routes!(cancel))
        .routes(routes!(read_steps))
}

/// Largest initial offset and orientation error a job may ask for (the workspace the twin's
/// protocol covers; Table 2's widest is 50 mm and 9 deg).
const MAX_INITIAL_POS_MM: f64 = 200.0;
const MAX_INITIAL_ORI_DEG: f64 = 20.0;

#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateJob {
    /// `active` (the active policy, or the configured controller when none is active), a
    /// built-in controller, a bundled policy, or `policy:<id>`.
    #[schema(
        pattern = "^(active|expert|expert-state-only|expert-careful|visual-servo|spiral|da-dmp|hierarchical|bc|td3|policy:[0-9]{1,18})$"
    )]
    controller: String,
    /// The episode's seed (default: a random one, stored with the job).
    #[serde(default, deserialize_with = "crate::integer::optional_integer")]
    seed: Option<u64>,
    /// Initial offset and orientation error (default: the cell file's).
    initial: Option<InitialBody>,
    /// Keep the job's steps as a demonstration when it succeeds.
    demonstration: Option<bool>,
}

#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct InitialBody {
    /// Offset from the mouth pose, mm.
    #[schema(minimum = 0.0, maximum = 200.0)]
    pos_mm: f64,
    /// Orientation error, deg.
    #[schema(minimum = 0.0, maximum = 20.0)]
    ori_deg: f64,
}

/// Jobs waiting at most: each holds its controller (a policy's weights) in memory until it runs.
const MAX_QUEUED_JOBS: usize = 100;

/// Queues a job on the cell (operator).
#[utoipa::path(post, path = "/api/jobs", tag = "jobs", request_body = CreateJob,
    responses((status = 201, description = "Queued", body = Job)))]
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

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
pub struct ListQuery {
    /// Only jobs in this state.
    #[param(inline, value_type = Option<JobStatus>)]
    status: Option<String>,
    /// Only jobs of this controller (as stored: a name or `policy:<id>`).
    controller: Option<String>,
    /// Only jobs of this policy.
    policy_id: Option<i64>,
    /// Created at or after this UTC time (2026-11-22 or 2026-11-22T08:00:00Z).
    #[param(
        pattern = "^[0-9]{4}-[0-9]{2}-[0-9]{2}(T[0-9]{2}:[0-9]{2}(:[0-9]{2}(\\.[0-9]{1,3})?)?)?Z?$"
    )]
    since: Option<String>,
    /// Created before this UTC time.
    #[param(
        pattern = "^[0-9]{4}-[0-9]{2}-[0-9]{2}(T[0-9]{2}:[0-9]{2}(:[0-9]{2}(\\.[0-9]{1,3})?)?)?Z?$"
    )]
    until: Option<String>,
    /// Jobs per page (default 50).
    #[param(minimum = 1, maximum = 1000)]
    limit: Option<i64>,
    /// Jobs to skip.
    #[param(minimum = 0)]
    offset: Option<i64>,
}

const MAX_PAGE: i64 = 1000;

/// A page of jobs and how many match.
#[derive(Serialize, ToSchema)]
pub struct JobPage {
    items: Vec<Job>,
    /// Jobs that match the filter, on every page.
    total: i64,
}

/// Jobs, newest first, filtered (viewer).
#[utoipa::path(get, path = "/api/jobs", tag = "jobs", params(ListQuery),
    responses((status = 200, description = "A page of jobs", body = JobPage)))]
async fn list(
    State(context): State<Context>,
    auth: Auth,
    Query(query): Query<ListQuery>,
) -> ApiResult<Json<JobPage>> {
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
    Ok(Json(JobPage { items, total }))
}

async fn find(context: &Context, id: i64) -> ApiResult<Job> {
    jobs::get(&context.db, id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("no job with id {id}")))
}

/// One job (viewer).
#[utoipa::path(get, path = "/api/jobs/{id}", tag = "jobs", params(("id" = i64, Path)),
    responses((status = 200, description = "The job", body = Job)))]
async fn read(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
) -> ApiResult<Json<Job>> {
    auth.require(Role::Viewer)?;
    Ok(Json(find(&context, id).await?))
}

/// Cancels a queued or running job (operator); answers once its end is stored.
#[utoipa::path(post, path = "/api/jobs/{id}/cancel", tag = "jobs", params(("id" = i64, Path)),
    responses((status = 200, description = "The job, cancelled", body = Job)))]
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

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
pub struct StepsQuery {
    /// `json` (default) or `csv`.
    #[param(inline, value_type = Option<StepsFormat>)]
    format: Option<String>,
}

/// The answers `/api/jobs/{id}/steps` can give.
#[derive(ToSchema)]
#[allow(dead_code)] // Described, not built: the query carries the name as text.
#[schema(rename_all = "snake_case")]
enum StepsFormat {
    Json,
    Csv,
}

/// A job's recorded steps, in order (viewer), as JSON or CSV.
#[utoipa::path(get, path = "/api/jobs/{id}/steps", tag = "jobs",
    params(("id" = i64, Path), StepsQuery),
    responses((status = 200, description = "The steps",
        content((Items<StoredStep> = "application/json"), (String = "text/csv")))))]
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
        None | Some("json") => Ok(Json(Items { items: rows }).into_response()),
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

#[cfg(test)]
mod tests {
    use crate::policy::{BUILTIN_CONTROLLERS, LEARNED_CONTROLLERS};
    use std::collections::BTreeSet;

    /// The pattern the API description gives `controller` names every controller the service
    /// knows, and nothing else, besides `active` and `policy:<id>`.
    #[test]
    fn the_described_controller_pattern_names_every_controller_and_nothing_else() {
        let document: serde_json::Value =
            serde_json::from_str(crate::http::openapi_json()).unwrap();
        let pattern =
            document["components"]["schemas"]["CreateJob"]["properties"]["controller"]["pattern"]
                .as_str()
                .unwrap();
        let named: BTreeSet<&str> = pattern
            .trim_start_matches("^(")
            .trim_end_matches(")$")
            .split('|')
            .filter(|name| *name != "active" && !name.starts_with("policy:"))
            .collect();
        let known: BTreeSet<&str> = BUILTIN_CONTROLLERS
            .iter()
            .chain(&LEARNED_CONTROLLERS)
            .copied()
            .collect();
        assert_eq!(named, known);
    }
}
