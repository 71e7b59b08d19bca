//! `assembly-cell`: the digital twin, learning and service behind `celld`.
//!
//! Pure libraries (no async runtime, no storage): [`geometry`], [`kinematics`], [`collision`],
//! [`camera`], [`robot`] (the robot trait and its supervisor), [`sim`], [`policy`], [`learning`]. The service: [`cell`] (hardware seam, job
//! core, control thread), [`storage`] (SQLite), [`workflows`] (what the service does, no HTTP),
//! [`http`] (axum, translating requests), [`metrics`], wired by [`app`].
//! See docs/design.md §3 and docs/.

pub mod app;
pub mod camera;
pub mod cell;
pub mod collision;
pub mod config;
pub mod drivers;
pub mod error_text;
pub mod files;
pub mod fleet;
pub mod geometry;
pub mod http;
pub mod integer;
pub mod kinematics;
pub mod learning;
pub mod metrics;
pub mod opcua;
pub mod policy;
pub mod robot;
pub mod sim;
pub mod storage;
pub mod threads;
pub mod workflows;
