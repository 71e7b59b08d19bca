//! The hardware seam: what the control loop needs from a cell, robot and camera together.
//!
//! Every move a backend executes has passed the collision supervisor (reachability and leg
//! stroke, the OBB test, exact clearance) first: the robot is always a
//! [`Supervised`](crate::robot::Supervised) robot: the twin's `TwinDrive` here, a PI hexapod's
//! `GcsRobot` in [`DriverBackend`](super::DriverBackend). Camera ingestion runs on a thread of
//! its own ([`Ingestion`]).

use super::ingestion::{Ingestion, IngestionStopped};
use crate::config::cell::CellConfig;
use crate::geometry::{CellFrames, Move};
use crate::sim::env::{first_usable_estimate, ingest_for};
use crate::sim::{AssemblyEnv, EnvError, EnvOptions, InitialConditions, Observation, StepResult};

/// What a driver latched on: it moves nothing until an operator reset (`GET /api/cell`'s
/// `driver_latch`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, utoipa::ToSchema)]
pub struct DriverLatch {
    /// A short stable name: `controller_dropped`, `controller_timeout`, `position_mismatch`.
    pub code: String,
    /// What happened, with its numbers.
    pub reason: String,
    /// When the driver latched, ms since the Unix epoch.
    pub since_unix_ms: u64,
}

/// Stops the robot from any thread (see [`CellBackend::emergency_stop`]).
pub type EmergencyStop = std::sync::Arc<dyn Fn() + Send + Sync>;

/// Why a backend could not start an episode or take a step.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BackendError {
    #[error(transparent)]
    Twin(#[from] EnvError),
    #[error(transparent)]
    Ingestion(#[from] IngestionStopped),
    /// The hexapod controller's driver.
    #[error("robot: {0}")]
    Drive(#[from] crate::drivers::gcs::GcsError),
    /// The camera's driver.
    #[error(transparent)]
    Camera(#[from] crate::drivers::igtl::camera::FrameError),
}

/// A cell the control loop can drive: start an episode, execute supervised moves, hold.
///
/// A step is two calls, so that camera ingestion's work on a capture overlaps the rest of the
/// control period: `act` sends the move and has the camera capture; `settle`, at the next
/// tick, takes ingestion's estimate and returns the step's result.
pub trait CellBackend: Send {
    /// `twin`, or the driver's name.
    fn name(&self) -> &str;
    /// Brings Segment I to an episode's start (the twin samples it from `seed` and `initial`)
    /// and waits for the first usable camera frame.
    fn start(&mut self, seed: u64, initial: InitialConditions)
    -> Result<Observation, BackendError>;
    /// Supervises and executes one move and has the camera capture; ingestion starts on it.
    fn act(&mut self, action: &Move) -> Result<(), BackendError>;
    /// The result of the move `act` sent: waits for ingestion's estimate of its capture (ready
    /// long before when a control period has passed) and judges the step.
    fn settle(&mut self) -> Result<StepResult, BackendError>;
    /// Stops motion at once and keeps the robot where it is (protective stop).
    fn hold(&mut self);
    /// Stops motion from any thread, at once, without waiting for the control thread (which
    /// may be waiting on the robot); the e-stop calls it before it latches. None: the
    /// control thread's `hold` is as fast.
    fn emergency_stop(&self) -> Option<EmergencyStop> {
        None
    }
    /// The operator's reset (after an e-stop): a driver that lost its hardware reconnects
    /// and checks it here, and moves nothing until it has. The twin has nothing to reset.
    fn reset(&mut self) -> Result<(), BackendError> {
        Ok(())
    }
    /// Why the backend's hardware driver holds until an operator reset, if it does. The twin
    /// never latches.
    fn latch(&self) -> Option<DriverLatch> {
        None
    }
    /// Called between jobs, a few times a second: a driver notices hardware that went away
    /// while it had nothing to ask of it, without sending anything.
    fn watch(&mut self) {}
}

/// The digital twin as a cell backend, its camera's shots ingested on their own thread.
pub struct TwinBackend {
    env: AssemblyEnv,
    ingestion: Ingestion,
    /// A shot was handed to ingestion and its estimate not yet taken.
    awaiting_estimate: bool,
}

impl TwinBackend {
    /// The twin of `cell`. Ingestion keeps to `cpu` when given (the control thread's CPU).
    /// Like a real cell it has one robot, kept from job to job, and each job starts from the
    /// drift the ones before learned of it.
    pub fn new(cell: &CellConfig, cpu: Option<usize>) -> Self {
        let options = Self::options(cell);
        let ingest = ingest_for(cell, &CellFrames::from_config(cell), &options);
        TwinBackend {
            env: AssemblyEnv::new(cell, options),
            ingestion: Ingestion::spawn(ingest, cpu),
            awaiting_estimate: false,
        }
    }

    /// The twin's options: the cell file's, with its one robot kept.
    pub fn options(cell: &CellConfig) -> EnvOptions {
        EnvOptions {
            kept_robots: 1,
            robot_seed: crate::sim::CELL_ROBOT_SEED,
            ..EnvOptions::from_cell(cell)
        }
    }
}

impl CellBackend for TwinBackend {
    fn name(&self) -> &str {
        "twin"
    }

    fn start(
        &mut self,
        seed: u64,
        initial: InitialConditions,
    ) -> Result<Observation, BackendError> {
        if std::mem::take(&mut self.awaiting_estimate) {
            // A move nobody settled: its estimate must not pass for the new episode's.
            self.ingestion.receive()?;
        }
        self.env.begin_episode(seed, initial)?;
        let estimate = first_usable_estimate(|first| {
            self.ingestion.take(self.env.capture_still(first).clone())
        })?;
        Ok(self.env.start_from(&estimate))
    }

    fn act(&mut self, action: &Move) -> Result<(), BackendError> {
        let shot = self.env.act(action)?.clone();
        self.ingestion.send(shot)?;
        self.awaiting_estimate = true;
        Ok(())
    }

    fn settle(&mut self) -> Result<StepResult, BackendError> {
        if !std::mem::take(&mut self.awaiting_estimate) {
            return Err(EnvError::OutOfOrder("settle without a move; call act first").into());
        }
        let estimate = self.ingestion.receive()?;
        Ok(self.env.settle(&estimate)?)
    }

    /// The twin's robot moves only inside `act`, so between moves it already holds; ending
    /// the episode is the caller's part.
    fn hold(&mut self) {}

    /// As with a real robot, the robot may have been serviced while the e-stop was latched:
    /// the next episode forgets what the cell remembers of its drift.
    fn reset(&mut self) -> Result<(), BackendError> {
        self.env.forget_robot();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::{Controller, expert::Expert};

    /// Runs one expert episode from `seed`; the drift's σ per mm along the axis the next
    /// episode starts from.
    fn episode_then_next_drift_sd(backend: &mut TwinBackend, cell: &CellConfig, seed: u64) -> f64 {
        let initial = InitialConditions::from_cell(cell);
        let mut expert = Expert::new(cell);
        expert.reset(seed);
        let mut observation = backend.start(seed, initial).unwrap();
        loop {
            backend.act(&expert.act(&observation).action).unwrap();
            let result = backend.settle().unwrap();
            observation = result.observation;
            if result.done {
                break;
            }
        }
        let next = backend.start(seed + 1, initial).unwrap();
        next.estimate.drift_knowledge(0).sd_per_mm()[2]
    }

    #[test]
    fn the_twin_remembers_its_robot_from_job_to_job_until_an_operators_reset() {
        let cell = CellConfig::reference();
        let mut backend = TwinBackend::new(&cell, None);
        let prior_sd = crate::camera::FusionTuning::default().drift_prior_sd;
        let remembered = episode_then_next_drift_sd(&mut backend, &cell, 1);
        assert!(remembered < prior_sd / 3.0, "{remembered} per mm");
        backend.reset().unwrap();
        let initial = InitialConditions::from_cell(&cell);
        let after_reset = backend.start(5, initial).unwrap();
        let sd = after_reset.estimate.drift_knowledge(0).sd_per_mm()[2];
        assert!(
            (sd - prior_sd).abs() < prior_sd * 0.01,
            "{sd} per mm after a reset"
        );
    }
}
