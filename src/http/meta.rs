//! Health, Prometheus metrics and the OpenAPI document (no token), the caller's own token
//! (any role), tokens and the audit log (admin).

use super::Context;
use super::auth::Auth;
use super::error::{ApiError, ApiResult, Json, Query};
use crate::storage::audit::{self, AuditEntry};
use crate::storage::tokens::{self, NewToken, Role};
use axum::Router;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use axum::routing::{get, post};
use serde::Deserialize;
use serde_json::{Value, json};

/// The OpenAPI 3 description of every route.
pub const OPENAPI: &str = include_str!("openapi.json");

pub fn router() -> Router<Context> {
    Router::new()
        .route("/api/health", get(health))
        .route("/metrics", get(metrics))
        .route("/api/openapi.json", get(openapi))
        .route("/api/me", get(me))
        .route("/api/tokens", post(create_token))
        .route("/api/audit", get(read_audit))
}

async fn health(State(context): State<Context>) -> impl IntoResponse {
    let database = sqlx::query_scalar::<_, i64>("SELECT 1")
        .fetch_one(&context.db.reader)
        .await
        .is_ok();
    let control_thread = context.cell.is_running();
    let healthy = database && control_thread;
    let status = if healthy {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    let body = json!({
        "status": if healthy { "ok" } else { "degraded" },
        "version": env!("CARGO_PKG_VERSION"),
        "database": database,
        "control_thread": control_thread,
        "accepting_jobs": context.accepting_jobs(),
    });
    (status, Json(body))
}

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

async fn openapi() -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "application/json")], OPENAPI)
}

/// Who the token belongs to and what its role may do (the dashboard shows only that).
async fn me(auth: Auth) -> Json<Value> {
    let caller = &auth.0;
    Json(json!({
        "token_id": caller.token_id,
        "name": caller.name,
        "role": caller.role,
        "may": {
            "view": true,
            "operate": caller.role >= Role::Operator,
            "administer": caller.role >= Role::Admin,
        },
    }))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateToken {
    role: Role,
    name: String,
}

async fn create_token(
    State(context): State<Context>,
    auth: Auth,
    Json(body): Json<CreateToken>,
) -> ApiResult<(StatusCode, Json<NewToken>)> {
    let caller = auth.require(Role::Admin)?;
    let name = body.name.trim();
    if name.is_empty() || name.len() > 100 {
        return Err(ApiError::unprocessable("name must be 1 to 100 characters"));
    }
    let token = tokens::create(&context.db, body.role, name, &caller.name).await?;
    audit::record(
        &context.db,
        &caller.name,
        "token.create",
        json!({"token_id": token.id, "name": name, "role": body.role}),
    )
    .await?;
    Ok((StatusCode::CREATED, Json(token)))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Page {
    limit: Option<i64>,
    offset: Option<i64>,
}

async fn read_audit(
    State(context): State<Context>,
    auth: Auth,
    Query(page): Query<Page>,
) -> ApiResult<Json<Value>> {
    auth.require(Role::Admin)?;
    let limit = page.limit.unwrap_or(100).clamp(1, 1000);
    let offset = page.offset.unwrap_or(0).max(0);
    let items: Vec<AuditEntry> = audit::list(&context.db, limit, offset).await?;
    Ok(Json(json!({"items": items})))
}
