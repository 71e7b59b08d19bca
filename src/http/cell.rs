//! `/api/cell`: the cell's state (viewer), e-stop and reset (operator).

use super::Context;
use super::auth::Auth;
use super::error::{ApiError, ApiResult, Json};
use crate::cell::{CellCommand, CellStatus};
use crate::storage::tokens::Role;
use crate::storage::{self, audit};
use axum::extract::State;
use serde::Serialize;
use serde_json::json;
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<Context> {
    OpenApiRouter::new()
        .routes(routes!(read))
        .routes(routes!(estop))
        .routes(routes!(reset))
}

/// The cell: its backend, e-stop latch, running and queued jobs, last estimated pose.
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
async fn estop(State(context): State<Context>, auth: Auth) -> ApiResult<Json<CellView>> {
    let caller = auth.require(Role::Operator)?;
    let running = context.cell.status().current_job;
    context
        .cell
        .ask(|reply| CellCommand::EStop { reply })
        .await?;
    store_latch(&context).await.map_err(|e| ApiError {
        message: format!(
            "motion is stopped and the e-stop latched, but the latch could not be stored and \
             would not survive a restart: {}",
            e.message
        ),
        ..e
    })?;
    audit::record(
        &context.db,
        &caller.name,
        "cell.estop",
        json!({"job": running}),
    )
    .await?;
    if let Some(id) = running {
        super::jobs::wait_until_final(&context, id).await?;
    }
    Ok(Json(view(&context)))
}

/// Clears the e-stop latch (operator). Starts nothing: the next motion is the next job an
/// operator creates.
#[utoipa::path(post, path = "/api/cell/reset", tag = "cell",
    responses((status = 200, description = "Unlatched", body = CellView)))]
async fn reset(State(context): State<Context>, auth: Auth) -> ApiResult<Json<CellView>> {
    let caller = auth.require(Role::Operator)?;
    context
        .cell
        .ask(|reply| CellCommand::Reset { reply })
        .await?;
    store_latch(&context).await?;
    audit::record(&context.db, &caller.name, "cell.reset", json!({})).await?;
    Ok(Json(view(&context)))
}

/// Stores the control thread's latch as it is now. The control thread is asked first, so a
/// stop never waits on storage; the writes are serialised and each stores the latest state,
/// so an e-stop and a reset racing each other cannot leave the stored latch behind the
/// control thread's (which a restart would then believe).
async fn store_latch(context: &Context) -> ApiResult<()> {
    let _one_writer = context.latch_writes.lock().await;
    let latched = context.cell.status().estop_latched;
    storage::set_cell_flag(&context.db.writer, "estop", latched).await?;
    Ok(())
}
