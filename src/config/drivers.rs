//! `[robot]` and `[camera]` of the service's settings: which drivers stand behind the cell.
//! Both `twin` (the default: the in-process digital twin), or the real drivers together:
//! `robot.driver = "gcs"` (a PI hexapod controller) with `camera.driver = "igtl"` (an
//! OpenIGTLink camera or tracker). docs/integration.md describes each key.

use crate::drivers::gcs::GcsSettings;
use crate::drivers::igtl::camera::CameraSettings;
use serde::Deserialize;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RobotDriver {
    Twin,
    Gcs,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraDriver {
    Twin,
    Igtl,
}

/// `[robot]`: the hexapod controller.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RobotDriverConfig {
    pub driver: RobotDriver,
    /// The controller's host name or IP address.
    pub address: String,
    /// The controller's TCP port (PI's is 50000).
    pub port: u16,
    /// Longest wait for the TCP connection, ms.
    pub connect_timeout_ms: u64,
    /// Longest wait for an answer, ms; a later one drops the connection and latches the
    /// driver until an operator reset.
    pub answer_timeout_ms: u64,
    /// Longest wait for on target beyond the move's allowed time (its time at the platform's
    /// speeds × `move_time_factor`), ms; then `STP` and the job fails.
    pub on_target_deadline_ms: u64,
    /// A move is allowed this many times its time at the platform's speeds.
    pub move_time_factor: f64,
    /// Largest difference per axis between the controller's position and where the cell put
    /// the platform before the driver latches (`position_mismatch`), mm (X Y Z).
    pub position_tolerance_mm: f64,
    /// The same for U V W, deg.
    pub orientation_tolerance_deg: f64,
    /// Pause between `ONT?` polls, ms (0: back to back).
    pub poll_interval_ms: u64,
    /// The platform's velocity, set with `VLS` at connection and reset, mm/s; none leaves
    /// the controller's own.
    pub velocity_mm_s: Option<f64>,
    /// The controller is `celld twin-server`: each job's start asks it to draw the job's
    /// episode. Leave false for a real controller.
    pub rehearsal: bool,
}

impl Default for RobotDriverConfig {
    fn default() -> Self {
        let gcs = GcsSettings::default();
        RobotDriverConfig {
            driver: RobotDriver::Twin,
            address: "127.0.0.1".into(),
            port: 50000,
            connect_timeout_ms: gcs.connect_timeout_ms,
            answer_timeout_ms: gcs.answer_timeout_ms,
            on_target_deadline_ms: gcs.on_target_deadline_ms,
            move_time_factor: gcs.move_time_factor,
            position_tolerance_mm: gcs.position_tolerance_mm,
            orientation_tolerance_deg: gcs.orientation_tolerance_deg,
            poll_interval_ms: gcs.poll_interval_ms,
            velocity_mm_s: gcs.velocity_mm_s,
            rehearsal: false,
        }
    }
}

impl RobotDriverConfig {
    pub fn gcs_settings(&self) -> GcsSettings {
        GcsSettings {
            connect_timeout_ms: self.connect_timeout_ms,
            answer_timeout_ms: self.answer_timeout_ms,
            on_target_deadline_ms: self.on_target_deadline_ms,
            move_time_factor: self.move_time_factor,
            poll_interval_ms: self.poll_interval_ms,
            velocity_mm_s: self.velocity_mm_s,
            position_tolerance_mm: self.position_tolerance_mm,
            orientation_tolerance_deg: self.orientation_tolerance_deg,
        }
    }

    /// `address:port`.
    pub fn endpoint(&self) -> String {
        endpoint(&self.address, self.port)
    }
}

/// `[camera]`: the measuring camera.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraDriverConfig {
    pub driver: CameraDriver,
    /// The camera's (or tracker's) OpenIGTLink server: host name or IP address.
    pub address: String,
    /// Its TCP port (OpenIGTLink's is 18944).
    pub port: u16,
    /// Longest wait for the TCP connection, ms.
    pub connect_timeout_ms: u64,
    /// Longest wait for a capture's frame, ms.
    pub frame_timeout_ms: u64,
    /// Oldest frame accepted (by this machine's clock), ms.
    pub max_age_ms: u64,
    /// Ask for each capture with `GET_POINT` (true), or take the newest frame the camera
    /// streams (false).
    pub triggered: bool,
}

impl Default for CameraDriverConfig {
    fn default() -> Self {
        let camera = CameraSettings::default();
        CameraDriverConfig {
            driver: CameraDriver::Twin,
            address: "127.0.0.1".into(),
            port: 18944,
            connect_timeout_ms: camera.connect_timeout_ms,
            frame_timeout_ms: camera.frame_timeout_ms,
            max_age_ms: camera.max_age_ms,
            triggered: camera.triggered,
        }
    }
}

impl CameraDriverConfig {
    pub fn camera_settings(&self) -> CameraSettings {
        CameraSettings {
            connect_timeout_ms: self.connect_timeout_ms,
            frame_timeout_ms: self.frame_timeout_ms,
            max_age_ms: self.max_age_ms,
            triggered: self.triggered,
        }
    }

    /// `address:port`.
    pub fn endpoint(&self) -> String {
        endpoint(&self.address, self.port)
    }
}

fn endpoint(address: &str, port: u16) -> String {
    if address.contains(':') && !address.starts_with('[') {
        format!("[{address}]:{port}")
    } else {
        format!("{address}:{port}")
    }
}

/// Why the two drivers do not go together, or a timeout makes no sense; `None` when they do.
pub fn check(
    robot: &RobotDriverConfig,
    camera: &CameraDriverConfig,
) -> Option<(&'static str, String, &'static str)> {
    match (robot.driver, camera.driver) {
        (RobotDriver::Twin, CameraDriver::Twin) => return None,
        (RobotDriver::Gcs, CameraDriver::Igtl) => {}
        (RobotDriver::Gcs, CameraDriver::Twin) => {
            return Some((
                "camera.driver",
                "twin".into(),
                "robot.driver = \"gcs\" needs camera.driver = \"igtl\": the twin's camera sees only the twin's robot",
            ));
        }
        (RobotDriver::Twin, CameraDriver::Igtl) => {
            return Some((
                "robot.driver",
                "twin".into(),
                "camera.driver = \"igtl\" needs robot.driver = \"gcs\": a real camera sees a real robot",
            ));
        }
    }
    if !(robot.move_time_factor.is_finite() && robot.move_time_factor >= 1.0) {
        return Some((
            "robot.move_time_factor",
            robot.move_time_factor.to_string(),
            "must be a number ≥ 1: a move takes at least its time at the platform's speeds",
        ));
    }
    for (key, value) in [
        ("robot.position_tolerance_mm", robot.position_tolerance_mm),
        (
            "robot.orientation_tolerance_deg",
            robot.orientation_tolerance_deg,
        ),
    ] {
        if !(value.is_finite() && value > 0.0) {
            return Some((key, value.to_string(), "must be a number > 0"));
        }
    }
    if let Some(velocity) = robot.velocity_mm_s
        && !(velocity.is_finite() && velocity > 0.0)
    {
        return Some((
            "robot.velocity_mm_s",
            velocity.to_string(),
            "must be a number > 0",
        ));
    }
    for (key, value) in [
        ("robot.connect_timeout_ms", robot.connect_timeout_ms),
        ("robot.answer_timeout_ms", robot.answer_timeout_ms),
        ("robot.on_target_deadline_ms", robot.on_target_deadline_ms),
        ("camera.connect_timeout_ms", camera.connect_timeout_ms),
        ("camera.frame_timeout_ms", camera.frame_timeout_ms),
        ("camera.max_age_ms", camera.max_age_ms),
    ] {
        if value == 0 {
            return Some((key, "0".into(), "must be ≥ 1 ms"));
        }
    }
    None
}
