//! `/api/jobs`: create (operator), list and read (viewer), cancel (operator), and each job's
//! stored steps as JSON or CSV.

use super::Context;
use super::auth::{Auth, Operator};
use super::error::{ApiError, ApiResult, Items, Json, Path, Query};
use super::stats::check_time_range;
use crate::cell::JobStatus;
use crate::storage::jobs::{self, Job, JobFilter};
use crate::storage::steps::{self, StoredStep};
use crate::storage::tokens::Role;
use crate::workflows::{self, jobs::JobRequest};
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
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

#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateJob {
    /// `active` (the active policy, or the configured controller when none is active), a
    /// built-in controller, a bundled policy, or `policy:<id>`.
    #[schema(
        pattern = "^(active|expert|expert-state-only|expert-careful|expert-swift|visual-servo|spiral|da-dmp|hierarchical-reference|bc|td3|hierarchical-cells|hierarchical-swift-reference|hierarchical-swift-cells|policy:[0-9]{1,18})$"
    )]
    controller: String,
    /// The episode's seed, any u64 (default: a random one, stored with the job).
    #[schema(minimum = 0, maximum = 18_446_744_073_709_551_615_u64)]
    #[serde(default, deserialize_with = "crate::integer::optional_integer")]
    seed: Option<u64>,
    /// Initial offset and orientation error (default: the cell file's).
    initial: Option<InitialBody>,
    /// Keep the job's steps as a demonstration when it succeeds.
    demonstration: Option<bool>,
    /// Admin only: run a registered policy the evaluation gate refuses (never evaluated on
    /// this cell, below the threshold, or still being evaluated), for the reason given, which
    /// the audit log keeps. An operator sending it is refused (403).
    override_gate: Option<OverrideGate>,
}

#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct OverrideGate {
    /// Why this policy may drive the robot without passing the gate.
    #[schema(min_length = 1, max_length = 500, pattern = r"\S")]
    reason: String,
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

/// Queues a job on the cell (operator). A registered policy runs only if it is the active one,
/// a bundled one, or its evaluation on this cell passed the gate; else 409 says why, unless an
/// admin overrides the gate with a reason (`override_gate`).
#[utoipa::path(post, path = "/api/jobs", tag = "jobs", request_body = CreateJob,
    responses((status = 201, description = "Queued", body = Job)))]
async fn create(
    State(context): State<Context>,
    Operator(caller): Operator,
    Json(body): Json<CreateJob>,
) -> ApiResult<(StatusCode, Json<Job>)> {
    if body.override_gate.is_some() && caller.role < Role::Admin {
        return Err(ApiError::forbidden(format!(
            "override_gate needs the admin role; token `{}` is {}",
            caller.name,
            caller.role.as_str()
        )));
    }
    let request = JobRequest {
        controller: body.controller,
        seed: body.seed,
        initial: body.initial.map(|i| (i.pos_mm, i.ori_deg)),
        demonstration: body.demonstration.unwrap_or(false),
        override_gate: body.override_gate.map(|o| o.reason),
    };
    let job = workflows::jobs::create(&context, request, &caller.name).await?;
    Ok((StatusCode::CREATED, Json(job)))
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
pub struct ListQuery {
    /// Only jobs in this state.
    #[param(inline, value_type = Option<JobStatus>)]
    pub(crate) status: Option<String>,
    /// Only jobs of this controller (as stored: a name or `policy:<id>`).
    pub(crate) controller: Option<String>,
    /// Only jobs of this policy.
    pub(crate) policy_id: Option<i64>,
    /// Created at or after this UTC time (2026-11-22 or 2026-11-22T08:00:00Z).
    #[param(
        pattern = "^[0-9]{4}-[0-9]{2}-[0-9]{2}(T[0-9]{2}:[0-9]{2}(:[0-9]{2}(\\.[0-9]{1,3})?)?)?Z?$"
    )]
    pub(crate) since: Option<String>,
    /// Created before this UTC time.
    #[param(
        pattern = "^[0-9]{4}-[0-9]{2}-[0-9]{2}(T[0-9]{2}:[0-9]{2}(:[0-9]{2}(\\.[0-9]{1,3})?)?)?Z?$"
    )]
    pub(crate) until: Option<String>,
    /// Jobs per page (default 50).
    #[param(minimum = 1, maximum = 1000)]
    pub(crate) limit: Option<i64>,
    /// Jobs to skip.
    #[param(minimum = 0)]
    pub(crate) offset: Option<i64>,
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
    let filter = job_filter(query)?;
    let (items, total) = jobs::list(&context.db, &filter).await?;
    Ok(Json(JobPage { items, total }))
}

/// The filter a list query asks for, its values checked.
pub fn job_filter(query: ListQuery) -> ApiResult<JobFilter> {
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
    Ok(JobFilter {
        status,
        controller: query.controller,
        policy_id: query.policy_id,
        since: query.since,
        until: query.until,
        limit,
        offset,
    })
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
    Ok(Json(workflows::jobs::find(&context, id).await?))
}

/// Cancels a queued or running job (operator); answers once its end is stored.
#[utoipa::path(post, path = "/api/jobs/{id}/cancel", tag = "jobs", params(("id" = i64, Path)),
    responses((status = 200, description = "The job, cancelled", body = Job)))]
async fn cancel(
    State(context): State<Context>,
    _: Operator,
    Path(id): Path<i64>,
) -> ApiResult<Json<Job>> {
    Ok(Json(workflows::jobs::cancel(&context, id).await?))
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
    workflows::jobs::find(&context, id).await?;
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

    /// A stored step is described with the controller's proposal (six numbers or null) and
    /// the rules that changed it (names, always there).
    #[test]
    fn a_stored_step_is_described_with_its_proposal_and_rules() {
        let document: serde_json::Value =
            serde_json::from_str(crate::http::openapi_json()).unwrap();
        let step = &document["components"]["schemas"]["StoredStep"];
        let proposed = &step["properties"]["proposed"];
        assert_eq!(
            proposed["type"],
            serde_json::json!(["array", "null"]),
            "{proposed}"
        );
        assert_eq!(proposed["items"]["type"], "number", "{proposed}");
        assert_eq!(
            (&proposed["minItems"], &proposed["maxItems"]),
            (&6.into(), &6.into())
        );
        let rules = &step["properties"]["rules"];
        assert_eq!(rules["type"], "array", "{rules}");
        assert_eq!(rules["items"]["type"], "string", "{rules}");
        let required = step["required"].as_array().unwrap();
        assert!(required.contains(&"rules".into()), "{step}");
        assert!(!required.contains(&"proposed".into()), "{step}");
    }
}
