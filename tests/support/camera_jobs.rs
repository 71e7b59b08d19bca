//! Jobs through the drivers against an in-process `celld twin-server`, and pyigtl as a live
//! tracker in front of its camera: what `research/src/bin/camera_goals.rs`,
//! `tests/drivers/camera_goals_smoke.rs` and `tests/drivers/drivers_camera_peers.rs` share.

use assembly_cell::camera::StateEstimator;
use assembly_cell::cell::CellBackend;
use assembly_cell::cell::DriverSettings;
use assembly_cell::cell::job::{ControllerSource, JobEnd, JobRun, JobSpec, SafetyLimits};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::drivers::gcs::GcsSettings;
use assembly_cell::drivers::igtl::camera::CameraSettings;
use assembly_cell::geometry::CellFrames;
use assembly_cell::sim::InitialConditions;
use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Child, Command, Stdio};

/// One `expert` job of episode `seed` on `backend`, run to its end: the end, and each step's
/// `detected` (the steps that detected something).
pub fn run_job(
    seed: u64,
    cell: &CellConfig,
    backend: &mut dyn CellBackend,
) -> anyhow::Result<(JobEnd, Vec<String>)> {
    let spec = JobSpec {
        id: seed as i64,
        controller: ControllerSource::Builtin("expert".into()),
        seed,
        initial: InitialConditions::from_cell(cell),
        demonstration: false,
    };
    let limits = SafetyLimits {
        deadline_s: 10.0,
        max_stale_steps: 4,
    };
    let mut run = JobRun::start(&spec, cell, backend, limits, 0.0)
        .map_err(|end| anyhow::anyhow!("job {seed} did not start: {:?}", end.failure_reason))?;
    let mut detected = Vec::new();
    loop {
        let report = run.step(backend, &|| 0.0);
        detected.extend(report.record.and_then(|r| r.detected));
        if let Some(end) = report.end {
            return Ok((end, detected));
        }
    }
}

/// The drivers against a twin-server's controller at `gcs` and a camera at `camera`
/// (rehearsal: each job draws its episode there), with generous answer and frame timeouts
/// (2 s) so that only a fault, not a slow shared machine, ends a job.
pub fn driver_settings(camera: SocketAddr, gcs: SocketAddr, triggered: bool) -> DriverSettings {
    DriverSettings {
        robot_address: gcs.to_string(),
        robot: GcsSettings {
            answer_timeout_ms: 2000,
            ..GcsSettings::default()
        },
        camera_address: camera.to_string(),
        camera: CameraSettings {
            frame_timeout_ms: 2000,
            triggered,
            ..CameraSettings::default()
        },
        rehearsal: true,
    }
}

/// `tests/drivers/pyigtl_tracker_relay.py` running in front of a camera, killed when dropped.
pub struct PyTrackerRelay {
    child: Child,
    /// Where it serves its TRANSFORM frames.
    pub address: SocketAddr,
    /// Holds its spec file.
    _dir: tempfile::TempDir,
}

impl PyTrackerRelay {
    /// Starts the relay in front of the streaming camera at `camera`, fitting `cell`'s fixture
    /// layout with the estimator's rejection threshold.
    pub fn start(cell: &CellConfig, camera: SocketAddr) -> anyhow::Result<PyTrackerRelay> {
        let frames = CellFrames::from_config(cell);
        let threshold = StateEstimator::new(cell, &frames).rejection_threshold_mm();
        let points = |points: &[nalgebra::Point3<f64>]| -> serde_json::Value {
            points.iter().map(|p| vec![p.x, p.y, p.z]).collect()
        };
        let spec = serde_json::json!({
            "layout": {"C1": points(&frames.c1_points_mm), "C2": points(&frames.c2_points_mm)},
            "labels": {"C1": frames.c1_labels, "C2": frames.c2_labels},
            "reject_above_mm": threshold,
        });
        let dir = tempfile::tempdir()?;
        let path = dir.path().join("tracker.json");
        std::fs::write(&path, spec.to_string())?;
        // The repository's root: this crate's, or the one above it for `research/`.
        let script = Path::new(env!("CARGO_MANIFEST_DIR"))
            .ancestors()
            .map(|dir| dir.join("tests/drivers/pyigtl_tracker_relay.py"))
            .find(|script| script.exists())
            .ok_or_else(|| anyhow::anyhow!("tests/drivers/pyigtl_tracker_relay.py is not found"))?;
        let mut child = Command::new("python3")
            .arg(script)
            .arg(&path)
            .arg(camera.port().to_string())
            .arg(camera.ip().to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .map_err(|e| anyhow::anyhow!("cannot run python3: {e}"))?;
        let mut line = String::new();
        let stdout = child.stdout.take().expect("a piped stdout");
        BufReader::new(stdout).read_line(&mut line)?;
        let port: Option<u16> = line
            .trim()
            .strip_prefix("port ")
            .and_then(|p| p.parse().ok());
        let Some(port) = port else {
            let _ = child.kill();
            let _ = child.wait();
            anyhow::bail!("the tracker relay's first line is not `port N`: {line:?}");
        };
        Ok(PyTrackerRelay {
            child,
            address: SocketAddr::from(([127, 0, 0, 1], port)),
            _dir: dir,
        })
    }
}

impl Drop for PyTrackerRelay {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
