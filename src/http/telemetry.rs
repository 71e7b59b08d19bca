//! `/api/telemetry`: Server-Sent Events, one `step` event per control step and one `job` event
//! per job status change, `cell` on e-stop and reset. Each subscriber has a bounded buffer; one
//! that falls behind skips ahead (a `lagged` event says how many it missed, and the metrics
//! count them), so a slow reader never holds up the control loop.

use super::auth::StreamCaller;
use super::error::ApiResult;
use super::{Context, TelemetryMessage};
use crate::metrics::Metrics;
use crate::storage::tokens::Role;
use axum::Router;
use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::routing::get;
use futures_util::Stream;
use std::convert::Infallible;
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::{broadcast, watch};

pub fn router() -> Router<Context> {
    Router::new().route("/api/telemetry", get(subscribe))
}

/// Counts the subscriber while its stream lives.
struct Subscription {
    receiver: broadcast::Receiver<TelemetryMessage>,
    shutdown: watch::Receiver<bool>,
    metrics: Metrics,
}

impl Drop for Subscription {
    fn drop(&mut self) {
        self.metrics.telemetry_subscribers.dec();
    }
}

async fn subscribe(
    State(context): State<Context>,
    StreamCaller(auth): StreamCaller,
) -> ApiResult<Sse<impl Stream<Item = Result<Event, Infallible>>>> {
    auth.require(Role::Viewer)?;
    context.metrics.telemetry_subscribers.inc();
    let subscription = Subscription {
        receiver: context.telemetry.subscribe(),
        shutdown: context.shutdown.clone(),
        metrics: context.metrics.clone(),
    };
    let stream = futures_util::stream::unfold(subscription, |mut sub| async move {
        if *sub.shutdown.borrow() {
            return None;
        }
        let event = tokio::select! {
            message = sub.receiver.recv() => match message {
                Ok(message) => Event::default().event(message.event).data(&*message.data),
                Err(RecvError::Lagged(skipped)) => {
                    sub.metrics.telemetry_lagged.inc_by(skipped);
                    Event::default().event("lagged").data(format!("{{\"skipped\":{skipped}}}"))
                }
                Err(RecvError::Closed) => return None,
            },
            _ = sub.shutdown.changed() => return None,
        };
        Some((Ok(event), sub))
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}
