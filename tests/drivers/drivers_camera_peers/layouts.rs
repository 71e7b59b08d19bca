//! Fixture layouts from a calibration file: the bundled file is the generated ring to the
//! bit, a report's ids cross the wire and map back, a calibration σ widens the fit's
//! covariance, and a bad file is refused naming the point.

use super::{assembled, ingest_all, stamp, still_captures};
use assembly_cell::camera::{CameraFrame, StateEstimator};
use assembly_cell::config::cell::{CellConfig, CellConfigError};
use assembly_cell::config::fixture_layout::LayoutError;
use assembly_cell::drivers::igtl::camera::FrameAssembler;
use assembly_cell::drivers::igtl::codec::{Content, Timestamp};
use assembly_cell::drivers::twin_server::point_message;
use assembly_cell::geometry::CellFrames;
use std::path::{Path, PathBuf};

/// The bundled calibration file that reproduces the reference cell's generated ring.
fn ring_file() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("cells/phi170-fixtures.csv")
}

/// The reference cell with `camera.fixture_layout = "fixtures.csv"`, that file holding
/// `layout`, in a folder of its own.
fn calibrated_cell(layout: &str) -> (tempfile::TempDir, Result<CellConfig, CellConfigError>) {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("fixtures.csv"), layout).unwrap();
    let text = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/cells/phi170.toml"))
        .replace("[camera]", "[camera]\nfixture_layout = \"fixtures.csv\"");
    let path = dir.path().join("cell.toml");
    std::fs::write(&path, text).unwrap();
    let cell = CellConfig::load(&path);
    (dir, cell)
}

#[test]
fn the_bundled_calibration_file_is_the_generated_ring_to_the_bit() {
    let ring = CellConfig::reference();
    let (_dir, calibrated) = calibrated_cell(&std::fs::read_to_string(ring_file()).unwrap());
    let calibrated = calibrated.unwrap();
    let (a, b) = (
        CellFrames::from_config(&ring),
        CellFrames::from_config(&calibrated),
    );
    assert_eq!(a.c1_points_mm, b.c1_points_mm);
    assert_eq!(a.c2_points_mm, b.c2_points_mm);
    assert_eq!(
        (&a.c1_labels, &a.c1_sigma_mm),
        (&b.c1_labels, &b.c1_sigma_mm)
    );
    // The same episodes, estimate for estimate, to the bit.
    for seed in [1, 2] {
        let (captures, truth) = still_captures(&ring, seed, 40);
        let (again, _) = still_captures(&calibrated, seed, 40);
        assert_eq!(captures, again);
        let x = ingest_all(&ring, &captures, &truth);
        let y = ingest_all(&calibrated, &again, &truth);
        for (p, q) in x.estimates.iter().zip(&y.estimates) {
            let bits = |s: &[f64; 12]| s.map(f64::to_bits);
            assert_eq!(bits(&p.state), bits(&q.state));
            assert_eq!(bits(&p.raw_state), bits(&q.raw_state));
        }
    }
}

#[test]
fn points_named_by_their_calibrated_ids_cross_the_wire_and_estimate_alike() {
    // The ring again, its points given ids of a photogrammetry report (C1 101–106, C2 7, 9, …)
    // and listed backwards: a camera names them so, the driver maps them back to the layout,
    // and the estimates are the ring's.
    let ring = CellConfig::reference();
    let text = std::fs::read_to_string(ring_file()).unwrap();
    let mut lines: Vec<String> = text
        .lines()
        .filter(|l| l.starts_with("C1") || l.starts_with("C2"))
        .map(|line| {
            let mut values: Vec<String> = line.split(',').map(str::to_string).collect();
            let id: u16 = values[1].trim().parse().unwrap();
            values[1] = if values[0] == "C1" {
                101 + id
            } else {
                7 + 2 * id
            }
            .to_string();
            values.join(",")
        })
        .collect();
    lines.reverse();
    let relabelled = format!("fixture,id,x_mm,y_mm,z_mm\n{}\n", lines.join("\n"));
    let (_dir, calibrated) = calibrated_cell(&relabelled);
    let calibrated = calibrated.unwrap();
    let frames = CellFrames::from_config(&calibrated);
    assert_eq!(frames.c1_labels, [106, 105, 104, 103, 102, 101]);
    let (captures, truth) = still_captures(&ring, 4, 30);
    // The same physical points: the ring's point k is the backwards layout's 5 − k.
    let relabelled_captures: Vec<CameraFrame> = captures
        .iter()
        .map(|capture| {
            let mut frame = capture.clone();
            for point in &mut frame.points {
                point.id = 5 - point.id;
            }
            frame
        })
        .collect();
    let ring_frames = CellFrames::from_config(&ring);
    let wire = |cell: &CellConfig, frames: &CellFrames, captures: &[CameraFrame]| {
        let mut assembler = FrameAssembler::new(frames, u64::MAX / 2);
        let received: Vec<CameraFrame> = captures
            .iter()
            .enumerate()
            .flat_map(|(k, capture)| {
                let at = Timestamp::from_secs_f64(10.0 + k as f64);
                let message = point_message(capture, frames, 2, 0, at);
                assembled(&mut assembler, &[message])
            })
            .collect();
        (received.clone(), ingest_all(cell, &received, &truth))
    };
    let (ring_received, x) = wire(&ring, &ring_frames, &captures);
    let (received, y) = wire(&calibrated, &frames, &relabelled_captures);
    // On the wire the points carry the report's ids; back in the driver, their layout index.
    let first = point_message(&relabelled_captures[0], &frames, 2, 0, stamp(0));
    let Content::Point(elements) = &first.content else {
        panic!("a POINT message")
    };
    for element in elements {
        let id: u16 = element.name.parse().unwrap();
        match element.group.as_str() {
            "C1" => assert!((101..=106).contains(&id), "{id}"),
            _ => assert!(id % 2 == 1 && (7..=17).contains(&id), "{id}"),
        }
    }
    for (a, b) in ring_received.iter().zip(&received) {
        for (p, q) in a.points.iter().zip(&b.points) {
            assert_eq!(
                (p.fixture, p.id, p.position_mm),
                (q.fixture, 5 - q.id, q.position_mm)
            );
        }
    }
    for (p, q) in x.estimates.iter().zip(&y.estimates) {
        for (a, b) in p.state.iter().zip(q.state) {
            assert!((a - b).abs() < 1e-6, "{:?} {:?}", p.state, q.state);
        }
    }
}

#[test]
fn a_calibration_sigma_widens_the_fits_covariance_as_it_should() {
    // Every point given σ_c = 0.05 mm: each point's variance is the data sheet's σ² + σ_c², so
    // the fit's covariance grows by a factor between the smallest and the largest of
    // 1 + σ_c²/σ² over the points (equal factors would scale it exactly).
    let ring = CellConfig::reference();
    let text = std::fs::read_to_string(ring_file()).unwrap();
    let with_sigma: String = text
        .lines()
        .map(|line| match line {
            l if l.starts_with("fixture") => format!("{l},sigma_mm\n"),
            l if l.starts_with("C1") || l.starts_with("C2") => format!("{l},0.05\n"),
            l => format!("{l}\n"),
        })
        .collect();
    let (_dir, calibrated) = calibrated_cell(&with_sigma);
    let calibrated = calibrated.unwrap();
    let frames = CellFrames::from_config(&calibrated);
    assert!(frames.c2_sigma_mm.iter().all(|s| *s == 0.05));
    let mut ring_exact = ring.clone();
    ring_exact.imperfections.camera_noise = false;
    ring_exact.imperfections.dropped_points = false;
    ring_exact.imperfections.outliers = false;
    let (captures, _) = still_captures(&ring_exact, 5, 1);
    let plain = StateEstimator::new(&ring, &CellFrames::from_config(&ring))
        .estimate(&captures[0], 1.0)
        .unwrap();
    let widened = StateEstimator::new(&calibrated, &frames)
        .estimate(&captures[0], 1.0)
        .unwrap();
    // The poses are the same fit (the fit is unweighted).
    assert_eq!(plain.m_f, widened.m_f);
    let sheet = assembly_cell::camera::PointNoise::of(&ring.camera);
    let factors: Vec<f64> = captures[0]
        .points
        .iter()
        .map(|p| 1.0 + 0.05f64.powi(2) / sheet.at_mm(&p.position_mm).powi(2))
        .collect();
    let (low, high) = factors
        .iter()
        .fold((f64::MAX, 0.0f64), |(l, h), f| (l.min(*f), h.max(*f)));
    for i in 0..6 {
        let ratio = widened.covariance[(i, i)] / plain.covariance[(i, i)];
        assert!(
            ratio > low * (1.0 - 1e-9) && ratio < high * (1.0 + 1e-9),
            "{i}: {ratio} not in [{low}, {high}]"
        );
    }
}

#[test]
fn a_bad_calibration_file_is_refused_naming_the_point() {
    let ring = std::fs::read_to_string(ring_file()).unwrap();
    let (_dir, duplicated) = calibrated_cell(&format!("{ring}C2,3,1,2,3\n"));
    let error = duplicated.unwrap_err();
    // The problem is said once, in the message, not again as a source in an error chain.
    assert!(std::error::Error::source(&error).is_none());
    let message = error.to_string();
    assert!(
        message.contains("fixtures.csv") && message.contains("point C2 3 again"),
        "{message}"
    );
    let (_dir, few) = calibrated_cell(
        &ring
            .lines()
            .filter(|l| !l.starts_with("C1") || l.starts_with("C1,0"))
            .collect::<Vec<_>>()
            .join("\n"),
    );
    match few {
        Err(CellConfigError::Layout { problem, .. }) => assert_eq!(
            problem,
            LayoutError::TooFew {
                fixture: "C1",
                found: 1,
                needed: 3
            }
        ),
        other => panic!("{other:?}"),
    }
    let (_dir, negative) = calibrated_cell("fixture,id,x_mm,y_mm,z_mm,sigma_mm\nC1,4,1,2,3,-1\n");
    let message = negative.unwrap_err().to_string();
    assert!(
        message.contains("point C1 4: `sigma_mm` is -1"),
        "{message}"
    );
    let (_dir, not_finite) = calibrated_cell("fixture,id,x_mm,y_mm,z_mm\nC2,8,1,inf,3\n");
    let message = not_finite.unwrap_err().to_string();
    assert!(message.contains("point C2 8: `y_mm` is inf"), "{message}");
    // A file that is not there is named.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cell.toml");
    let text = include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/cells/phi170.toml"))
        .replace("[camera]", "[camera]\nfixture_layout = \"missing.csv\"");
    std::fs::write(&path, text).unwrap();
    let message = CellConfig::load(&path).unwrap_err().to_string();
    assert!(message.contains("missing.csv"), "{message}");
}
