//! Health, Prometheus metrics and the OpenAPI description (no token), the caller's own token
//! (any role), tokens and the audit log (admin).

use super::Context;
use super::auth::{Admin, Auth};
use super::error::{ApiResult, Items, Json, Query};
use crate::storage::audit::{self, AuditEntry};
use crate::storage::health::WriteFault;
use crate::storage::tokens::{NewToken, Role};
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<Context> {
    OpenApiRouter::new()
        .routes(routes!(health))
        .routes(routes!(metrics))
        .routes(routes!(openapi))
        .routes(routes!(me))
        .routes(routes!(create_token))
        .routes(routes!(read_audit))
}

#[derive(Serialize, ToSchema)]
pub struct Health {
    /// `ok`, or `degraded` when the database or the control thread is gone or the database
    /// takes no writes.
    status: &'static str,
    version: &'static str,
    /// Whether the database answers and takes writes (see `storage`).
    database: bool,
    control_thread: bool,
    accepting_jobs: bool,
    /// Whether writes commit; when they do not, the error and since when.
    storage: Storage,
}

/// The database's writes as the service last saw them.
#[derive(Serialize, ToSchema)]
pub struct Storage {
    /// False from a write that failed for the storage (a full disk, an I/O error) until one
    /// commits again; the storage writer retries on its own.
    writable: bool,
    /// The standing fault (none while writable).
    fault: Option<WriteFault>,
}

/// Whether the service can work: 200 when it can, 503 when the database or the control thread
/// is gone or the database takes no writes (requests that write answer 503
/// `storage_unavailable` then; the service recovers by itself once the disk has room).
#[utoipa::path(get, path = "/api/health", tag = "service", security(()),
    responses(
        (status = 200, description = "Healthy", body = Health),
        (status = 503, description = "Degraded: the body says what is missing", body = Health),
    ))]
async fn health(State(context): State<Context>) -> impl IntoResponse {
    let database = sqlx::query_scalar::<_, i64>("SELECT 1")
        .fetch_one(&context.db.reader)
        .await
        .is_ok();
    let fault = context.db.health.fault();
    let database = database && fault.is_none();
    let control_thread = context.cell.is_running();
    let healthy = database && control_thread;
    let status = if healthy {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    let body = Health {
        status: if healthy { "ok" } else { "degraded" },
        version: env!("CARGO_PKG_VERSION"),
        database,
        control_thread,
        accepting_jobs: context.accepting_jobs(),
        storage: Storage {
            writable: fault.is_none(),
            fault,
        },
    };
    (status, Json(body))
}

/// Prometheus metrics (text exposition format).
#[utoipa::path(get, path = "/metrics", tag = "service", security(()),
    responses((status = 200, description = "The metrics", body = String,
        content_type = "text/plain")))]
async fn metrics(State(context): State<Context>) -> impl IntoResponse {
    let status = context.cell.status();
    context.metrics.queue_length.set(status.queue.len() as i64);
    (
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        context.metrics.render(),
    )
}

/// This description (OpenAPI 3.1); browse it at `/api/docs`.
#[utoipa::path(get, path = "/api/openapi.json", tag = "service", security(()),
    responses((status = 200, description = "The OpenAPI document", body = Object)))]
async fn openapi() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "application/json")],
        super::openapi_json(),
    )
}

#[derive(Serialize, ToSchema)]
pub struct Me {
    token_id: i64,
    name: String,
    role: Role,
    may: May,
}

/// What the caller's role allows.
#[derive(Serialize, ToSchema)]
pub struct May {
    view: bool,
    operate: bool,
    administer: bool,
}

/// Who the token belongs to and what its role may do (the dashboard shows only that).
#[utoipa::path(get, path = "/api/me", tag = "service",
    responses((status = 200, description = "The caller", body = Me)))]
async fn me(auth: Auth) -> Json<Me> {
    let caller = auth.0;
    Json(Me {
        may: May {
            view: true,
            operate: caller.role >= Role::Operator,
            administer: caller.role >= Role::Admin,
        },
        token_id: caller.token_id,
        name: caller.name,
        role: caller.role,
    })
}

#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateToken {
    role: Role,
    /// Who or what the token is for; spaces around it are dropped.
    #[schema(min_length = 1, max_length = 100, pattern = r"\S")]
    name: String,
    /// Seconds from now until the token stops authenticating (default: never).
    #[serde(default, deserialize_with = "crate::integer::optional_integer")]
    #[schema(minimum = 1, maximum = 315_360_000)]
    expires_in_s: Option<u64>,
}

/// A new token (admin). The secret is in the answer once and stored only as a hash.
#[utoipa::path(post, path = "/api/tokens", tag = "service", request_body = CreateToken,
    responses((status = 201, description = "The new token, with its secret", body = NewToken)))]
async fn create_token(
    State(context): State<Context>,
    Admin(caller): Admin,
    Json(body): Json<CreateToken>,
) -> ApiResult<(StatusCode, Json<NewToken>)> {
    let token = crate::workflows::tokens::create(
        &context.db,
        body.role,
        &body.name,
        body.expires_in_s,
        &caller.name,
        &caller.name,
    )
    .await?;
    Ok((StatusCode::CREATED, Json(token)))
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
pub struct Page {
    /// Entries, newest first (default 100; clamped to 1..=1000).
    limit: Option<i64>,
    /// Entries to skip (default 0; a negative value counts as 0).
    offset: Option<i64>,
}

/// Who did what and when (admin), newest first.
#[utoipa::path(get, path = "/api/audit", tag = "service", params(Page),
    responses((status = 200, description = "A page of the audit log", body = Items<AuditEntry>)))]
async fn read_audit(
    State(context): State<Context>,
    _: super::auth::Admin,
    Query(page): Query<Page>,
) -> ApiResult<Json<Items<AuditEntry>>> {
    let limit = page.limit.unwrap_or(100).clamp(1, 1000);
    let offset = page.offset.unwrap_or(0).max(0);
    let items = audit::list(&context.db, limit, offset).await?;
    Ok(Json(Items { items }))
}
