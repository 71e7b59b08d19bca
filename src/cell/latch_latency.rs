//! How soon a lost controller shows as the cell's latch (`celld latency`): the control thread
//! runs the drivers against an in-process twin-server through a relay; the relay closes the
//! controller's connection while the cell is idle, and the time is taken to the control
//! thread's status showing the latch (what `GET /api/cell` reads) and to its latch event (what
//! the telemetry sends). The operator's reset then clears it for the next sample.

use super::drivers::{DriverBackend, DriverSettings};
use super::job::SafetyLimits;
use super::task::{self, CellCommand, CellEvent, LoopSettings};
use crate::config::cell::CellConfig;
use crate::drivers::gcs::GcsSettings;
use crate::drivers::igtl::camera::CameraSettings;
use crate::drivers::latency::Samples;
use crate::drivers::twin_server::{TwinServer, TwinServerOptions};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Duration, Instant};

/// A relay in front of the controller whose connections can be closed at once.
struct Relay {
    address: SocketAddr,
    open: Arc<Mutex<Vec<TcpStream>>>,
}

impl Relay {
    fn start(upstream: SocketAddr) -> std::io::Result<Relay> {
        let listener = TcpListener::bind("127.0.0.1:0")?;
        let address = listener.local_addr()?;
        let open: Arc<Mutex<Vec<TcpStream>>> = Arc::default();
        let streams = open.clone();
        std::thread::spawn(move || {
            for client in listener.incoming() {
                let (Ok(client), Ok(server)) = (client, TcpStream::connect(upstream)) else {
                    continue;
                };
                let _ = (client.set_nodelay(true), server.set_nodelay(true));
                let (Ok(c), Ok(s)) = (client.try_clone(), server.try_clone()) else {
                    continue;
                };
                streams.lock().unwrap_or_else(|e| e.into_inner()).extend(
                    [client.try_clone(), server.try_clone()]
                        .into_iter()
                        .flatten(),
                );
                std::thread::spawn(move || copy(client, s));
                std::thread::spawn(move || copy(server, c));
            }
        });
        Ok(Relay { address, open })
    }

    /// Closes every connection through the relay, as a controller that goes away does.
    fn cut(&self) {
        for stream in self
            .open
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .drain(..)
        {
            let _ = stream.shutdown(Shutdown::Both);
        }
    }
}

fn copy(mut from: TcpStream, mut to: TcpStream) {
    let _ = std::io::copy(&mut from, &mut to);
    let _ = to.shutdown(Shutdown::Write);
}

/// `count` lost connections, each timed to the status and to the event, µs.
pub fn measure(cell: &CellConfig, count: usize) -> anyhow::Result<Vec<Samples>> {
    let server = TwinServer::start(&TwinServerOptions::loopback(cell, 1))?;
    let relay = Relay::start(server.gcs)?;
    let settings = DriverSettings {
        robot_address: relay.address.to_string(),
        robot: GcsSettings::default(),
        camera_address: server.igtl.to_string(),
        camera: CameraSettings::default(),
        rehearsal: true,
    };
    let backend = DriverBackend::connect(cell, settings, None)?;
    let (events, latched) = mpsc::channel();
    let sink = Box::new(move |event: CellEvent| {
        if let CellEvent::Latches {
            driver_latch: Some(_),
            ..
        } = event
        {
            let _ = events.send(Instant::now());
        }
    });
    let loop_settings = LoopSettings {
        period: None,
        limits: SafetyLimits {
            deadline_s: 1.0,
            max_stale_steps: 4,
        },
        estop_latched: false,
        counters: Default::default(),
        cpu: None,
    };
    let (handle, thread) = task::spawn(cell.clone(), Box::new(backend), loop_settings, sink);
    let (mut to_status, mut to_event) = (Vec::new(), Vec::new());
    for k in 0..count {
        // At different phases of the control thread's look at its hardware.
        std::thread::sleep(Duration::from_millis(20 + (k as u64 * 7) % 50));
        let cut = Instant::now();
        relay.cut();
        while handle.status().driver_latch.is_none() {
            if cut.elapsed() > Duration::from_secs(5) {
                anyhow::bail!("the latch did not show within 5 s");
            }
            std::thread::sleep(Duration::from_micros(100));
        }
        to_status.push(cut.elapsed().as_secs_f64() * 1e6);
        let event = latched.recv_timeout(Duration::from_secs(5))?;
        to_event.push(event.duration_since(cut).as_secs_f64() * 1e6);
        let (reply, answer) = tokio::sync::oneshot::channel();
        handle.send(CellCommand::Reset { reply })?;
        answer
            .blocking_recv()?
            .map_err(|reason| anyhow::anyhow!("the reset failed: {reason}"))?;
    }
    let (reply, _answer) = tokio::sync::oneshot::channel();
    let _ = handle.send(CellCommand::Shutdown { reply });
    let _ = thread.join();
    Ok(vec![
        Samples {
            name: "latch (controller lost to the cell's status)",
            micros: to_status,
        },
        Samples {
            name: "latch (controller lost to the latch event)",
            micros: to_event,
        },
    ])
}
