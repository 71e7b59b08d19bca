//! `/api/fleet/…`: the fleet as every cell in it sees it (viewer), and activating a policy
//! on every cell where it passed (admin). A cell in no fleet answers 404 `no_fleet`; one whose
//! fleet database is unreachable answers 503 `fleet_unavailable` and runs on.

use super::Context;
use super::auth::{Admin, Auth};
use super::error::{ApiResult, Items, Json, Path, Query};
use super::jobs::{ListQuery, job_filter};
use super::stats::{Stats, check_time_range, group_by};
use crate::fleet::reads::{self, FleetCell, FleetJob, FleetJobFilter, FleetPolicy};
use crate::fleet::registry::{self, Activation};
use crate::storage::tokens::Role;
use crate::workflows::fleet::{check_cell, link, unavailable};
use crate::workflows::{self, Error};
use axum::extract::State;
use axum::http::StatusCode;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<Context> {
    OpenApiRouter::new()
        .routes(routes!(cells))
        .routes(routes!(jobs))
        .routes(routes!(stats))
        .routes(routes!(policies))
        .routes(routes!(activate))
        .routes(routes!(activation))
}

/// Every cell of the fleet as its last heartbeat told it (viewer).
#[utoipa::path(get, path = "/api/fleet/cells", tag = "fleet",
    responses(
        (status = 200, description = "The cells", body = Items<FleetCell>),
        (status = 404, description = "This cell is in no fleet (`no_fleet`)",
            body = crate::http::document::ErrorBody),
        (status = 503, description = "The fleet's database is unreachable (`fleet_unavailable`)",
            body = crate::http::document::ErrorBody),
    ))]
async fn cells(State(context): State<Context>, auth: Auth) -> ApiResult<Json<Items<FleetCell>>> {
    auth.require(Role::Viewer)?;
    let link = link(&context)?;
    let items = reads::cells(&link.fleet).await.map_err(unavailable)?;
    Ok(Json(Items { items }))
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
pub struct FleetJobsQuery {
    /// Only this cell's jobs.
    #[param(pattern = "^[A-Za-z0-9._-]{1,64}$")]
    cell: Option<String>,
    /// Only jobs in this state.
    #[param(inline, value_type = Option<crate::cell::JobStatus>)]
    status: Option<String>,
    /// Only jobs of this controller.
    controller: Option<String>,
    /// Only jobs of this policy (its id on its cell).
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

/// A page of the fleet's jobs and how many match.
#[derive(Serialize, ToSchema)]
pub struct FleetJobPage {
    items: Vec<FleetJob>,
    total: i64,
}

/// The fleet's jobs, newest first, filtered as `/api/jobs` is, and by cell (viewer).
#[utoipa::path(get, path = "/api/fleet/jobs", tag = "fleet", params(FleetJobsQuery),
    responses(
        (status = 200, description = "A page of jobs", body = FleetJobPage),
        (status = 404, description = "This cell is in no fleet (`no_fleet`)",
            body = crate::http::document::ErrorBody),
        (status = 503, description = "The fleet's database is unreachable (`fleet_unavailable`)",
            body = crate::http::document::ErrorBody),
    ))]
async fn jobs(
    State(context): State<Context>,
    auth: Auth,
    Query(query): Query<FleetJobsQuery>,
) -> ApiResult<Json<FleetJobPage>> {
    auth.require(Role::Viewer)?;
    check_cell(query.cell.as_deref())?;
    let jobs = job_filter(ListQuery {
        status: query.status,
        // As replication stores it: PostgreSQL's text holds no NUL.
        controller: query.controller.map(|c| c.replace('\0', "\u{FFFD}")),
        policy_id: query.policy_id,
        since: query.since,
        until: query.until,
        limit: query.limit,
        offset: query.offset,
    })?;
    let link = link(&context)?;
    let filter = FleetJobFilter {
        cell: query.cell,
        jobs,
    };
    let (items, total) = reads::jobs(&link.fleet, &filter)
        .await
        .map_err(unavailable)?;
    Ok(Json(FleetJobPage { items, total }))
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
pub struct FleetStatsQuery {
    /// Only this cell's jobs.
    #[param(pattern = "^[A-Za-z0-9._-]{1,64}$")]
    cell: Option<String>,
    /// Jobs created at or after this UTC time (2026-11-22 or 2026-11-22T08:00:00Z).
    #[param(
        pattern = "^[0-9]{4}-[0-9]{2}-[0-9]{2}(T[0-9]{2}:[0-9]{2}(:[0-9]{2}(\\.[0-9]{1,3})?)?)?Z?$"
    )]
    since: Option<String>,
    /// Jobs created before this UTC time.
    #[param(
        pattern = "^[0-9]{4}-[0-9]{2}-[0-9]{2}(T[0-9]{2}:[0-9]{2}(:[0-9]{2}(\\.[0-9]{1,3})?)?)?Z?$"
    )]
    until: Option<String>,
    /// `day` (default) or `controller`.
    #[param(inline, value_type = Option<super::stats::StatsGroup>)]
    by: Option<String>,
}

/// `/api/stats` over the fleet's jobs, or one cell's (viewer).
#[utoipa::path(get, path = "/api/fleet/stats", tag = "fleet", params(FleetStatsQuery),
    responses(
        (status = 200, description = "The figures", body = Stats),
        (status = 404, description = "This cell is in no fleet (`no_fleet`)",
            body = crate::http::document::ErrorBody),
        (status = 503, description = "The fleet's database is unreachable (`fleet_unavailable`)",
            body = crate::http::document::ErrorBody),
    ))]
async fn stats(
    State(context): State<Context>,
    auth: Auth,
    Query(query): Query<FleetStatsQuery>,
) -> ApiResult<Json<Stats>> {
    auth.require(Role::Viewer)?;
    let by = group_by(query.by.as_deref())?;
    check_time_range(&query.since, &query.until)?;
    check_cell(query.cell.as_deref())?;
    let link = link(&context)?;
    let (total, groups) = reads::stats(
        &link.fleet,
        query.cell.as_deref(),
        query.since.as_deref(),
        query.until.as_deref(),
        by,
    )
    .await
    .map_err(unavailable)?;
    Ok(Json(Stats { total, groups }))
}

/// The fleet's registry: each policy, and how each cell holds it (viewer).
#[utoipa::path(get, path = "/api/fleet/policies", tag = "fleet",
    responses(
        (status = 200, description = "The registry", body = Items<FleetPolicy>),
        (status = 404, description = "This cell is in no fleet (`no_fleet`)",
            body = crate::http::document::ErrorBody),
        (status = 503, description = "The fleet's database is unreachable (`fleet_unavailable`)",
            body = crate::http::document::ErrorBody),
    ))]
async fn policies(
    State(context): State<Context>,
    auth: Auth,
) -> ApiResult<Json<Items<FleetPolicy>>> {
    auth.require(Role::Viewer)?;
    let link = link(&context)?;
    let items = reads::policies(&link.fleet).await.map_err(unavailable)?;
    Ok(Json(Items { items }))
}

/// Asks every cell to activate the registry's policy `sha256` where its own evaluation
/// passed the gate (admin); each cell answers in a second or two, or once an evaluation
/// it is running ends (`GET /api/fleet/activations/{id}`).
#[utoipa::path(post, path = "/api/fleet/policies/{sha256}/activate", tag = "fleet",
    params(("sha256" = String, Path, description = "The policy file's sha256, hex")),
    responses(
        (status = 202, description = "The request, answered by each cell", body = Activation),
        (status = 404, description = "No such policy in the registry, or no fleet",
            body = crate::http::document::ErrorBody),
        (status = 503, description = "The fleet's database is unreachable (`fleet_unavailable`)",
            body = crate::http::document::ErrorBody),
    ))]
async fn activate(
    State(context): State<Context>,
    Admin(caller): Admin,
    Path(sha256): Path<String>,
) -> ApiResult<(StatusCode, Json<Activation>)> {
    let request = workflows::fleet::request_activation(&context, &sha256, &caller.name).await?;
    Ok((StatusCode::ACCEPTED, Json(request)))
}

/// An activation request and the cells' answers so far (viewer).
#[utoipa::path(get, path = "/api/fleet/activations/{id}", tag = "fleet",
    params(("id" = i64, Path)),
    responses(
        (status = 200, description = "The request and its answers", body = Activation),
        (status = 404, description = "No such request, or no fleet",
            body = crate::http::document::ErrorBody),
        (status = 503, description = "The fleet's database is unreachable (`fleet_unavailable`)",
            body = crate::http::document::ErrorBody),
    ))]
async fn activation(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
) -> ApiResult<Json<Activation>> {
    auth.require(Role::Viewer)?;
    let link = link(&context)?;
    registry::activation(&link.fleet, id)
        .await
        .map_err(unavailable)?
        .map(Json)
        .ok_or_else(|| Error::not_found(format!("no fleet activation request {id}")).into())
}
