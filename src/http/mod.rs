//! The REST surface (axum): each resource owns its `router()`; [`Context`] is the one shared
//! state; [`error::ApiError`] is the one error. Described by `openapi.json` in this folder,
//! served at `/api/openapi.json`.

pub mod auth;
pub mod cell;
pub mod error;
pub mod jobs;
pub mod meta;
pub mod stats;
pub mod telemetry;

use crate::cell::CellHandle;
use crate::config::cell::CellConfig;
use crate::config::service::ServiceConfig;
use crate::metrics::Metrics;
use crate::storage::Db;
use axum::Router;
use axum::extract::DefaultBodyLimit;
use error::ApiError;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use tokio::sync::{broadcast, watch};

/// One telemetry event, serialised once for every subscriber.
#[derive(Debug, Clone)]
pub struct TelemetryMessage {
    /// SSE event name: `step`, `job` or `cell`.
    pub event: &'static str,
    pub data: Arc<str>,
}

/// Everything a handler may need, cheap to clone.
#[derive(Clone)]
pub struct Context {
    pub db: Db,
    pub cell: CellHandle,
    pub cell_config: Arc<CellConfig>,
    pub settings: Arc<ServiceConfig>,
    pub metrics: Metrics,
    pub telemetry: broadcast::Sender<TelemetryMessage>,
    /// False once shutdown began: no new jobs.
    pub accepting: Arc<AtomicBool>,
    /// Becomes true at shutdown, so open streams end.
    pub shutdown: watch::Receiver<bool>,
}

impl Context {
    pub fn accepting_jobs(&self) -> bool {
        self.accepting.load(Ordering::SeqCst)
    }
}

/// The whole API.
pub fn router(context: Context) -> Router {
    let body_limit = context.settings.http.body_limit_bytes;
    Router::new()
        .merge(meta::router())
        .merge(cell::router())
        .merge(jobs::router())
        .merge(stats::router())
        .merge(telemetry::router())
        .fallback(|| async { ApiError::not_found("no such route") })
        .method_not_allowed_fallback(|| async {
            ApiError::new(
                axum::http::StatusCode::METHOD_NOT_ALLOWED,
                "method_not_allowed",
                "this route does not take that method",
            )
        })
        .layer(DefaultBodyLimit::max(body_limit))
        .with_state(context)
}
