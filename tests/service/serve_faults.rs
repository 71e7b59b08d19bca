//! `celld serve` under faults and abuse: each module takes one kind (storage, work, connections,
//! access, inputs) against a real server, with its own SQLite file.

use crate::serve_support;

mod access;
mod connections;
mod inputs;
mod storage;
mod work;
