//! `/api/cell`: the cell's state (viewer), e-stop and reset (operator).

use super::Context;
use super::auth::{Auth, Operator};
use super::error::{ApiResult, Json};
use crate::cell::CellStatus;
use crate::storage::tokens::Role;
use crate::workflows;
use axum::extract::State;
use serde::Serialize;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<Context> {
    OpenApiRouter::new()
        .routes(routes!(read))
        .routes(routes!(estop))
        .routes(routes!(reset))
}

/// The cell: its backend, e-stop latch, the driver's latch, running and queued jobs, last
/// estimated pose. `accepting_jobs` is false while either is latched or the service stops.
#[derive(Serialize, ToSchema)]
pub struct CellView {
    #[serde(flatten)]
    status: CellStatus,
    cell: String,
    queue_length: usize,
    accepting_jobs: bool,
    /// The names a job's `controller` takes besides `active` and `policy:<id>`.
    controllers: Vec<&'static str>,
}

fn view(context: &Context) -> CellView {
    let status = context.cell.status();
    CellView {
        queue_length: status.queue.len(),
        status,
        cell: context.cell_config.name.clone(),
        accepting_jobs: context.accepting_jobs(),
        controllers: crate::policy::BUILTIN_CONTROLLERS
            .iter()
            .chain(&crate::policy::LEARNED_CONTROLLERS)
            .copied()
            .collect(),
    }
}

/// The cell as it is now.
#[utoipa::path(get, path = "/api/cell", tag = "cell",
    responses((status = 200, description = "The cell", body = CellView)))]
async fn read(State(context): State<Context>, auth: Auth) -> ApiResult<Json<CellView>> {
    auth.require(Role::Viewer)?;
    Ok(Json(view(&context)))
}

/// Latches the e-stop (operator): motion stops at once, the running job fails with `estop`,
/// queued jobs are cancelled. Stays latched (across restarts too) until a reset.
#[utoipa::path(post, path = "/api/cell/estop", tag = "cell",
    responses((status = 200, description = "Stopped and latched", body = CellView)))]
async fn estop(
    State(context): State<Context>,
    Operator(caller): Operator,
) -> ApiResult<Json<CellView>> {
    workflows::cell::estop(&context, &caller.name).await?;
    Ok(Json(view(&context)))
}

/// Clears the e-stop latch and the robot driver's (operator): a driver reconnects if it must
/// and checks the hardware. Starts nothing: the next motion is the next job an operator
/// creates.
#[utoipa::path(post, path = "/api/cell/reset", tag = "cell",
    responses(
        (status = 200, description = "Unlatched", body = CellView),
        (status = 503, description = "The hardware is not ready (unreachable, not referenced, \
            moved): both latches stay; the body says why"),
    ))]
async fn reset(
    State(context): State<Context>,
    Operator(caller): Operator,
) -> ApiResult<Json<CellView>> {
    workflows::cell::reset(&context, &caller.name).await?;
    Ok(Json(view(&context)))
}
