//! The drivers' latencies, measured on this machine against an in-process `celld twin-server`
//! on loopback (`celld latency`): a move's round trip (`MOV` to on-target confirmed and the
//! position read back), camera ingestion (an OpenIGTLink message's bytes to the estimate),
//! and the e-stop (the call to `STP` seen on the wire by a relay between the driver and the
//! controller, while the control thread keeps moving).

use super::gcs::{GcsRobot, GcsSettings};
use super::igtl::camera::FrameAssembler;
use super::igtl::codec::{HEADER_BYTES, Header, Message, Timestamp};
use super::twin_server::{TwinServer, TwinServerOptions, point_message};
use crate::camera::ingest::{Ingest, Shot};
use crate::config::cell::CellConfig;
use crate::geometry::{CellFrames, Move};
use crate::robot::Robot;
use crate::sim::InitialConditions;
use crate::sim::rig::TwinRig;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// Samples of one latency, in microseconds.
#[derive(Debug, Clone, PartialEq)]
pub struct Samples {
    pub name: &'static str,
    pub micros: Vec<f64>,
}

impl Samples {
    /// The `q` quantile (0..=1), µs; NaN without samples.
    pub fn quantile(&self, q: f64) -> f64 {
        let mut sorted = self.micros.clone();
        sorted.sort_by(f64::total_cmp);
        if sorted.is_empty() {
            return f64::NAN;
        }
        let rank = (q * (sorted.len() - 1) as f64).round() as usize;
        sorted[rank.min(sorted.len() - 1)]
    }
}

/// Ingestion's samples at a few lengths of its episode: the frames up to the length, the last
/// [`LENGTH_SAMPLES`] of them. The watch on Segment II weighs every frame of the episode, so
/// these show whether a frame costs more the longer the episode has run.
const EPISODE_LENGTHS: [(usize, &str); 3] = [
    (100, "  ingestion at frames 1-100 of the episode"),
    (1000, "  ingestion at frames 901-1000"),
    (5000, "  ingestion at frames 4901-5000"),
];
/// Frames timed at each of [`EPISODE_LENGTHS`].
const LENGTH_SAMPLES: usize = 100;

/// Measures the three latencies, `count` samples each (the e-stop's: `count / 10`, at least 1),
/// and ingestion's at each of [`EPISODE_LENGTHS`] that `count` reaches (ingestion's samples are
/// one episode's frames, in order).
pub fn measure(cell: &CellConfig, count: usize) -> anyhow::Result<Vec<Samples>> {
    let server = TwinServer::start(&TwinServerOptions::loopback(cell, 1))?;
    let settings = GcsSettings::default();
    let mut robot = GcsRobot::connect(&server.gcs.to_string(), settings, cell)?;
    let mut round_trip = Vec::with_capacity(count);
    for k in 0..count {
        let step = Move::translation(0.0, 0.0, if k % 2 == 0 { 0.01 } else { -0.01 });
        let start = Instant::now();
        robot.execute(&step)?;
        round_trip.push(start.elapsed().as_secs_f64() * 1e6);
    }
    let ingested = ingestion(cell, count)?;
    let by_length = by_episode_length(&ingested);
    let mut measured = vec![
        Samples {
            name: "move round trip (MOV to on target and POS?)",
            micros: round_trip,
        },
        Samples {
            name: "ingestion (POINT message to estimate)",
            micros: ingested,
        },
    ];
    measured.extend(by_length);
    measured.push(Samples {
        name: "e-stop (call to STP on the wire, while moving)",
        micros: estop(cell, &server, (count / 10).max(1))?,
    });
    Ok(measured)
}

/// One episode's ingestion samples, frame by frame, at each of [`EPISODE_LENGTHS`] they reach.
fn by_episode_length(micros: &[f64]) -> Vec<Samples> {
    EPISODE_LENGTHS
        .iter()
        .filter(|(length, _)| *length <= micros.len())
        .map(|&(length, name)| Samples {
            name,
            micros: micros[length - LENGTH_SAMPLES.min(length)..length].to_vec(),
        })
        .collect()
}

/// Message bytes to estimate: decode, frame, fit, fusion; the captures prepared beforehand.
fn ingestion(cell: &CellConfig, count: usize) -> anyhow::Result<Vec<f64>> {
    let frames = CellFrames::from_config(cell);
    let mut rig = TwinRig::new(cell);
    rig.begin_episode(2, InitialConditions::from_cell(cell))
        .expect("the reference episode starts");
    let now = Timestamp::now().as_secs_f64();
    let messages: Vec<Vec<u8>> = (0..count)
        .map(|k| {
            let stamp = Timestamp::from_secs_f64(now + k as f64 * 1e-3);
            point_message(rig.capture(), &frames, 2, 0, stamp).encode()
        })
        .collect();
    let mut assembler = FrameAssembler::new(&frames, u64::MAX / 2);
    let mut ingest = Ingest::new(cell, &frames);
    let mut micros = Vec::with_capacity(count);
    let mut fresh = 0;
    for (k, bytes) in messages.iter().enumerate() {
        let start = Instant::now();
        let header: &[u8; HEADER_BYTES] = bytes[..HEADER_BYTES].try_into().expect("a header");
        let message = Header::decode(header)
            .and_then(|header| Message::decode(&header, &bytes[HEADER_BYTES..]))
            .expect("a message this module wrote");
        let frame = assembler
            .take(&message, Timestamp::from_secs_f64(now))
            .expect("a fresh frame")
            .expect("a POINT message is a frame");
        let estimate = ingest.take(&Shot {
            new_episode: k == 0,
            forget_robot: false,
            executed: None,
            remaining: None,
            frame,
        });
        micros.push(start.elapsed().as_secs_f64() * 1e6);
        fresh += usize::from(estimate.fresh);
    }
    // Timing frames the estimator refused would time the refusal, not the fit.
    if fresh * 10 < count * 9 {
        anyhow::bail!("only {fresh} of {count} captures gave an estimate");
    }
    Ok(micros)
}

/// From the e-stop's call to `STP` passing a relay on its way to the controller, while the
/// control thread moves the platform back and forth.
fn estop(cell: &CellConfig, server: &TwinServer, count: usize) -> anyhow::Result<Vec<f64>> {
    let (relay, seen) = relay(server.gcs)?;
    let settings = GcsSettings::default();
    let mut robot = GcsRobot::connect(&relay.to_string(), settings, cell)?;
    let stop = robot.emergency_stop();
    let (go, pressed) = mpsc::channel::<()>();
    let (done, finished) = mpsc::channel::<Vec<f64>>();
    std::thread::spawn(move || {
        let mut micros = Vec::with_capacity(count);
        for _ in 0..count {
            std::thread::sleep(Duration::from_millis(3));
            while seen.try_recv().is_ok() {}
            let start = Instant::now();
            if !stop() {
                break;
            }
            let Ok(at) = seen.recv_timeout(Duration::from_secs(1)) else {
                break;
            };
            micros.push(at.saturating_duration_since(start).as_secs_f64() * 1e6);
        }
        let _ = go.send(());
        let _ = done.send(micros);
    });
    let mut k = 0;
    while pressed.try_recv().is_err() {
        let step = Move::translation(0.0, 0.0, if k % 2 == 0 { 0.01 } else { -0.01 });
        // A stop between MOV and its ERR? fails that move with error 10: expected here.
        let _ = robot.execute(&step);
        k += 1;
    }
    Ok(finished.recv()?)
}

/// A relay to `upstream` on a free loopback port; sends the instant each `STP` line from the
/// client passes it.
fn relay(upstream: SocketAddr) -> anyhow::Result<(SocketAddr, mpsc::Receiver<Instant>)> {
    let listener = TcpListener::bind("127.0.0.1:0")?;
    let address = listener.local_addr()?;
    let (seen, receiver) = mpsc::channel();
    std::thread::spawn(move || {
        let Ok((mut client, _)) = listener.accept() else {
            return;
        };
        let Ok(mut controller) = TcpStream::connect(upstream) else {
            return;
        };
        let _ = (client.set_nodelay(true), controller.set_nodelay(true));
        let (Ok(mut back_from), Ok(mut back_to)) = (controller.try_clone(), client.try_clone())
        else {
            return;
        };
        std::thread::spawn(move || std::io::copy(&mut back_from, &mut back_to));
        let mut chunk = [0u8; 1024];
        let mut line = Vec::new();
        loop {
            let n = match client.read(&mut chunk) {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            let at = Instant::now();
            for &byte in &chunk[..n] {
                if byte == b'\n' {
                    if line == b"STP" {
                        let _ = seen.send(at);
                    }
                    line.clear();
                } else {
                    line.push(byte);
                }
            }
            if controller.write_all(&chunk[..n]).is_err() {
                return;
            }
        }
    });
    Ok((address, receiver))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_latency_gets_its_samples() {
        let samples = measure(&CellConfig::reference(), 20).unwrap();
        let counts: Vec<usize> = samples.iter().map(|s| s.micros.len()).collect();
        assert_eq!(counts, [20, 20, 2]);
        for latency in &samples {
            let (p50, p99) = (latency.quantile(0.5), latency.quantile(0.99));
            assert!(p50.is_finite() && p50 > 0.0 && p99 >= p50, "{latency:?}");
        }
    }

    #[test]
    fn ingestion_is_read_at_the_episode_lengths_it_reaches() {
        let micros: Vec<f64> = (1..=1500).map(f64::from).collect();
        let lengths = by_episode_length(&micros);
        // Frames 1-100 and 901-1000 (the samples are the frames' numbers); 5000 not reached.
        let ranges: Vec<(f64, f64, usize)> = lengths
            .iter()
            .map(|s| (s.micros[0], s.quantile(1.0), s.micros.len()))
            .collect();
        assert_eq!(ranges, [(1.0, 100.0, 100), (901.0, 1000.0, 100)]);
        assert!(by_episode_length(&micros[..99]).is_empty());
    }

    #[test]
    fn quantiles_are_read_from_the_sorted_samples() {
        let samples = Samples {
            name: "x",
            micros: (1..=100).rev().map(f64::from).collect(),
        };
        assert_eq!(samples.quantile(0.0), 1.0);
        assert_eq!(samples.quantile(0.5), 51.0);
        assert_eq!(samples.quantile(0.99), 99.0);
        assert_eq!(samples.quantile(1.0), 100.0);
        assert!(
            Samples {
                name: "x",
                micros: vec![]
            }
            .quantile(0.5)
            .is_nan()
        );
    }
}
