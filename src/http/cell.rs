//! `/api/cell`: the cell's state and its machine record (viewer); e-stop, reset and the other
//! PackML commands (operator).

use super::Context;
use super::auth::{Auth, Operator};
use super::error::{ApiResult, Json};
use crate::cell::CellStatus;
use crate::cell::packml::{Command, Counters, MachineStatus};
use crate::storage::machine::{self, CycleTime, StoredTransition};
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
        .routes(routes!(machine))
        .routes(routes!(stop))
        .routes(routes!(hold))
        .routes(routes!(unhold))
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
/// and checks the hardware; the machine state goes from Aborted, Stopped or Complete to Idle
/// (PackML Clear, then Reset). Starts nothing: the next motion is the next job an operator
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

/// The machine state, its counters, the latest transitions and good parts' cycle times.
#[derive(Serialize, ToSchema)]
pub struct MachineView {
    #[serde(flatten)]
    machine: MachineStatus,
    /// Mean cycle time of the good parts, s.
    mean_cycle_time_s: Option<f64>,
    /// The latest 50 transitions, newest first.
    transitions: Vec<StoredTransition>,
    /// The latest 50 good parts' cycle times, newest first.
    cycle_times: Vec<CycleTime>,
}

/// The PackML machine state (docs/opcua.md), its stop reason, the production counters (kept
/// across restarts), its latest transitions and cycle times.
#[utoipa::path(get, path = "/api/cell/machine", tag = "cell",
    responses((status = 200, description = "The machine state and counters", body = MachineView)))]
async fn machine(State(context): State<Context>, auth: Auth) -> ApiResult<Json<MachineView>> {
    auth.require(Role::Viewer)?;
    let machine = context.cell.status().machine;
    let counters: &Counters = &machine.counters;
    Ok(Json(MachineView {
        mean_cycle_time_s: counters.mean_cycle_time_s(),
        transitions: machine::transitions(&context.db, 50).await?,
        cycle_times: machine::recent_cycle_times(&context.db, 50).await?,
        machine,
    }))
}

/// PackML Stop (operator): the robot holds, the running and queued jobs are cancelled
/// (`stopped`), and the cell stays Stopped, taking no jobs, until a reset.
#[utoipa::path(post, path = "/api/cell/stop", tag = "cell",
    responses(
        (status = 200, description = "Stopped", body = CellView),
        (status = 409, description = "The cell is Stopped or Aborted already"),
    ))]
async fn stop(
    State(context): State<Context>,
    Operator(caller): Operator,
) -> ApiResult<Json<CellView>> {
    workflows::cell::command(&context, &caller.name, Command::Stop).await?;
    Ok(Json(view(&context)))
}

/// PackML Hold (operator): the running job pauses once its current move is done; queued jobs
/// wait. Taken in Execute and Suspended.
#[utoipa::path(post, path = "/api/cell/hold", tag = "cell",
    responses(
        (status = 200, description = "Held", body = CellView),
        (status = 409, description = "Nothing runs to hold"),
    ))]
async fn hold(
    State(context): State<Context>,
    Operator(caller): Operator,
) -> ApiResult<Json<CellView>> {
    workflows::cell::command(&context, &caller.name, Command::Hold).await?;
    Ok(Json(view(&context)))
}

/// PackML Unhold (operator): a held job goes on.
#[utoipa::path(post, path = "/api/cell/unhold", tag = "cell",
    responses(
        (status = 200, description = "Executing again", body = CellView),
        (status = 409, description = "The cell is not Held"),
    ))]
async fn unhold(
    State(context): State<Context>,
    Operator(caller): Operator,
) -> ApiResult<Json<CellView>> {
    workflows::cell::command(&context, &caller.name, Command::Unhold).await?;
    Ok(Json(view(&context)))
}
