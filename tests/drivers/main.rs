//! The drivers against their peers: the GCS hexapod and OpenIGTLink camera drivers against
//! `celld twin-server` and against independent clients (PI's PIPython, pyigtl; the Python
//! peer scripts beside this file), jobs through the drivers end to end, stalls and faults.

#[path = "../support/camera_jobs.rs"]
mod camera_jobs;
#[path = "../support/drivers.rs"]
mod drivers_support;
#[path = "../support/serve.rs"]
mod serve_support;

mod camera_goals_smoke;
mod drivers_camera_faults;
mod drivers_camera_peers;
mod drivers_end_to_end;
mod drivers_gcs;
mod drivers_peers;
mod drivers_service;
mod drivers_stalls;
