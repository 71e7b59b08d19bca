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

use std::net::{TcpStream, ToSocketAddrs};

/// Where the drivers report their figures (the service's metrics). The drivers see only this.
pub trait DriverObserver: Send + Sync {
    /// One command's round trip to the hexapod controller, from sent to answered, s.
    fn controller_round_trip(&self, seconds: f64);
    /// A camera frame's age when the cell took it, by the cell's clock, s.
    fn camera_frame_age(&self, seconds: f64);
    /// A connection made again after one was lost: `robot` or `camera`.
    fn reconnected(&self, driver: &'static str);
}

/// Reports to no one.
pub struct Unobserved;

impl DriverObserver for Unobserved {
    fn controller_round_trip(&self, _: f64) {}
    fn camera_frame_age(&self, _: f64) {}
    fn reconnected(&self, _: &'static str) {}
}
use std::time::Duration;

/// Opens a TCP connection to `address` (`host:port`) within `timeout_ms`, with Nagle's delay
/// off (every command and frame is small and wanted at once). The error is the reason in
/// words; each driver names the address in its own typed error.
pub(crate) fn connect_tcp(address: &str, timeout_ms: u64) -> Result<TcpStream, String> {
    let target = address
        .to_socket_addrs()
        .map_err(|e| e.to_string())?
        .next()
        .ok_or_else(|| "the address resolves to nothing".to_string())?;
    let stream = TcpStream::connect_timeout(&target, Duration::from_millis(timeout_ms))
        .map_err(|e| e.to_string())?;
    stream.set_nodelay(true).map_err(|e| e.to_string())?;
    Ok(stream)
}
