pub mod clearance;
pub mod obb;
pub mod risk;
pub mod supervisor;
