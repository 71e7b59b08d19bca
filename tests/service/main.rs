//! `celld serve` as its clients meet it: the HTTP API, its conformance to its own OpenAPI
//! description, the dashboard in a browser, the client examples, policies, demonstrations,
//! training, recovery and faults. Each test starts its own server on its own SQLite file.

#[path = "../support/browser.rs"]
mod browser_support;
#[path = "../support/drivers.rs"]
mod drivers_support;
#[path = "../support/fleet.rs"]
mod fleet_support;
#[path = "../support/postgres.rs"]
mod postgres_support;
#[path = "../support/serve.rs"]
mod serve_support;

mod api_conformance;
mod dashboard_browser;
mod examples_run;
mod fleet;
mod fleet_dashboard;
mod machine_state;
mod opcua_server;
mod opcua_service;
mod postgres_harness;
mod serve_api;
mod serve_demonstrations;
mod serve_faults;
mod serve_policies;
mod serve_recovery;
mod serve_training;
