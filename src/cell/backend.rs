//! The hardware seam: what the control loop needs from a cell, robot and camera together.
//!
//! Every move a backend executes has passed the collision supervisor (reachability and leg
//! stroke, the OBB test, exact clearance) first. The twin runs the supervisor inside
//! [`AssemblyEnv::step`]; a real robot driver is wrapped by the same supervisor before it sees
//! a pose.

use crate::config::cell::CellConfig;
use crate::geometry::Move;
use crate::sim::{AssemblyEnv, EnvError, EnvOptions, InitialConditions, Observation, StepResult};

/// A cell the control loop can drive: start an episode, execute supervised moves, hold.
pub trait CellBackend: Send {
    /// `twin`, or the driver's name.
    fn name(&self) -> &str;
    /// Brings Segment I to an episode's start (the twin samples it from `seed` and `initial`)
    /// and waits for the first usable camera frame.
    fn start(&mut self, seed: u64, initial: InitialConditions) -> Result<Observation, EnvError>;
    /// Supervises and executes one move, captures and estimates the new state.
    fn step(&mut self, action: &Move) -> Result<StepResult, EnvError>;
    /// Stops motion at once and keeps the robot where it is (protective stop).
    fn hold(&mut self);
}

/// The digital twin as a cell backend.
pub struct TwinBackend {
    env: AssemblyEnv,
}

impl TwinBackend {
    pub fn new(cell: &CellConfig) -> Self {
        TwinBackend {
            env: AssemblyEnv::new(cell, EnvOptions::from_cell(cell)),
        }
    }
}

impl CellBackend for TwinBackend {
    fn name(&self) -> &str {
        "twin"
    }

    fn start(&mut self, seed: u64, initial: InitialConditions) -> Result<Observation, EnvError> {
        self.env.reset_with(seed, initial)
    }

    fn step(&mut self, action: &Move) -> Result<StepResult, EnvError> {
        self.env.step(action)
    }

    /// The twin's robot moves only inside `step`, so between steps it already holds; ending
    /// the episode is the caller's part.
    fn hold(&mut self) {}
}
