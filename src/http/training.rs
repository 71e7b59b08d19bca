//! `/api/training`: start a training run (admin), follow it (viewer), cancel it (admin). One
//! run at a time, on a thread of its own at low priority, so a running job keeps its timing.
//! The result is registered as a `candidate` policy linked to the run, and the run to the
//! demonstrations it learned from.

use super::Context;
use super::auth::{Admin, Auth};
use super::error::{ApiResult, Items, Json, Path};
use crate::learning::run::{TrainingPart, TrainingSettings};
use crate::storage::tokens::Role;
use crate::storage::training;
use crate::workflows::queue::Cancelled;
use crate::workflows::{self, training::TrainingRequest};
use axum::extract::State;
use axum::http::StatusCode;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<Context> {
    OpenApiRouter::new()
        .routes(routes!(start, list))
        .routes(routes!(read))
        .routes(routes!(cancel))
}

#[derive(Debug, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct StartBody {
    /// Overrides `settings.part`.
    part: Option<TrainingPart>,
    /// Overrides `settings.seed`; any u64.
    #[schema(minimum = 0, maximum = 18_446_744_073_709_551_615_u64)]
    #[serde(default, deserialize_with = "crate::integer::optional_integer")]
    seed: Option<u64>,
    /// TD3 episodes (overrides `settings.td3_episodes`).
    #[schema(minimum = 1, maximum = 1_000_000)]
    #[serde(default, deserialize_with = "crate::integer::optional_integer")]
    episodes: Option<usize>,
    /// Stored demonstrations to learn from, each once; none: record `record` episodes of the
    /// demonstrator in the twin.
    #[schema(schema_with = distinct_ids)]
    #[serde(default, deserialize_with = "crate::integer::optional_integers")]
    demonstrations: Option<Vec<i64>>,
    /// Episodes to record when no demonstrations are named (default 400).
    #[schema(minimum = 10, maximum = 100_000)]
    #[serde(default, deserialize_with = "crate::integer::optional_integer")]
    record: Option<usize>,
    /// Every other setting; what is left out keeps its default (`celld train all`'s).
    settings: Option<TrainingSettings>,
}

/// `demonstrations`' schema: `null`, or at most `MAX_NAMED_DEMONSTRATIONS` ids, none twice.
fn distinct_ids() -> utoipa::openapi::schema::Array {
    use utoipa::openapi::schema::{ArrayBuilder, ObjectBuilder, SchemaType, Type};
    ArrayBuilder::new()
        .schema_type(SchemaType::from_iter([Type::Array, Type::Null]))
        .items(ObjectBuilder::new().schema_type(Type::Integer).format(Some(
            utoipa::openapi::SchemaFormat::KnownFormat(utoipa::openapi::KnownFormat::Int64),
        )))
        .max_items(Some(workflows::training::MAX_NAMED_DEMONSTRATIONS))
        .unique_items(true)
        .build()
}

/// Starts a training run (admin): demonstrations in, a candidate policy out, on a
/// low-priority thread beside the cell. It waits in the work queue with evaluations
/// (`queued`, with its `queue_position`) while `work.concurrency` pieces of work compute;
/// past `work.queue_length` waiting, 429 with `Retry-After`.
#[utoipa::path(post, path = "/api/training", tag = "training", request_body = StartBody,
    responses(
        (status = 202, description = "Started, or queued", body = training::TrainingRun),
        (status = 429, description = "The work queue is full (`work.queue_length`)",
            body = crate::http::document::ErrorBody,
            headers(("Retry-After" = u64, description = "Seconds worth waiting first"))),
    ))]
async fn start(
    State(context): State<Context>,
    Admin(caller): Admin,
    Json(body): Json<StartBody>,
) -> ApiResult<(StatusCode, Json<training::TrainingRun>)> {
    let request = TrainingRequest {
        settings: body.settings,
        part: body.part,
        seed: body.seed,
        episodes: body.episodes,
        demonstrations: body.demonstrations.unwrap_or_default(),
        record: body.record,
    };
    let run = workflows::training::start(&context, request, &caller.name).await?;
    Ok((StatusCode::ACCEPTED, Json(run)))
}

/// Every training run, newest first (viewer).
#[utoipa::path(get, path = "/api/training", tag = "training",
    responses((status = 200, description = "The runs", body = Items<training::TrainingRun>)))]
async fn list(
    State(context): State<Context>,
    auth: Auth,
) -> ApiResult<Json<Items<training::TrainingRun>>> {
    auth.require(Role::Viewer)?;
    Ok(Json(Items {
        items: workflows::training::list(&context).await?,
    }))
}

/// One training run with its live stage, progress and learning curve (viewer).
#[utoipa::path(get, path = "/api/training/{id}", tag = "training", params(("id" = i64, Path)),
    responses((status = 200, description = "The run", body = training::TrainingRun)))]
async fn read(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
) -> ApiResult<Json<training::TrainingRun>> {
    auth.require(Role::Viewer)?;
    Ok(Json(workflows::training::get(&context, id).await?))
}

#[derive(Serialize, ToSchema)]
pub struct Cancelling {
    id: i64,
    /// `cancelled`: it was queued and has left the queue; `cancelling`: it runs, stops at its
    /// next check and is then `cancelled`.
    #[schema(pattern = "^(cancelled|cancelling)$")]
    status: &'static str,
}

/// Cancels a training run (admin): a queued one leaves the queue and ends `cancelled`; a
/// running one stops at its next check.
#[utoipa::path(post, path = "/api/training/{id}/cancel", tag = "training",
    params(("id" = i64, Path)),
    responses((status = 202, description = "Cancelling", body = Cancelling)))]
async fn cancel(
    State(context): State<Context>,
    Admin(caller): Admin,
    Path(id): Path<i64>,
) -> ApiResult<(StatusCode, Json<Cancelling>)> {
    let cancelled = workflows::training::cancel(&context, id, &caller.name).await?;
    let status = match cancelled {
        Cancelled::Dequeued => "cancelled",
        _ => "cancelling",
    };
    Ok((StatusCode::ACCEPTED, Json(Cancelling { id, status })))
}
