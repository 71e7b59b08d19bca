//! Drivers for a real cell: the hexapod controller over PI's GCS 2.0 protocol ([`gcs`]) and the
//! protocol modules are pure (text in, typed values out); the clients use std TCP and threads,
//! since the control loop is a plain thread.

pub mod gcs;
pub mod igtl;
