//! The cell as the service drives it: the hardware behind a trait (the digital twin is one
//! implementation), one job's run as a pure `step` core, and the threads around it.
//!
//! `backend` and `job` are pure (no async runtime, no storage); `task` is the thin thread shell
//! that owns the robot, runs the queue in order and reports events to whoever `app.rs` wires in;
//! `ingestion` is camera ingestion's thread.

pub mod backend;
pub mod cpu;
pub mod drivers;
pub mod ingestion;
pub mod job;
pub mod latch_latency;
pub mod packml;
pub mod task;

pub use backend::{BackendError, CellBackend, DriverLatch, TwinBackend};
pub use drivers::{DriverBackend, DriverSettings};
pub use job::{
    ControllerSource, JobEnd, JobRun, JobSpec, JobStatus, SafetyLimits, StepRecord, StepUncertainty,
};
pub use task::{CellCommand, CellEvent, CellHandle, CellStatus, JobProgress, MachineUpdate};
