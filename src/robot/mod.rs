//! The robot seam: what the cell needs from a 6-SPS robot, whoever drives it.
//!
//! [`Robot`] is the trait a driver implements (the twin's is `sim::TwinDrive`). Safety is not
//! the driver's business: [`Supervised`] wraps any `Robot` and is itself a `Robot`, so every
//! move passes the collision supervisor before the driver sees it (docs/design.md §3 and §8).

mod speeds;
mod supervised;

pub use speeds::PlatformSpeeds;
pub use supervised::Supervised;

use crate::collision::supervisor::VetoReason;
use crate::drivers::gcs::GcsError;
use crate::geometry::{Move, Pose};
use crate::kinematics::KinematicsError;

/// Why a robot did not execute a move.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RobotError {
    /// The supervisor refused the move; the robot never saw it.
    #[error("vetoed: {0}")]
    Vetoed(VetoReason),
    /// The robot could not execute the move (no pose for its leg lengths, a drive fault).
    #[error("robot fault: {0}")]
    Fault(RobotFault),
}

/// What kept a robot from executing a move it was allowed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RobotFault {
    /// The move's pose has no leg lengths, or the legs' lengths no pose.
    #[error(transparent)]
    Kinematics(#[from] KinematicsError),
    /// The hexapod controller or the connection to it failed.
    #[error(transparent)]
    Drive(#[from] GcsError),
}

/// A robot the cell commands in its own language: moves of Segment I in {M}.
pub trait Robot {
    /// The platform pose last commanded, in {O} and the robot's nominal model.
    fn setpoint(&self) -> Pose;
    /// The legs' encoder readings, mm.
    fn encoders_mm(&self) -> [f64; 6];
    /// Moves Segment I by `step` (in {M}, from the setpoint) and returns once it is there.
    fn execute(&mut self, step: &Move) -> Result<(), RobotError>;
    /// Stops motion at once and keeps the robot where it is (protective stop).
    fn hold(&mut self);
}

impl<R: Robot + ?Sized> Robot for &mut R {
    fn setpoint(&self) -> Pose {
        (**self).setpoint()
    }

    fn encoders_mm(&self) -> [f64; 6] {
        (**self).encoders_mm()
    }

    fn execute(&mut self, step: &Move) -> Result<(), RobotError> {
        (**self).execute(step)
    }

    fn hold(&mut self) {
        (**self).hold()
    }
}
