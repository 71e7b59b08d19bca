//! The REST surface (axum): each resource owns its `router()` and only translates requests
//! into the `workflows` that do the work; [`Context`] is the one shared state;
//! [`error::ApiError`] is the one error. The OpenAPI description is derived from the
//! handlers' annotations and the types they take and return ([`openapi`]), so it cannot drift
//! from them; it is served at `/api/openapi.json` and browsable at `/api/docs`.

pub mod auth;
pub mod auth_limit;
pub mod cell;
pub mod dashboard;
pub mod demonstrations;
pub mod document;
pub mod error;
pub mod fleet;
pub mod jobs;
pub mod meta;
pub mod policies;
pub mod server;
pub mod stats;
pub mod telemetry;
pub mod tokens;
pub mod training;

pub use crate::workflows::{Context, TelemetryMessage};
use axum::Router;
use axum::extract::DefaultBodyLimit;
use error::ApiError;
use utoipa_axum::router::OpenApiRouter;

/// Every described route, with the OpenAPI description collected from their annotations.
/// `max_upload_bytes` is the body limit of the two upload routes (policies, demonstrations).
fn described_routes(max_upload_bytes: usize) -> OpenApiRouter<Context> {
    OpenApiRouter::with_openapi(document::base())
        .merge(meta::router())
        .merge(cell::router())
        .merge(jobs::router())
        .merge(policies::router(max_upload_bytes))
        .merge(demonstrations::router(max_upload_bytes))
        .merge(stats::router())
        .merge(fleet::router())
        .merge(telemetry::router())
        .merge(tokens::router())
        .merge(training::router())
}

/// The OpenAPI description of every route, as served at `/api/openapi.json`.
pub fn openapi() -> utoipa::openapi::OpenApi {
    document::finish(described_routes(usize::MAX).into_openapi())
}

/// [`openapi`] as JSON, made once.
pub fn openapi_json() -> &'static str {
    static JSON: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    JSON.get_or_init(|| serde_json::to_string(&openapi()).expect("the OpenAPI document serialises"))
}

/// The whole API.
pub fn router(context: Context) -> Router {
    let body_limit = context.settings.http.body_limit_bytes;
    let api: Router<Context> = described_routes(context.settings.policies.max_upload_bytes).into();
    let access = &context.settings.access;
    let limiter: auth_limit::Limiter =
        std::sync::Arc::new(std::sync::Mutex::new(auth_limit::FailureTable::new(
            access.auth_failure_limit,
            std::time::Duration::from_secs(access.auth_failure_window_s),
            access.auth_failure_addresses,
        )));
    Router::new()
        .merge(dashboard::router())
        .merge(document::browser())
        .merge(api)
        .fallback(|| async { ApiError::not_found("no such route") })
        .method_not_allowed_fallback(|| async {
            ApiError::new(
                axum::http::StatusCode::METHOD_NOT_ALLOWED,
                "method_not_allowed",
                "this route does not take that method",
            )
        })
        .layer(DefaultBodyLimit::max(body_limit))
        .layer(axum::middleware::from_fn_with_state(
            limiter,
            auth_limit::limit,
        ))
        // One span per request (method, path, status, latency) at CELLD_LOG=debug.
        .layer(tower_http::trace::TraceLayer::new_for_http().make_span_with(request_span))
        .layer(axum::middleware::from_fn_with_state(
            context.clone(),
            refuse_announced_oversize,
        ))
        .with_state(context)
}

/// The span of a request: its method, path and query with any `access_token` value replaced
/// (the telemetry stream takes the token there), never a header.
fn request_span(request: &axum::http::Request<axum::body::Body>) -> tracing::Span {
    let query = request.uri().query().map(redact_query).unwrap_or_default();
    tracing::debug_span!(
        "request",
        method = %request.method(),
        path = %request.uri().path(),
        query = %query,
    )
}

/// A query string with the value of every `access_token` replaced by `[redacted]`.
fn redact_query(query: &str) -> String {
    query
        .split('&')
        .map(|pair| match pair.split_once('=') {
            Some((key, _)) if key.eq_ignore_ascii_case("access_token") => {
                format!("{key}=[redacted]")
            }
            _ => pair.to_string(),
        })
        .collect::<Vec<_>>()
        .join("&")
}

/// Answers 413 from the headers alone when `Content-Length` is over the route's limit, before
/// any of the body is read (a body without a length is cut at the limit as it is read).
async fn refuse_announced_oversize(
    axum::extract::State(context): axum::extract::State<Context>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> axum::response::Response {
    use axum::response::IntoResponse;
    let limit = if matches!(
        request.uri().path(),
        "/api/policies" | "/api/demonstrations"
    ) {
        context.settings.policies.max_upload_bytes
    } else {
        context.settings.http.body_limit_bytes
    };
    let announced = request
        .headers()
        .get(axum::http::header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    match announced {
        Some(length) if length > limit as u64 => ApiError::new(
            axum::http::StatusCode::PAYLOAD_TOO_LARGE,
            "too_large",
            format!("length limit exceeded: the body is {length} bytes, the limit is {limit}"),
        )
        .into_response(),
        _ => next.run(request).await,
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_query_keeps_everything_but_the_token() {
        assert_eq!(
            super::redact_query("job=3&access_token=celld_ab12&x="),
            "job=3&access_token=[redacted]&x="
        );
        assert_eq!(
            super::redact_query("ACCESS_TOKEN=s&access_token"),
            "ACCESS_TOKEN=[redacted]&access_token"
        );
        assert_eq!(super::redact_query("limit=5"), "limit=5");
    }
}
