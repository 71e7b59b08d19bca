//! The libraries against independent answers: kinematics, collision, the camera's fit and
//! estimator, the twin, the scripted controllers, policy files and cell files; the bundled
//! policies' goals on a few episodes (`celld check --smoke`); and the product's words about
//! itself. One test binary, so the crate is linked once for all of them.

mod camera_fit;
mod cell_config;
mod collision_reference;
mod dmp_baseline;
mod drift_memory;
mod estimator_consistency;
mod fault_reactions;
mod kinematics_roundtrip;
mod policy_file;
mod policy_goals_smoke;
mod product_speaks_for_itself;
mod twin_env;
