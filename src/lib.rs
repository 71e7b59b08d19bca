//! `assembly-cell`: the digital twin, learning and service behind `celld`.
//!
//! Pure libraries (no async runtime, no storage): [`geometry`], [`kinematics`], [`collision`],
//! [`camera`], [`sim`], [`policy`]. See DESIGN.md §3 and docs/.

pub mod camera;
pub mod collision;
pub mod config;
pub mod geometry;
pub mod kinematics;
pub mod learning;
pub mod policy;
pub mod sim;
