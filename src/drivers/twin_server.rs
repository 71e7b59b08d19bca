//! The twin as a cell's hardware on the network: its platform behind a GCS 2.0 controller
//! ([`TwinController`]) and its camera behind an OpenIGTLink server, for `celld twin-server`.
//! std TCP and one thread per connection.
//!
//! The camera captures when asked (`GET_POINT`) and answers with one POINT message of the
//! coded points it decoded; with a stream rate it also sends a capture at that rate to every
//! client. Both sides share one twin and one clock (seconds since the start), so a capture
//! sees the platform where it is, mid-move too.

use super::gcs::twin::TwinController;
use super::igtl::codec::{Content, HEADER_BYTES, Header, Message, PointElement, Timestamp};
use crate::camera::{CameraFrame, Fixture};
use crate::config::cell::CellConfig;
use crate::geometry::CellFrames;
use crate::sim::rig::TwinRig;
use crate::sim::{CELL_ROBOT_SEED, InitialConditions};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

/// What `celld twin-server` is asked to be.
#[derive(Debug, Clone)]
pub struct TwinServerOptions {
    pub cell: CellConfig,
    /// The episode's seed.
    pub seed: u64,
    /// Where the GCS controller listens (port 0: any free one).
    pub gcs: SocketAddr,
    /// Where the OpenIGTLink camera listens (port 0: any free one).
    pub igtl: SocketAddr,
    /// Start referenced with the servos on (as after an integrator's setup), or as after
    /// power-on.
    pub ready: bool,
    /// Captures streamed to each camera client per second (0: only on `GET_POINT`), Hz.
    pub stream_hz: f64,
    /// The header version of the POINT messages sent (1 or 2).
    pub igtl_version: u16,
    /// Moves arrive at once (`ONT?` 1 right after `MOV`) instead of taking the time the
    /// cell's speeds give them.
    pub instant_moves: bool,
}

impl TwinServerOptions {
    /// `cell`'s twin on free loopback ports, drawing episode `seed`: ready (referenced, servos
    /// on), moves arriving at once, answering captures on `GET_POINT` only, in header version
    /// 2. What the in-process uses (`celld latency`, the tests) want.
    pub fn loopback(cell: &CellConfig, seed: u64) -> Self {
        let any = SocketAddr::from(([127, 0, 0, 1], 0));
        TwinServerOptions {
            cell: cell.clone(),
            seed,
            gcs: any,
            igtl: any,
            ready: true,
            stream_hz: 0.0,
            igtl_version: 2,
            instant_moves: true,
        }
    }
}

/// The twin both servers drive, and their clock.
struct Twin {
    rig: TwinRig,
    controller: TwinController,
    start: Instant,
}

impl Twin {
    /// Seconds since the servers started: the controller's time.
    fn now_s(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    /// One capture of the scene with the platform where it is now.
    fn capture(&mut self) -> CameraFrame {
        let now_s = self.now_s();
        self.controller.place(&mut self.rig, now_s);
        self.rig.capture().clone()
    }
}

type Shared = Arc<Mutex<Twin>>;

fn lock(twin: &Shared) -> std::sync::MutexGuard<'_, Twin> {
    twin.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The running servers: their addresses. They run until the process ends.
pub struct TwinServer {
    pub gcs: SocketAddr,
    pub igtl: SocketAddr,
    twin: Shared,
}

impl TwinServer {
    /// Starts the episode of `options.seed` and both servers.
    pub fn start(options: &TwinServerOptions) -> anyhow::Result<TwinServer> {
        if !(options.stream_hz.is_finite() && options.stream_hz >= 0.0) {
            anyhow::bail!(
                "the camera stream rate must be a finite number ≥ 0 Hz, got {}",
                options.stream_hz
            );
        }
        if !(1..=2).contains(&options.igtl_version) {
            anyhow::bail!(
                "the OpenIGTLink header version must be 1 or 2, got {}",
                options.igtl_version
            );
        }
        // One cell, one robot, kept from job to job as the service's own twin keeps it.
        let mut rig = TwinRig::new(&options.cell).with_kept_robot(CELL_ROBOT_SEED);
        rig.begin_episode(options.seed, InitialConditions::from_cell(&options.cell))
            .map_err(|e| anyhow::anyhow!("the episode's initial pose is unreachable: {e}"))?;
        let controller =
            TwinController::new(&rig, options.ready).with_instant_moves(options.instant_moves);
        let twin = Arc::new(Mutex::new(Twin {
            rig,
            controller,
            start: Instant::now(),
        }));
        let gcs = TcpListener::bind(options.gcs)
            .map_err(|e| anyhow::anyhow!("cannot listen on {} (GCS): {e}", options.gcs))?;
        let igtl = TcpListener::bind(options.igtl)
            .map_err(|e| anyhow::anyhow!("cannot listen on {} (OpenIGTLink): {e}", options.igtl))?;
        let server = TwinServer {
            gcs: gcs.local_addr()?,
            igtl: igtl.local_addr()?,
            twin: twin.clone(),
        };
        let shared = twin.clone();
        spawn("celld-gcs", move || {
            accept(gcs, shared, |stream, twin| serve_gcs(stream, &twin))
        });
        let camera = CameraSide {
            stream_hz: options.stream_hz,
            version: options.igtl_version,
        };
        spawn("celld-igtl", move || {
            accept(igtl, twin, move |stream, twin| camera.serve(stream, &twin))
        });
        Ok(server)
    }
}

impl TwinServer {
    /// The true pose of {M} in {F} now (the twin's ground truth, which no client can ask for).
    pub fn true_f_m(&self) -> crate::geometry::Pose {
        lock(&self.twin).rig.true_f_m()
    }

    /// The moves the controller accepted (`MOV`, `MVR`), oldest first: when each arrived and
    /// its target X Y Z (mm) U V W (deg). The last 4096 are kept.
    pub fn moves_started(&self) -> Vec<(Instant, [f64; 6])> {
        let twin = lock(&self.twin);
        twin.controller
            .moves_started()
            .map(|&(at_s, target)| (twin.start + Duration::from_secs_f64(at_s), target))
            .collect()
    }
}

fn spawn(name: &str, work: impl FnOnce() + Send + 'static) {
    std::thread::Builder::new()
        .name(name.into())
        .spawn(work)
        .expect("spawn a twin-server thread");
}

fn accept(
    listener: TcpListener,
    twin: Shared,
    serve: impl Fn(TcpStream, Shared) + Clone + Send + 'static,
) {
    for stream in listener.incoming() {
        let Ok(stream) = stream else { continue };
        let _ = stream.set_nodelay(true);
        let (twin, serve) = (twin.clone(), serve.clone());
        spawn("celld-twin-conn", move || serve(stream, twin));
    }
}

/// Whether `byte` is a single-character command (`#4`, `#5`, `#7`, `#24`, …): any control
/// character but the line's own LF, CR and TAB. It acts at once, even within a line.
fn single_character(byte: u8) -> bool {
    byte < 32 && !matches!(byte, b'\n' | b'\r' | b'\t')
}

/// One GCS connection: single control characters act at once; other commands end at LF.
fn serve_gcs(mut stream: TcpStream, twin: &Shared) {
    let mut line = Vec::with_capacity(128);
    let mut chunk = [0u8; 1024];
    loop {
        let n = match stream.read(&mut chunk) {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        for &byte in &chunk[..n] {
            let answer = if single_character(byte) {
                let mut guard = lock(twin);
                let now_s = guard.now_s();
                let Twin {
                    rig, controller, ..
                } = &mut *guard;
                controller.handle_char(byte, rig, now_s)
            } else if byte == b'\n' {
                let text = String::from_utf8_lossy(&line).into_owned();
                line.clear();
                let mut guard = lock(twin);
                let now_s = guard.now_s();
                let Twin {
                    rig, controller, ..
                } = &mut *guard;
                controller
                    .handle(text.trim_end_matches('\r'), rig, now_s)
                    .map(String::into_bytes)
            } else {
                line.push(byte);
                None
            };
            if let Some(answer) = answer
                && stream.write_all(&answer).is_err()
            {
                return;
            }
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct CameraSide {
    stream_hz: f64,
    version: u16,
}

impl CameraSide {
    /// One camera connection: answers each `GET_POINT` with a capture; streams captures when
    /// a rate is set.
    fn serve(self, stream: TcpStream, twin: &Shared) {
        let Ok(writer) = stream.try_clone() else {
            return;
        };
        let writer = Arc::new(Mutex::new(writer));
        if self.stream_hz > 0.0 {
            let (twin, writer) = (twin.clone(), writer.clone());
            let period = Duration::from_secs_f64(1.0 / self.stream_hz);
            spawn("celld-igtl-stream", move || {
                loop {
                    std::thread::sleep(period);
                    if !self.send_capture(&twin, &writer, 0) {
                        return;
                    }
                }
            });
        }
        let mut reader = stream;
        let mut header = [0u8; HEADER_BYTES];
        let mut body = Vec::new();
        loop {
            if reader.read_exact(&mut header).is_err() {
                return;
            }
            let Ok(parsed) = Header::decode(&header) else {
                return;
            };
            body.resize(parsed.body_size as usize, 0);
            if reader.read_exact(&mut body).is_err() {
                return;
            }
            let asked = match Message::decode(&parsed, &body) {
                Ok(Message {
                    content: Content::Query(kind),
                    message_id,
                    ..
                }) if kind == "GET_POINT" => Some(message_id),
                _ => None,
            };
            if let Some(message_id) = asked
                && !self.send_capture(twin, &writer, message_id)
            {
                return;
            }
        }
    }

    /// Captures and sends one POINT message; false once the client is gone.
    fn send_capture(&self, twin: &Shared, writer: &Mutex<TcpStream>, message_id: u32) -> bool {
        let message = {
            let mut twin = lock(twin);
            let frame = twin.capture();
            point_message(
                &frame,
                twin.rig.frames(),
                self.version,
                message_id,
                Timestamp::now(),
            )
        };
        writer
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .write_all(&message.encode())
            .is_ok()
    }
}

/// A capture as a POINT message: group `C1`/`C2`, name the point's label in its fixture's
/// layout (`frames`), position in mm.
pub fn point_message(
    frame: &CameraFrame,
    frames: &CellFrames,
    version: u16,
    message_id: u32,
    timestamp: Timestamp,
) -> Message {
    let points = frame
        .points
        .iter()
        .map(|point| PointElement {
            name: label_of(frames, point.fixture, point.id).to_string(),
            group: match point.fixture {
                Fixture::C1 => "C1".into(),
                Fixture::C2 => "C2".into(),
            },
            rgba: [255, 255, 255, 255],
            position: point.position_mm.coords.map(|v| v as f32).into(),
            diameter: 0.0,
            owner: String::new(),
        })
        .collect();
    Message {
        version,
        device: "camera".into(),
        timestamp,
        message_id,
        content: Content::Point(points),
    }
}

/// The label a camera names point `index` of `fixture` by (the index itself past the layout).
fn label_of(frames: &CellFrames, fixture: Fixture, index: u16) -> u16 {
    let labels = match fixture {
        Fixture::C1 => &frames.c1_labels,
        Fixture::C2 => &frames.c2_labels,
    };
    labels.get(usize::from(index)).copied().unwrap_or(index)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drivers::gcs::protocol::{AXES, axis_values};
    use crate::drivers::gcs::twin::STOP_CHAR;
    use std::io::{BufRead, BufReader};

    /// Sends `lines`; the answer, all its lines (each but the last ends with a space).
    fn ask(reader: &mut BufReader<TcpStream>, writer: &mut TcpStream, lines: &str) -> String {
        writer.write_all(lines.as_bytes()).unwrap();
        let mut answer = String::new();
        while reader.read_line(&mut answer).unwrap() > 0 && answer.ends_with(" \n") {}
        answer
    }

    #[test]
    fn a_timed_move_is_logged_with_its_instant_and_a_stop_leaves_the_platform_part_way() {
        let options = TwinServerOptions {
            instant_moves: false,
            ..TwinServerOptions::loopback(&CellConfig::reference(), 2)
        };
        let server = TwinServer::start(&options).unwrap();
        let mut writer = TcpStream::connect(server.gcs).unwrap();
        let mut reader = BufReader::new(writer.try_clone().unwrap());
        let start = axis_values(&ask(&mut reader, &mut writer, "POS? Z\n"), &["Z"]).unwrap()[0];
        let before = Instant::now();
        // 20 mm at 1 mm/s: it runs until stopped.
        assert_eq!(ask(&mut reader, &mut writer, "VLS 1\nERR?\n"), "0\n");
        let z = start + 20.0;
        assert_eq!(
            ask(&mut reader, &mut writer, &format!("MOV Z {z}\nERR?\n")),
            "0\n"
        );
        let after = Instant::now();
        let moves = server.moves_started();
        assert_eq!(moves.len(), 1);
        assert!(before <= moves[0].0 && moves[0].0 <= after);
        assert_eq!(moves[0].1[2], z);
        writer.write_all(&[STOP_CHAR]).unwrap();
        assert_eq!(ask(&mut reader, &mut writer, "ERR?\n"), "10\n");
        // The platform stopped part way; the rig, and a capture, are there.
        let answer = ask(&mut reader, &mut writer, "POS?\n");
        let stopped = axis_values(&answer, &AXES).unwrap();
        assert!(start < stopped[2] && stopped[2] < z, "{answer}");
        let frame = lock(&server.twin).capture();
        assert!(!frame.points.is_empty());
        let setpoint = lock(&server.twin).rig.setpoint();
        assert!((setpoint.translation.z - stopped[2]).abs() < 1e-9);
    }
}
