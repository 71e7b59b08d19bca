//! Bearer tokens and roles. `Authorization: Bearer TOKEN` on every route but health, metrics
//! and the OpenAPI document. A browser's EventSource cannot send headers, so the telemetry
//! stream also takes `?access_token=TOKEN` ([`StreamCaller`]); no other route does, so tokens
//! stay out of ordinary URLs and logs.

use super::Context;
use super::error::ApiError;
use crate::storage::tokens::{Caller, Role};
use axum::extract::FromRequestParts;
use axum::http::request::Parts;

/// The authenticated caller of a request.
pub struct Auth(pub Caller);

impl Auth {
    /// Refuses (403) a caller below `role`.
    pub fn require(&self, role: Role) -> Result<&Caller, ApiError> {
        if self.0.role >= role {
            Ok(&self.0)
        } else {
            Err(ApiError::forbidden(format!(
                "this needs the {} role; token `{}` is {}",
                role.as_str(),
                self.0.name,
                self.0.role.as_str()
            )))
        }
    }
}

async fn caller_of(context: &Context, secret: Option<&str>) -> Result<Caller, ApiError> {
    use crate::workflows::tokens::{AuthError, authenticate};
    let secret = secret.ok_or_else(|| {
        ApiError::unauthorized("missing token: send `Authorization: Bearer TOKEN`")
    })?;
    authenticate(context, secret).await.map_err(|e| match e {
        AuthError::Storage(_) => ApiError::new(
            axum::http::StatusCode::INTERNAL_SERVER_ERROR,
            "storage",
            e.to_string(),
        ),
        refused => ApiError::unauthorized(refused.to_string()),
    })
}

fn bearer(parts: &Parts) -> Result<Option<&str>, ApiError> {
    let Some(value) = parts.headers.get(axum::http::header::AUTHORIZATION) else {
        return Ok(None);
    };
    let value = value
        .to_str()
        .map_err(|_| ApiError::unauthorized("the Authorization header is not text"))?;
    value
        .strip_prefix("Bearer ")
        .map(|s| Some(s.trim()))
        .ok_or_else(|| ApiError::unauthorized("the Authorization header must be `Bearer TOKEN`"))
}

impl FromRequestParts<Context> for Auth {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, context: &Context) -> Result<Self, ApiError> {
        Ok(Auth(caller_of(context, bearer(parts)?).await?))
    }
}

/// Like [`Auth`], also taking the token from `?access_token=`.
pub struct StreamCaller(pub Auth);

impl FromRequestParts<Context> for StreamCaller {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, context: &Context) -> Result<Self, ApiError> {
        let from_query = parts.uri.query().and_then(|query| {
            query
                .split('&')
                .find_map(|pair| pair.strip_prefix("access_token="))
                .map(str::to_string)
        });
        let secret = match bearer(parts)? {
            Some(secret) => Some(secret.to_string()),
            None => from_query,
        };
        Ok(StreamCaller(Auth(
            caller_of(context, secret.as_deref()).await?,
        )))
    }
}

/// A caller with the operator role or above, checked from the headers alone: as an extractor
/// before the body's, a caller without the role is refused (403) before the body is read, so
/// what it sent cannot change the answer.
pub struct Operator(pub Caller);

impl FromRequestParts<Context> for Operator {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, context: &Context) -> Result<Self, ApiError> {
        let auth = Auth::from_request_parts(parts, context).await?;
        auth.require(Role::Operator)?;
        Ok(Operator(auth.0))
    }
}

/// A caller with the admin role, checked from the headers alone, as [`Operator`].
pub struct Admin(pub Caller);

impl FromRequestParts<Context> for Admin {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, context: &Context) -> Result<Self, ApiError> {
        let auth = Auth::from_request_parts(parts, context).await?;
        auth.require(Role::Admin)?;
        Ok(Admin(auth.0))
    }
}
