//! The OpenIGTLink camera as a plant's camera or tracker behaves: a tracker that fits the
//! fixtures itself and sends their frames (TRANSFORM) estimates as the camera that sends its
//! points (POINT) does, without teaching ingestion a noise the points never had; a streaming
//! camera left running while the cell is idle gives its newest frame; fixture layouts come
//! from a calibration file. The peers: in-process servers and relays, and pyigtl (from PyPI)
//! as a streaming camera and as a tracker (without it, its test says so and passes; with `CI`
//! set, a missing one fails it).

// The tracker-relay job runner and its settings, shared with examples/camera_goals.rs.
#[path = "support/camera_jobs.rs"]
#[allow(dead_code)]
mod camera_jobs;
mod drivers_support;
#[path = "drivers_camera_peers/layouts.rs"]
mod layouts;

use assembly_cell::camera::ingest::{Detected, Estimate, Ingest, Shot};
use assembly_cell::camera::{CameraFrame, Fixture, FrameKind, StateEstimator};
use assembly_cell::cell::DriverBackend;
use assembly_cell::config::cell::CellConfig;
use assembly_cell::drivers::igtl::camera::{
    CameraSettings, FrameAssembler, IgtlCamera, read_message,
};
use assembly_cell::drivers::igtl::codec::{Content, Message, Timestamp};
use assembly_cell::drivers::twin_server::{TwinServer, TwinServerOptions, point_message};
use assembly_cell::geometry::fit::fit_frame;
use assembly_cell::geometry::{CellFrames, Pose};
use assembly_cell::sim::InitialConditions;
use assembly_cell::sim::rig::TwinRig;
use camera_jobs::{driver_settings, run_job};
use drivers_support::{python_has, script};
use nalgebra::Point3;
use std::io::{BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::process::{Command, Stdio};
use std::time::Duration;

/// What a tracker does with a capture: fits each fixture's frame to its points (leaving out,
/// one by one, points further than `reject_above_mm` from the fit, as the estimator does).
fn tracker_fit(
    frames: &CellFrames,
    capture: &CameraFrame,
    fixture: Fixture,
    reject_above_mm: f64,
) -> Pose {
    let layout = match fixture {
        Fixture::C1 => &frames.c1_points_mm,
        Fixture::C2 => &frames.c2_points_mm,
    };
    let (model, measured): (Vec<Point3<f64>>, Vec<Point3<f64>>) = capture
        .points
        .iter()
        .filter(|p| p.fixture == fixture)
        .map(|p| (layout[usize::from(p.id)], p.position_mm))
        .unzip();
    fit_frame(&model, &measured, reject_above_mm)
        .expect("a capture of the twin fits")
        .pose
}

/// A fixture's frame as a TRANSFORM message (the matrix's columns, then the translation).
fn transform_message(device: &str, pose: &Pose, timestamp: Timestamp) -> Message {
    let r = pose.rotation.to_rotation_matrix();
    let (m, t) = (r.matrix(), pose.translation.vector);
    let values = [
        m[(0, 0)],
        m[(1, 0)],
        m[(2, 0)],
        m[(0, 1)],
        m[(1, 1)],
        m[(2, 1)],
        m[(0, 2)],
        m[(1, 2)],
        m[(2, 2)],
        t.x,
        t.y,
        t.z,
    ];
    Message {
        version: 2,
        device: device.into(),
        timestamp,
        message_id: 0,
        content: Content::Transform(values.map(|v| v as f32)),
    }
}

/// The tracker's two messages for a capture, with the capture's timestamp.
fn tracker_messages(
    frames: &CellFrames,
    capture: &CameraFrame,
    reject_above_mm: f64,
    timestamp: Timestamp,
) -> [Message; 2] {
    [Fixture::C1, Fixture::C2].map(|fixture| {
        let pose = tracker_fit(frames, capture, fixture, reject_above_mm);
        transform_message(&fixture.to_string(), &pose, timestamp)
    })
}

/// Frames a sequence of messages completes.
fn assembled(assembler: &mut FrameAssembler, messages: &[Message]) -> Vec<CameraFrame> {
    messages
        .iter()
        .filter_map(|message| {
            assembler
                .take(message, message.timestamp)
                .expect("a message the assembler takes")
        })
        .collect()
}

fn take(ingest: &mut Ingest, frame: CameraFrame, first: bool) -> Estimate {
    ingest.take(&Shot {
        new_episode: first,
        frame,
        ..Shot::default()
    })
}

/// What one path made of a still scene's captures.
struct Run {
    estimates: Vec<Estimate>,
    /// The filter's joint NEES against the twin's truth after the last frame.
    final_nees: f64,
}

fn ingest_all(cell: &CellConfig, frames: &[CameraFrame], truth: &Pose) -> Run {
    let mut ingest = Ingest::new(cell, &CellFrames::from_config(cell));
    let estimates: Vec<Estimate> = frames
        .iter()
        .enumerate()
        .map(|(k, frame)| take(&mut ingest, frame.clone(), k == 0))
        .collect();
    let last = estimates.last().expect("frames");
    Run {
        final_nees: last.filter.joint_nees(truth).expect("an estimate"),
        estimates,
    }
}

fn shifts(path: &Run) -> usize {
    path.estimates
        .iter()
        .filter(|e| {
            matches!(
                e.detected,
                Some(Detected::CameraShift | Detected::ShiftSuspected)
            )
        })
        .count()
}

/// The captures as the POINT camera sends them, assembled into frames.
fn point_frames(cell: &CellConfig, captures: &[CameraFrame]) -> Vec<CameraFrame> {
    let frames = CellFrames::from_config(cell);
    let mut assembler = FrameAssembler::new(&frames, u64::MAX / 2);
    captures
        .iter()
        .enumerate()
        .flat_map(|(k, capture)| {
            let message = point_message(capture, &frames, 2, 0, stamp(k));
            assembled(&mut assembler, &[message])
        })
        .collect()
}

/// The captures as a tracker sends them (`tracker`: its messages for a capture at a time),
/// assembled into frames.
fn fitted_frames(
    cell: &CellConfig,
    captures: &[CameraFrame],
    tracker: impl Fn(&CameraFrame, Timestamp) -> [Message; 2],
) -> Vec<CameraFrame> {
    let mut assembler = FrameAssembler::new(&CellFrames::from_config(cell), u64::MAX / 2);
    captures
        .iter()
        .enumerate()
        .flat_map(|(k, capture)| assembled(&mut assembler, &tracker(capture, stamp(k))))
        .collect()
}

/// The timestamp of capture `k` (4 Hz).
fn stamp(k: usize) -> Timestamp {
    Timestamp::from_secs_f64(1000.0 + k as f64 * 0.25)
}

/// `count` captures of the twin's still scene (episode `seed`), and the truth of {F} in {M}.
fn still_captures(cell: &CellConfig, seed: u64, count: usize) -> (Vec<CameraFrame>, Pose) {
    let mut rig = TwinRig::new(cell);
    rig.begin_episode(seed, InitialConditions::from_cell(cell))
        .unwrap();
    let captures = (0..count).map(|_| rig.capture().clone()).collect();
    (captures, rig.true_f_m().inverse())
}

/// Per component of the state, the RMS over frames of the two paths' difference and the
/// spread (standard deviation) of the POINT path's own frames.
fn difference_and_spread(a: &Run, b: &Run) -> Vec<(f64, f64)> {
    let n = a.estimates.len() as f64;
    (0..12)
        .map(|i| {
            let mean = a.estimates.iter().map(|e| e.raw_state[i]).sum::<f64>() / n;
            let spread = (a
                .estimates
                .iter()
                .map(|e| (e.raw_state[i] - mean).powi(2))
                .sum::<f64>()
                / (n - 1.0))
                .sqrt();
            let difference = (a
                .estimates
                .iter()
                .zip(&b.estimates)
                .map(|(x, y)| (x.raw_state[i] - y.raw_state[i]).powi(2))
                .sum::<f64>()
                / n)
                .sqrt();
            (difference, spread)
        })
        .collect()
}

/// A tracker's frames against the POINT camera's on the same captures: the held-to standard.
fn holds_to_the_point_path(
    cell: &CellConfig,
    by_points: &[CameraFrame],
    by_fits: &[CameraFrame],
    truth: &Pose,
) {
    assert_eq!(by_points.len(), by_fits.len());
    assert!(by_fits.iter().all(|f| f.kind
        == FrameKind::Fitted {
            variance_factor: 1.0
        }));
    let points = ingest_all(cell, by_points, truth);
    let fits = ingest_all(cell, by_fits, truth);
    // No frame of the still scene reads as a shift, on either path.
    assert_eq!(shifts(&points), 0);
    assert_eq!(shifts(&fits), 0);
    let fresh = fits.estimates.iter().filter(|e| e.fresh).count();
    assert!(fresh + 2 >= fits.estimates.len(), "{fresh} fresh");
    // The points' residuals show the camera as its data sheet says (the twin's noise scale
    // 1); the tracker's fits are taken at that noise, not at the zero their rebuilt points show.
    let learned = points.estimates.last().unwrap().filter.noise_scale();
    assert!((0.85..1.15).contains(&learned), "{learned}");
    assert_eq!(fits.estimates.last().unwrap().filter.noise_scale(), 1.0);
    // Frame by frame the two agree to well within the frames' own scatter.
    for (i, (difference, spread)) in difference_and_spread(&points, &fits).iter().enumerate() {
        assert!(
            *difference < 0.2 * spread,
            "state {i}: the paths differ by {difference} RMS, the frames scatter by {spread}"
        );
    }
    // Both fused estimates are consistent with the truth: the joint NEES (χ², 6 degrees of
    // freedom) under its 0.999 quantile, 22.5.
    assert!(points.final_nees < 22.5, "{}", points.final_nees);
    assert!(fits.final_nees < 22.5, "{}", fits.final_nees);
}

#[test]
fn a_tracker_fed_the_twins_points_estimates_as_the_point_camera_does() {
    let cell = CellConfig::reference();
    let frames = CellFrames::from_config(&cell);
    let threshold = StateEstimator::new(&cell, &frames).rejection_threshold_mm();
    for seed in [3, 11] {
        let (captures, truth) = still_captures(&cell, seed, 200);
        let by_points = point_frames(&cell, &captures);
        let by_fits = fitted_frames(&cell, &captures, |capture, at| {
            tracker_messages(&frames, capture, threshold, at)
        });
        holds_to_the_point_path(&cell, &by_points, &by_fits, &truth);
        // The root of the fault this guards against: the same fitted frames taken as
        // measured points teach a camera several times quieter than it is.
        let measured: Vec<CameraFrame> = by_fits
            .iter()
            .map(|f| CameraFrame {
                kind: FrameKind::Measured,
                ..f.clone()
            })
            .collect();
        let naive = ingest_all(&cell, &measured, &truth);
        let learned = naive.estimates.last().unwrap().filter.noise_scale();
        assert!(learned < 0.5, "{learned}");
    }
}

/// A tracker in front of `upstream` (a triggered POINT camera): queries go through; each
/// POINT message becomes the tracker's two TRANSFORM messages, with its timestamp.
fn tracker_relay(upstream: SocketAddr, frames: CellFrames, reject_above_mm: f64) -> SocketAddr {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let address = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        for client in listener.incoming() {
            let Ok(mut client) = client else { return };
            let Ok(camera) = TcpStream::connect(upstream) else {
                return;
            };
            let mut queries = client.try_clone().unwrap();
            let mut to_camera = camera.try_clone().unwrap();
            std::thread::spawn(move || std::io::copy(&mut queries, &mut to_camera));
            let frames = frames.clone();
            std::thread::spawn(move || {
                let mut camera = camera;
                let mut assembler = FrameAssembler::new(&frames, u64::MAX / 2);
                let mut body = Vec::new();
                while let Ok(message) = read_message(&mut camera, &mut body) {
                    let Ok(Some(capture)) = assembler.take(&message, message.timestamp) else {
                        continue;
                    };
                    let bytes: Vec<u8> =
                        tracker_messages(&frames, &capture, reject_above_mm, message.timestamp)
                            .iter()
                            .flat_map(Message::encode)
                            .collect();
                    if client.write_all(&bytes).is_err() {
                        return;
                    }
                }
            });
        }
    });
    address
}

#[test]
fn jobs_through_a_tracker_end_as_through_the_point_camera() {
    // The integrator's case: a tracker's TRANSFORMs, one per fixture per capture, fitted at
    // the cell's noise. Six jobs end as the POINT camera's do, and none names a shift.
    let cell = CellConfig::reference();
    let frames = CellFrames::from_config(&cell);
    let threshold = StateEstimator::new(&cell, &frames).rejection_threshold_mm();
    let server = TwinServer::start(&TwinServerOptions::loopback(&cell, 0)).unwrap();
    let tracker = tracker_relay(server.igtl, frames, threshold);
    let mut by_points =
        DriverBackend::connect(&cell, driver_settings(server.igtl, server.gcs, true), None)
            .unwrap();
    let mut by_fits =
        DriverBackend::connect(&cell, driver_settings(tracker, server.gcs, true), None).unwrap();
    for seed in 1..=6 {
        let (expected, _) = run_job(seed, &cell, &mut by_points).unwrap();
        let (got, detected) = run_job(seed, &cell, &mut by_fits).unwrap();
        assert!(
            !detected.iter().any(|d| d.starts_with("camera_shift")),
            "seed {seed}: {detected:?}"
        );
        assert_eq!(
            (got.status, &got.failure_reason),
            (expected.status, &expected.failure_reason),
            "seed {seed}: {detected:?}"
        );
    }
}

/// A pyigtl peer script's port, from its first line `port N`.
fn peer_port(child: &mut std::process::Child) -> u16 {
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    line.trim()
        .strip_prefix("port ")
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("{line}"))
}

fn points_json(frame: &CameraFrame) -> serde_json::Value {
    frame
        .points
        .iter()
        .map(|p| {
            serde_json::json!([
                p.fixture.to_string(),
                p.id.to_string(),
                [p.position_mm.x, p.position_mm.y, p.position_mm.z]
            ])
        })
        .collect()
}

/// Kills a peer script left running when the test ends, however it ends.
struct Peer(std::process::Child);

impl Drop for Peer {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn pyigtl_as_a_streaming_camera_gives_fresh_frames_after_an_idle_spell() {
    if !python_has("pyigtl", "pyigtl") {
        return;
    }
    let cell = CellConfig::reference();
    let frames = CellFrames::from_config(&cell);
    let (captures, _) = still_captures(&cell, 6, 20);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("captures.json");
    let json: Vec<serde_json::Value> = captures.iter().map(points_json).collect();
    std::fs::write(&path, serde_json::Value::from(json).to_string()).unwrap();
    let mut child = Command::new("python3")
        .arg(script("pyigtl_streamer.py"))
        .arg(&path)
        .arg("30")
        .stdout(Stdio::piped())
        .spawn()
        .expect("run python3");
    let port = peer_port(&mut child);
    let _peer = Peer(child);
    let settings = CameraSettings {
        triggered: false,
        frame_timeout_ms: 2000,
        max_age_ms: 1000,
        ..CameraSettings::default()
    };
    let mut camera = IgtlCamera::connect(&format!("127.0.0.1:{port}"), settings, &frames).unwrap();
    let mut ingest = Ingest::new(&cell, &frames);
    // Three jobs' worth of captures, each after the cell sat idle three seconds while the
    // camera streamed at 30 Hz (90 frames queued, most older than the limit).
    let mut last = 0;
    for episode in 0..3 {
        std::thread::sleep(Duration::from_secs(3));
        for step in 0..4 {
            let frame = camera
                .capture()
                .unwrap_or_else(|e| panic!("episode {episode}, capture {step}: {e}"));
            assert!(frame.sequence > last);
            last = frame.sequence;
            assert!(take(&mut ingest, frame, step == 0).fresh);
            std::thread::sleep(Duration::from_millis(250));
        }
    }
}

#[test]
fn pyigtl_as_a_tracker_estimates_as_the_point_camera_does() {
    if !python_has("pyigtl", "pyigtl") || !python_has("numpy", "numpy") {
        return;
    }
    let cell = CellConfig::reference();
    let frames = CellFrames::from_config(&cell);
    let threshold = StateEstimator::new(&cell, &frames).rejection_threshold_mm();
    let (captures, truth) = still_captures(&cell, 8, 120);
    let layout = |points: &[Point3<f64>]| -> serde_json::Value {
        points.iter().map(|p| vec![p.x, p.y, p.z]).collect()
    };
    let t0 = Timestamp::now().as_secs_f64();
    let spec = serde_json::json!({
        "layout": {"C1": layout(&frames.c1_points_mm), "C2": layout(&frames.c2_points_mm)},
        "reject_above_mm": threshold,
        "captures": captures.iter().enumerate().map(|(k, c)| serde_json::json!({
            "timestamp": t0 + k as f64 * 0.25, "points": points_json(c)})).collect::<Vec<_>>(),
    });
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tracker.json");
    std::fs::write(&path, spec.to_string()).unwrap();
    let mut child = Command::new("python3")
        .arg(script("pyigtl_tracker.py"))
        .arg(&path)
        .stdout(Stdio::piped())
        .spawn()
        .expect("run python3");
    let port = peer_port(&mut child);
    let _peer = Peer(child);
    let mut stream = TcpStream::connect(("127.0.0.1", port)).unwrap();
    let mut assembler = FrameAssembler::new(&frames, 600_000);
    let mut by_fits = Vec::new();
    let mut body = Vec::new();
    while by_fits.len() < captures.len() {
        let message = read_message(&mut stream, &mut body).expect("a message pyigtl wrote");
        assert_eq!(message.content.kind(), "TRANSFORM");
        by_fits.extend(assembler.take(&message, Timestamp::now()).unwrap());
    }
    let by_points = point_frames(&cell, &captures);
    holds_to_the_point_path(&cell, &by_points, &by_fits, &truth);
}
