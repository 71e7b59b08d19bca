//! Poses, frames and fitting a frame to measured fiducial points.

pub mod belief;
pub mod fit;
pub mod frames;
pub mod motion;
pub mod pose;

pub use belief::{Belief, Exact, PoseSd};
pub use frames::CellFrames;
pub use motion::Move;
pub use pose::Pose;
