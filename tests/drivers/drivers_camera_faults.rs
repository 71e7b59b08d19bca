//! Camera faults through the drivers: between `celld twin-server`'s camera and the cell, a
//! relay that goes silent, repeats a frame, or sends garbage. Each ends the job with a named
//! reason and names the fault at each step it shows in.

use crate::drivers_support;

use assembly_cell::cell::job::{ControllerSource, JobEnd, JobRun, JobSpec, SafetyLimits};
use assembly_cell::cell::{DriverBackend, DriverSettings};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::drivers::gcs::GcsSettings;
use assembly_cell::drivers::igtl::camera::CameraSettings;
use assembly_cell::drivers::twin_server::{TwinServer, TwinServerOptions};
use assembly_cell::sim::InitialConditions;
use drivers_support::{GARBAGE, PASS, REPEAT, SILENT, camera_relay};
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};

/// A job through the drivers whose camera misbehaves (`fault`) from its sixth step on:
/// its end, and the `detected` of each step.
fn job_with(fault: u8) -> (JobEnd, Vec<Option<String>>) {
    let cell = CellConfig::reference();
    let server = TwinServer::start(&TwinServerOptions::loopback(&cell, 0)).unwrap();
    let mode = Arc::new(AtomicU8::new(PASS));
    let settings = DriverSettings {
        robot_address: server.gcs.to_string(),
        robot: GcsSettings {
            answer_timeout_ms: 2000,
            ..GcsSettings::default()
        },
        camera_address: camera_relay(server.igtl, mode.clone()).to_string(),
        camera: CameraSettings {
            // Generous, but for the silent camera's test: a loaded test machine must not
            // make a late frame a fault.
            frame_timeout_ms: if fault == SILENT { 200 } else { 2000 },
            // A repeated frame ages by a step each time it comes again; on a loaded machine its
            // third coming could be past the default 500 ms and read as stale before it reads
            // as frozen.
            max_age_ms: 5000,
            ..CameraSettings::default()
        },
        rehearsal: true,
    };
    let mut backend = DriverBackend::connect(&cell, settings, None).unwrap();
    let spec = JobSpec {
        id: 1,
        controller: ControllerSource::Builtin("expert".into()),
        seed: 12,
        initial: InitialConditions::from_cell(&cell),
        demonstration: false,
    };
    let limits = SafetyLimits {
        deadline_s: 10.0,
        max_stale_steps: 4,
    };
    let mut run = JobRun::start(&spec, &cell, &mut backend, limits, 0.0).unwrap();
    let mut detected = Vec::new();
    for step in 0.. {
        if step == 5 {
            mode.store(fault, Ordering::SeqCst);
        }
        let report = run.step(&mut backend, &|| 0.0);
        if let Some(record) = report.record {
            detected.push(record.detected);
        }
        if let Some(end) = report.end {
            return (end, detected);
        }
    }
    unreachable!()
}

fn named_after_the_fault(detected: &[Option<String>]) -> Vec<&str> {
    detected[5..].iter().flatten().map(String::as_str).collect()
}

#[test]
fn a_silent_camera_ends_the_job_stale_and_each_step_names_it() {
    let (end, detected) = job_with(SILENT);
    assert_eq!(
        end.failure_reason.as_deref(),
        Some("stale_camera"),
        "{end:?}"
    );
    assert!(detected[..5].iter().all(Option::is_none), "{detected:?}");
    let named = named_after_the_fault(&detected);
    assert!(
        !named.is_empty() && named.iter().all(|d| *d == "camera_silent"),
        "{named:?}"
    );
}

#[test]
fn a_repeated_frame_ends_the_job_as_a_frozen_camera() {
    let (end, detected) = job_with(REPEAT);
    assert_eq!(
        end.failure_reason.as_deref(),
        Some("frozen_camera"),
        "{end:?}; detected at each step: {detected:?}"
    );
    assert_eq!(
        named_after_the_fault(&detected).last(),
        Some(&"frozen_camera")
    );
}

#[test]
fn garbage_from_the_camera_ends_the_job_stale_and_each_step_names_it() {
    let (end, detected) = job_with(GARBAGE);
    assert_eq!(
        end.failure_reason.as_deref(),
        Some("stale_camera"),
        "{end:?}"
    );
    let named = named_after_the_fault(&detected);
    assert!(named.contains(&"camera_garbage"), "{named:?}");
}
