//! `/api/telemetry`: Server-Sent Events, one `step` event per control step and one `job` event
//! per job status change, `cell` on e-stop and reset, `machine` on each change of the PackML
//! state or the counters. Each subscriber has a bounded buffer; one
//! that falls behind skips ahead (a `lagged` event says how many it missed, and the metrics
//! count them), so a slow reader never holds up the control loop.

use super::auth::StreamCaller;
use super::error::ApiResult;
use super::{Context, TelemetryMessage};
use crate::metrics::Metrics;
use crate::storage::tokens::Role;
use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use futures_util::{Stream, StreamExt};
use std::convert::Infallible;
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::{broadcast, watch};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<Context> {
    OpenApiRouter::new().routes(routes!(subscribe))
}

/// One event of the stream, as an SSE client reads it.
#[derive(utoipa::ToSchema)]
#[allow(dead_code)] // Described, not built: the events are written by axum's `Sse`.
struct StreamEvent {
    event: EventKind,
    /// The event's JSON, as text.
    data: String,
}

#[derive(utoipa::ToSchema)]
#[allow(dead_code)] // Described, not built.
#[schema(rename_all = "snake_case")]
enum EventKind {
    Cell,
    Step,
    Job,
    Machine,
    Lagged,
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

/// Live events (viewer) as Server-Sent Events: `cell` (`{"estop_latched": bool,
/// "driver_latch": null or {code, reason, since_unix_ms}}`, first the latches as they are, then
/// on each e-stop, reset and driver latch), `step` (one control step, as stored), `job`
/// (a job started or ended), `machine` (`{"transitions": [{from, to, cause}], "machine":
/// {state, state_number, unit_mode, stop_reason, counters}}`: the PackML state or the counters
/// changed; docs/opcua.md), `lagged` (`{"skipped": n}`: this
/// subscriber fell behind and skipped n events). The token may also come as `?access_token=`.
#[utoipa::path(get, path = "/api/telemetry", tag = "telemetry",
    security(("bearer" = []), ("access_token" = [])),
    responses((status = 200, description = "The event stream, until the service stops",
        body = StreamEvent, content_type = "text/event-stream")))]
async fn subscribe(
    State(context): State<Context>,
    StreamCaller(auth): StreamCaller,
) -> ApiResult<Sse<impl Stream<Item = Result<Event, Infallible>>>> {
    auth.require(Role::Viewer)?;
    // The latch as it is now, first: a subscriber (a dashboard reconnecting, say) starts from
    // the cell's state instead of waiting for the next change.
    let status = context.cell.status();
    let latches = serde_json::json!({
        "estop_latched": status.estop_latched,
        "driver_latch": status.driver_latch,
    });
    let now = TelemetryMessage {
        event: "cell",
        data: latches.to_string().into(),
    };
    let stream = futures_util::stream::once(async { now })
        .chain(messages(
            context.telemetry.subscribe(),
            context.shutdown.clone(),
            context.metrics.clone(),
        ))
        .map(|message| Ok(Event::default().event(message.event).data(&*message.data)));
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

/// One subscriber's messages until shutdown, counted as a subscriber while it lives. Falling
/// more than the channel's capacity behind yields one `lagged` message with the number
/// skipped (also counted in the metrics) and continues from the oldest message still held.
fn messages(
    receiver: broadcast::Receiver<TelemetryMessage>,
    shutdown: watch::Receiver<bool>,
    metrics: Metrics,
) -> impl Stream<Item = TelemetryMessage> {
    metrics.telemetry_subscribers.inc();
    let subscription = Subscription {
        receiver,
        shutdown,
        metrics,
    };
    futures_util::stream::unfold(subscription, |mut sub| async move {
        if *sub.shutdown.borrow() {
            return None;
        }
        let message = tokio::select! {
            message = sub.receiver.recv() => match message {
                Ok(message) => message,
                Err(RecvError::Lagged(skipped)) => {
                    sub.metrics.telemetry_lagged.inc_by(skipped);
                    TelemetryMessage {
                        event: "lagged",
                        data: format!("{{\"skipped\":{skipped}}}").into(),
                    }
                }
                Err(RecvError::Closed) => return None,
            },
            _ = sub.shutdown.changed() => return None,
        };
        Some((message, sub))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message(n: usize) -> TelemetryMessage {
        TelemetryMessage {
            event: "step",
            data: format!("{{\"step\":{n}}}").into(),
        }
    }

    #[tokio::test]
    async fn a_slow_subscriber_skips_ahead_and_is_counted() {
        let (sender, receiver) = broadcast::channel(4);
        let (stop, shutdown) = watch::channel(false);
        let metrics = Metrics::default();
        let mut stream = Box::pin(messages(receiver, shutdown, metrics.clone()));
        assert_eq!(metrics.telemetry_subscribers.get(), 1);
        // Ten events while the subscriber reads nothing: the sender never waits.
        for n in 1..=10 {
            sender.send(message(n)).unwrap();
        }
        let first = stream.next().await.unwrap();
        assert_eq!((first.event, &*first.data), ("lagged", "{\"skipped\":6}"));
        assert_eq!(metrics.telemetry_lagged.get(), 6);
        for n in 7..=10 {
            assert_eq!(
                &*stream.next().await.unwrap().data,
                format!("{{\"step\":{n}}}")
            );
        }
        stop.send(true).unwrap();
        assert!(stream.next().await.is_none(), "the stream ends at shutdown");
        drop(stream);
        assert_eq!(metrics.telemetry_subscribers.get(), 0);
    }
}
