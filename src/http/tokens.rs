//! `/api/tokens` beyond making one (in `meta`): the list without secrets and revocation, both
//! admin only.

use super::Context;
use super::auth::Auth;
use super::error::{ApiResult, Items, Json, Path};
use crate::storage::tokens::{Role, TokenInfo};
use crate::workflows;
use axum::extract::State;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<Context> {
    OpenApiRouter::new()
        .routes(routes!(list))
        .routes(routes!(revoke))
}

/// Every token, oldest first (admin): who it is for, its role, when it was made and by whom,
/// when it expires and whether it was revoked; never its secret nor its hash.
#[utoipa::path(get, path = "/api/tokens", tag = "service",
    responses((status = 200, description = "The tokens", body = Items<TokenInfo>)))]
async fn list(State(context): State<Context>, auth: Auth) -> ApiResult<Json<Items<TokenInfo>>> {
    auth.require(Role::Admin)?;
    let items = workflows::tokens::list(&context.db).await?;
    Ok(Json(Items { items }))
}

/// Revokes a token (admin): its next request is refused with 401, and the revocation is in the
/// audit log. Revoking a revoked token answers it unchanged; a token revoking itself, or the
/// last admin token that still authenticates, is refused (409).
#[utoipa::path(delete, path = "/api/tokens/{id}", tag = "service",
    params(("id" = i64, Path)),
    responses((status = 200, description = "The token, revoked", body = TokenInfo)))]
async fn revoke(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
) -> ApiResult<Json<TokenInfo>> {
    let caller = auth.require(Role::Admin)?;
    let info = workflows::tokens::revoke(&context, id, caller).await?;
    Ok(Json(info))
}
