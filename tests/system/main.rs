//! The cell as a system of processes talking over sockets: `celld serve` as its clients meet
//! it (`service/`) and the drivers against `celld twin-server` and independent peers
//! (`drivers/`). One binary, so that the long waits of one (schemathesis fuzzing the API, a
//! hundred stalled moves) run beside the other's tests, and the crate is linked once.

#[path = "../support/browser.rs"]
mod browser_support;
#[path = "../support/camera_jobs.rs"]
mod camera_jobs;
#[path = "../support/drivers.rs"]
mod drivers_support;
#[path = "../support/serve.rs"]
mod serve_support;

#[path = "../drivers/mod.rs"]
mod drivers;
#[path = "../service/mod.rs"]
mod service;
