//! The digital twin of the cell: an imperfect robot, an imperfect camera and the two parts,
//! wrapped as a reinforcement-learning environment (paper §4.1, docs/design.md §4).

pub mod batch;
pub mod env;
pub mod fault;
pub mod judge;
pub mod randomise;
pub mod reward;
pub mod rig;
pub mod robot;

pub use batch::BatchEnv;
pub use env::{
    AssemblyEnv, EnvError, EnvOptions, FailureReason, InitialConditions, Observation, Outcome,
    PoseErrors, StepResult,
};
pub use fault::{Fault, MAX_MISMATCH_SCALE, Mismatch, UnknownFault};
pub use reward::RewardTerms;
pub use robot::CELL_ROBOT_SEED;
