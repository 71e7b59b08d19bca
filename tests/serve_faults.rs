//! `celld serve` under faults and abuse: each module takes one kind (storage, work, connections,
//! access, inputs) against a real server, with its own SQLite file.

mod serve_support;

#[path = "serve_faults/access.rs"]
mod access;
#[path = "serve_faults/connections.rs"]
mod connections;
#[path = "serve_faults/inputs.rs"]
mod inputs;
#[path = "serve_faults/storage.rs"]
mod storage;
#[path = "serve_faults/work.rs"]
mod work;
