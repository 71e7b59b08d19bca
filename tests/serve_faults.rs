//! `celld serve` under faults and abuse: each module takes one kind (storage, work, connections,
//! access, inputs) against a real server, with its own SQLite file.

mod serve_support;

#[path = "serve_faults/inputs.rs"]
mod inputs;
