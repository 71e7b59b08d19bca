//! The service's Prometheus metrics (`GET /metrics`): jobs by outcome, control-step latency,
//! supervisor vetoes by reason, queue length, telemetry subscribers and their lag, and the
//! drivers' figures (controller round trips, camera frame age, reconnections, the latch).

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use std::sync::Arc;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct OutcomeLabel {
    /// The job's final status.
    pub status: String,
    /// Its failure reason, `none` on success.
    pub reason: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ReasonLabel {
    pub reason: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct DriverLabel {
    /// `robot` or `camera`.
    pub driver: String,
}

/// Every metric, cheap to clone (each is an `Arc` of atomics inside).
#[derive(Clone)]
pub struct Metrics {
    registry: Arc<Registry>,
    /// Jobs ended, by final status and failure reason.
    pub jobs: Family<OutcomeLabel, Counter>,
    /// Work time of one control step (decision, supervision, execution), s.
    pub step_seconds: Histogram,
    pub vetoes: Family<ReasonLabel, Counter>,
    pub queue_length: Gauge,
    pub telemetry_subscribers: Gauge,
    /// Telemetry events a slow subscriber skipped.
    pub telemetry_lagged: Counter,
    /// One command's round trip to the hexapod controller, s.
    pub controller_round_trip_seconds: Histogram,
    /// A camera frame's age when the cell took it (its timestamp to the cell's clock), s.
    pub camera_frame_age_seconds: Histogram,
    /// Connections the drivers made again after losing one, by driver.
    pub driver_reconnects: Family<DriverLabel, Counter>,
    /// 1 while the robot driver is latched (it moves nothing until an operator reset).
    pub driver_latched: Gauge,
    /// A replicated row's wait from its commit on the cell to its commit in the fleet, s.
    pub fleet_lag_seconds: Histogram,
    /// Rows committed on the cell and not yet in the fleet.
    pub fleet_backlog: Gauge,
    /// Rows (insertions, updates, deletions) the fleet committed.
    pub fleet_rows: Counter,
}

impl Default for Metrics {
    fn default() -> Self {
        let mut registry = Registry::with_prefix("celld");
        let jobs = Family::<OutcomeLabel, Counter>::default();
        registry.register("jobs", "Jobs ended, by outcome", jobs.clone());
        // 1 µs .. ~0.5 s.
        let step_seconds = Histogram::new(exponential_buckets(1e-6, 2.0, 20));
        registry.register(
            "control_step_seconds",
            "Work time of one control step (decision, supervision, execution)",
            step_seconds.clone(),
        );
        let vetoes = Family::<ReasonLabel, Counter>::default();
        registry.register(
            "supervisor_vetoes",
            "Moves the supervisor vetoed, by reason",
            vetoes.clone(),
        );
        let queue_length = Gauge::default();
        registry.register(
            "queue_length",
            "Jobs waiting for the robot",
            queue_length.clone(),
        );
        let telemetry_subscribers = Gauge::default();
        registry.register(
            "telemetry_subscribers",
            "Open telemetry streams",
            telemetry_subscribers.clone(),
        );
        let telemetry_lagged = Counter::default();
        registry.register(
            "telemetry_lagged_events",
            "Telemetry events skipped by subscribers that fell behind",
            telemetry_lagged.clone(),
        );
        // 10 µs .. ~5 s.
        let controller_round_trip_seconds = Histogram::new(exponential_buckets(1e-5, 2.0, 20));
        registry.register(
            "controller_round_trip_seconds",
            "One command's round trip to the hexapod controller",
            controller_round_trip_seconds.clone(),
        );
        // 1 ms .. ~16 s.
        let camera_frame_age_seconds = Histogram::new(exponential_buckets(1e-3, 2.0, 15));
        registry.register(
            "camera_frame_age_seconds",
            "A camera frame's age when the cell took it",
            camera_frame_age_seconds.clone(),
        );
        let driver_reconnects = Family::<DriverLabel, Counter>::default();
        registry.register(
            "driver_reconnects",
            "Connections the drivers made again after losing one",
            driver_reconnects.clone(),
        );
        let driver_latched = Gauge::default();
        registry.register(
            "driver_latched",
            "1 while the robot driver is latched until an operator reset",
            driver_latched.clone(),
        );
        // 1 ms .. ~65 s.
        let fleet_lag_seconds = Histogram::new(exponential_buckets(1e-3, 2.0, 17));
        registry.register(
            "fleet_lag_seconds",
            "A replicated row's wait from its commit on the cell to its commit in the fleet",
            fleet_lag_seconds.clone(),
        );
        let fleet_backlog = Gauge::default();
        registry.register(
            "fleet_backlog_rows",
            "Rows committed on the cell and not yet in the fleet",
            fleet_backlog.clone(),
        );
        let fleet_rows = Counter::default();
        registry.register(
            "fleet_replicated_rows",
            "Row insertions, updates and deletions the fleet committed",
            fleet_rows.clone(),
        );
        Metrics {
            registry: Arc::new(registry),
            fleet_lag_seconds,
            fleet_backlog,
            fleet_rows,
            controller_round_trip_seconds,
            camera_frame_age_seconds,
            driver_reconnects,
            driver_latched,
            jobs,
            step_seconds,
            vetoes,
            queue_length,
            telemetry_subscribers,
            telemetry_lagged,
        }
    }
}

impl Metrics {
    /// The text exposition format.
    pub fn render(&self) -> String {
        let mut out = String::new();
        prometheus_client::encoding::text::encode(&mut out, &self.registry)
            .expect("writing to a String cannot fail");
        out
    }

    pub fn count_job(&self, status: &str, reason: Option<&str>) {
        self.jobs
            .get_or_create(&OutcomeLabel {
                status: status.to_string(),
                reason: reason.unwrap_or("none").to_string(),
            })
            .inc();
    }

    pub fn count_veto(&self, reason: &str) {
        self.vetoes
            .get_or_create(&ReasonLabel {
                reason: reason.to_string(),
            })
            .inc();
    }
}

impl crate::drivers::DriverObserver for Metrics {
    fn controller_round_trip(&self, seconds: f64) {
        self.controller_round_trip_seconds.observe(seconds);
    }

    fn camera_frame_age(&self, seconds: f64) {
        self.camera_frame_age_seconds.observe(seconds);
    }

    fn reconnected(&self, driver: &'static str) {
        self.driver_reconnects
            .get_or_create(&DriverLabel {
                driver: driver.to_string(),
            })
            .inc();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_show_up_in_the_exposition() {
        let metrics = Metrics::default();
        metrics.count_job("succeeded", None);
        metrics.count_job("succeeded", None);
        metrics.count_veto("collision");
        metrics.step_seconds.observe(3e-6);
        let text = metrics.render();
        assert!(
            text.contains("celld_jobs_total{status=\"succeeded\",reason=\"none\"} 2"),
            "{text}"
        );
        assert!(
            text.contains("celld_supervisor_vetoes_total{reason=\"collision\"} 1"),
            "{text}"
        );
        assert!(
            text.contains("celld_control_step_seconds_count 1"),
            "{text}"
        );
    }
}
