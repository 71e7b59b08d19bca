//! Drivers for a real cell: the hexapod controller over PI's GCS 2.0 protocol ([`gcs`]) and
//! the measuring camera over OpenIGTLink ([`igtl`]). The protocol modules are pure (bytes and
//! text in, typed values out); the clients use std TCP and threads, since the control loop
//! is a plain thread. [`twin_server`] serves the twin as both (`celld twin-server`);
//! [`latency`] times the drivers against it (`celld latency`). docs/integration.md describes
//! the wiring.

pub mod gcs;
pub mod igtl;
pub mod latency;
pub mod twin_server;
