//! `/api/demonstrations`: import (admin), list and export (viewer), delete (admin). A job with
//! `"demonstration": true` records one when it succeeds. The format is `learning::demos`'s JSON
//! Lines, one step a line, which `celld train --demos-file` reads too.

use super::Context;
use super::auth::{Admin, Auth};
use super::error::{ApiError, ApiResult, Items, Json, Path, Query};
use crate::storage::demonstrations::{self, Demonstration};
use crate::storage::tokens::Role;
use crate::workflows;
use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{DefaultBodyLimit, State};
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use serde::Deserialize;
use utoipa::IntoParams;
use utoipa_axum::router::{OpenApiRouter, UtoipaMethodRouterExt};
use utoipa_axum::routes;

pub fn router(max_import_bytes: usize) -> OpenApiRouter<Context> {
    OpenApiRouter::new()
        .routes(routes!(import, list).layer(DefaultBodyLimit::max(max_import_bytes)))
        .routes(routes!(export, remove))
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
pub struct ImportQuery {
    /// The demonstration's name (default `imported`); spaces around it are dropped.
    #[param(min_length = 1, max_length = 100, pattern = r"\S")]
    name: Option<String>,
}

/// Imports demonstrations (admin): JSON Lines, one step a line, as `celld train --demos-file`
/// reads and the export writes. A bad line refuses the whole body (422 names the line).
#[utoipa::path(post, path = "/api/demonstrations", tag = "demonstrations", params(ImportQuery),
    request_body(content = String, content_type = "text/plain",
        description = "JSON Lines (any content type is read as such)"),
    responses((status = 201, description = "Stored", body = Demonstration)))]
async fn import(
    State(context): State<Context>,
    Admin(caller): Admin,
    Query(query): Query<ImportQuery>,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<(StatusCode, Json<Demonstration>)> {
    let body = body?;
    let name = query.name.as_deref().map(str::trim).unwrap_or("imported");
    let stored =
        workflows::demonstrations::import(&context, name, body.to_vec(), &caller.name).await?;
    Ok((StatusCode::CREATED, Json(stored)))
}

/// Every stored demonstration (viewer).
#[utoipa::path(get, path = "/api/demonstrations", tag = "demonstrations",
    responses((status = 200, description = "The demonstrations", body = Items<Demonstration>)))]
async fn list(State(context): State<Context>, auth: Auth) -> ApiResult<Json<Items<Demonstration>>> {
    auth.require(Role::Viewer)?;
    Ok(Json(Items {
        items: demonstrations::list(&context.db).await?,
    }))
}

/// One demonstration's steps as JSON Lines (viewer).
#[utoipa::path(get, path = "/api/demonstrations/{id}", tag = "demonstrations",
    params(("id" = i64, Path)),
    responses((status = 200, description = "The steps", body = String,
        content_type = "application/x-ndjson")))]
async fn export(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
) -> ApiResult<impl IntoResponse> {
    auth.require(Role::Viewer)?;
    let body = demonstrations::body(&context.db, id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("no demonstration with id {id}")))?;
    Ok(([(header::CONTENT_TYPE, "application/x-ndjson")], body))
}

/// Deletes a demonstration (admin).
#[utoipa::path(delete, path = "/api/demonstrations/{id}", tag = "demonstrations",
    params(("id" = i64, Path)),
    responses((status = 204, description = "Deleted")))]
async fn remove(
    State(context): State<Context>,
    Admin(caller): Admin,
    Path(id): Path<i64>,
) -> ApiResult<StatusCode> {
    workflows::demonstrations::delete(&context, id, &caller.name).await?;
    Ok(StatusCode::NO_CONTENT)
}
