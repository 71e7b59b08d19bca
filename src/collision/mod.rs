pub mod clearance;
pub mod obb;
pub mod supervisor;
