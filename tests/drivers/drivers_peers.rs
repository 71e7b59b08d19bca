//! The drivers against libraries no one here wrote (both from PyPI): PIPython, PI's own GCS
//! library, drives `celld twin-server` as it would a PI hexapod controller; pyigtl receives
//! the twin-server's camera and sends POINT and TRANSFORM messages to celld's camera driver.
//!
//! `.ci/run` installs both. Elsewhere, without one, its test says so and passes; with `CI`
//! set, a missing one fails it.

use crate::drivers_support;

use assembly_cell::camera::ingest::{Ingest, Shot};
use assembly_cell::camera::{CameraFrame, CodedPoint, Fixture};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::drivers::igtl::camera::{FrameAssembler, read_message};
use assembly_cell::drivers::igtl::codec::Timestamp;
use assembly_cell::geometry::{CellFrames, Pose};
use assembly_cell::sim::InitialConditions;
use assembly_cell::sim::rig::TwinRig;
use drivers_support::{TwinServer, python_has, script};
use nalgebra::Point3;
use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::process::{Command, Stdio};

/// PIPython's helpers (`pitools.startup`, `moveandwait`, `waitontarget`) and a user's script
/// against the twin-server as after power-on, its moves taking time: every command PIPython
/// sends is answered within PIPython's own timeout.
#[test]
fn pipython_drives_the_twin_server_as_a_pi_hexapod_controller() {
    if !python_has("pipython", "PIPython") {
        return;
    }
    let server = TwinServer::start(&["--unreferenced", "--seed", "3"]);
    let output = Command::new("python3")
        .arg(script("pipython_peer.py"))
        .arg(server.gcs.port().to_string())
        .output()
        .expect("run python3");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success() && stdout.trim_end().ends_with("ok"),
        "PIPython found problems:\n{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

/// A frame from the JSON a peer script prints or reads: `[[group, name, [x, y, z]], ...]`.
fn frame_of(points: &serde_json::Value) -> CameraFrame {
    let points = points
        .as_array()
        .expect("points")
        .iter()
        .map(|point| {
            let fixture = match point[0].as_str() {
                Some("C1") => Fixture::C1,
                Some("C2") => Fixture::C2,
                other => panic!("group {other:?}"),
            };
            let id = point[1].as_str().expect("name").parse().expect("an index");
            let xyz: Vec<f64> = (0..3).map(|k| point[2][k].as_f64().unwrap()).collect();
            CodedPoint {
                fixture,
                id,
                position_mm: Point3::new(xyz[0], xyz[1], xyz[2]),
            }
        })
        .collect();
    CameraFrame {
        points,
        sequence: 1,
        ..CameraFrame::default()
    }
}

fn ingest_first(cell: &CellConfig, frame: CameraFrame) -> assembly_cell::camera::ingest::Estimate {
    let mut ingest = Ingest::new(cell, &CellFrames::from_config(cell));
    ingest.take(&Shot {
        new_episode: true,
        frame,
        ..Shot::default()
    })
}

#[test]
fn pyigtl_receives_the_twin_servers_captures_in_both_header_versions() {
    if !python_has("pyigtl", "pyigtl") {
        return;
    }
    let cell = CellConfig::reference();
    for version in ["1", "2"] {
        let server = TwinServer::start(&[
            "--seed",
            "5",
            "--camera-stream-hz",
            "40",
            "--igtl-version",
            version,
        ]);
        let output = Command::new("python3")
            .arg(script("pyigtl_receiver.py"))
            .arg(server.igtl.port().to_string())
            .arg("3")
            .output()
            .expect("run python3");
        let stdout = String::from_utf8_lossy(&output.stdout);
        assert!(
            output.status.success(),
            "pyigtl could not receive:\n{stdout}\n{}",
            String::from_utf8_lossy(&output.stderr)
        );
        let messages: Vec<serde_json::Value> = stdout
            .lines()
            .map(|line| serde_json::from_str(line).expect("a JSON line"))
            .collect();
        assert_eq!(messages.len(), 3, "{stdout}");
        let mut last_timestamp = 0.0;
        for message in &messages {
            assert_eq!(message["version"].to_string(), version, "{message}");
            assert_eq!(message["device"], "camera");
            let timestamp = message["timestamp"].as_f64().unwrap();
            assert!(timestamp > last_timestamp, "{stdout}");
            last_timestamp = timestamp;
            // What pyigtl decoded is a capture the estimator can use.
            let frame = frame_of(&message["points"]);
            assert!(frame.points.len() >= 10, "{message}");
            let estimate = ingest_first(&cell, frame);
            assert!(estimate.fresh, "{message}");
        }
    }
}

/// One capture of the twin, as the camera decoded it.
fn twin_capture(cell: &CellConfig, seed: u64) -> CameraFrame {
    let mut rig = TwinRig::new(cell);
    rig.begin_episode(seed, InitialConditions::from_cell(cell))
        .unwrap();
    rig.capture().clone()
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

fn matrix_json(pose: &Pose) -> serde_json::Value {
    let m = pose.to_homogeneous();
    (0..4)
        .map(|r| (0..4).map(|c| m[(r, c)]).collect::<Vec<f64>>())
        .collect()
}

#[test]
fn pyigtl_sends_points_and_transforms_that_become_frames_in_order() {
    if !python_has("pyigtl", "pyigtl") {
        return;
    }
    let cell = CellConfig::reference();
    let frames = CellFrames::from_config(&cell);
    let capture = twin_capture(&cell, 9);
    let c1 = Pose::translation(5.0, -40.0, 1800.0);
    let c2 = Pose::translation(0.0, 30.0, 2000.0);
    let t0 = Timestamp::now().as_secs_f64();
    let point = |version: u16, at: f64| {
        serde_json::json!({"type": "POINT", "version": version, "device": "camera",
            "timestamp": at, "points": points_json(&capture)})
    };
    let transform = |device: &str, pose: &Pose, at: f64| {
        serde_json::json!({"type": "TRANSFORM", "version": 2, "device": device,
            "timestamp": at, "message_id": 7, "matrix": matrix_json(pose)})
    };
    let specs = serde_json::json!([
        point(1, t0),
        point(2, t0 + 0.25),
        transform("C1", &c1, t0 + 0.5),
        transform("C2", &c2, t0 + 0.5),
        // A new capture, the same capture again, then one older than the last.
        point(2, t0 + 0.75),
        point(2, t0 + 0.75),
        point(1, t0),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("messages.json");
    std::fs::write(&path, specs.to_string()).unwrap();
    let mut sender = Command::new("python3")
        .arg(script("pyigtl_sender.py"))
        .arg(&path)
        .stdout(Stdio::piped())
        .spawn()
        .expect("run python3");
    let mut lines = BufReader::new(sender.stdout.take().unwrap()).lines();
    let first = lines.next().expect("a first line").unwrap();
    let port: u16 = first
        .strip_prefix("port ")
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("{first}"));
    let mut stream = TcpStream::connect(("127.0.0.1", port)).unwrap();
    // The staleness limit is the driver's business and its unit tests'; here, a minute.
    let mut assembler = FrameAssembler::new(&frames, 60_000);
    let mut received = Vec::new();
    let mut body = Vec::new();
    while received.len() < 6 {
        let message = read_message(&mut stream, &mut body).expect("a message pyigtl wrote");
        if let Some(frame) = assembler.take(&message, Timestamp::now()).unwrap() {
            received.push((message.version, frame));
        }
    }
    drop(stream);
    let status = sender.wait().unwrap();
    assert!(status.success());

    let sequences: Vec<u64> = received.iter().map(|(_, f)| f.sequence).collect();
    assert_eq!(sequences, [1, 2, 3, 4, 4, 3], "new ×4, repeated, older");
    let versions: Vec<u16> = received.iter().map(|(v, _)| *v).collect();
    assert_eq!(versions, [1, 2, 2, 2, 2, 1]);
    // The points arrive as pyigtl writes them, in f32: within 1e-3 mm at 2 m.
    for (_, frame) in [&received[0], &received[1]] {
        assert_eq!(frame.points.len(), capture.points.len());
        for (got, sent) in frame.points.iter().zip(&capture.points) {
            assert_eq!((got.fixture, got.id), (sent.fixture, sent.id));
            assert!((got.position_mm - sent.position_mm).norm() < 1e-3);
        }
    }
    // The tracker's two fixture frames become their coded points at the nominal layout.
    let layout = &received[2].1;
    let expected = c2 * frames.c2_points_mm[0];
    let seen = layout
        .points
        .iter()
        .find(|p| p.fixture == Fixture::C2 && p.id == 0)
        .unwrap();
    assert!((seen.position_mm - expected).norm() < 1e-3);
    // The frame pyigtl carried gives the estimate the original gives, to f32's precision.
    let sent = ingest_first(&cell, capture.clone());
    let got = ingest_first(&cell, received[0].1.clone());
    assert!(sent.fresh && got.fresh);
    for (a, b) in sent.state.iter().zip(got.state) {
        assert!((a - b).abs() < 1e-2, "{:?} {:?}", sent.state, got.state);
    }
}
