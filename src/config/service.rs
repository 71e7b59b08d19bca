//! The service's own settings (`celld serve`): where it listens, where it keeps its data, which
//! cell it runs and how the control loop is timed.
//!
//! Layers, later wins: built-in defaults, a TOML file (`--config`), `CELLD_*` environment
//! variables, command-line flags. Every key is documented in `deploy/celld.example.toml`.

use super::drivers::{CameraDriver, CameraDriverConfig, RobotDriver, RobotDriverConfig};
use serde::Deserialize;
use std::fmt;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum ServiceConfigError {
    #[error("cannot read {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Parse { path: String, message: String },
    #[error("{origin}: `{key}` = `{value}`: {reason}")]
    Invalid {
        origin: String,
        key: &'static str,
        value: String,
        reason: String,
    },
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServiceConfig {
    /// Address the HTTP server binds (`127.0.0.1:0` picks a free port).
    pub listen: SocketAddr,
    /// The SQLite database file; its directory is created if missing, and the first admin
    /// token is written beside it as `admin.token`.
    pub db: PathBuf,
    /// Cell file; none means the bundled reference cell (cells/phi170.toml).
    pub cell: Option<PathBuf>,
    /// Run the twin as fast as it can instead of at the camera's rate.
    pub fast: bool,
    pub control: ControlConfig,
    pub http: HttpConfig,
    pub policies: PolicyConfig,
    /// Background work (evaluations, training runs): how many at once, how many may wait.
    pub work: WorkConfig,
    /// The hexapod controller's driver (`twin` or `gcs`).
    pub robot: RobotDriverConfig,
    /// The camera's driver (`twin` or `igtl`).
    pub camera: CameraDriverConfig,
    pub access: AccessConfig,
    pub opcua: OpcUaConfig,
    /// `[service]`: who this cell is to a fleet.
    pub service: IdentityConfig,
    /// `[fleet]`: the PostgreSQL this cell replicates to, if any.
    pub fleet: FleetConfig,
}

/// `[service]`: the cell's id, carried by every row it replicates to a fleet.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IdentityConfig {
    /// 1–64 letters, digits, `-`, `_` or `.`; none: the cell file's name without its
    /// extension (`phi170` for the bundled cell).
    pub cell_id: Option<String>,
}

/// `[fleet]`: one PostgreSQL the cell replicates its record to (`fleet`).
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FleetConfig {
    /// `postgres://user:password@host:port/database`; none: the cell is in no fleet.
    pub url: Option<String>,
}

/// The longest cell id.
pub const MAX_CELL_ID_CHARS: usize = 64;

/// Why `cell_id` cannot name a cell, if it cannot.
pub fn check_cell_id(cell_id: &str) -> Result<(), String> {
    let allowed = |c: char| c.is_ascii_alphanumeric() || "-_.".contains(c);
    if cell_id.is_empty() || cell_id.chars().count() > MAX_CELL_ID_CHARS {
        return Err(format!("must be 1 to {MAX_CELL_ID_CHARS} characters"));
    }
    if let Some(bad) = cell_id.chars().find(|&c| !allowed(c)) {
        return Err(format!(
            "`{bad}` is not allowed: use letters, digits, `-`, `_` and `.`"
        ));
    }
    Ok(())
}

/// Why `url` cannot be a fleet's database, if it cannot: it must be a PostgreSQL URL.
pub fn check_fleet_url(url: &str) -> Result<(), String> {
    let scheme = url.split_once("://").map(|(scheme, _)| scheme);
    match scheme {
        Some("postgres" | "postgresql") => Ok(()),
        Some(other) => Err(format!(
            "a fleet is a PostgreSQL database: expected postgres://…, not {other}://"
        )),
        None => Err("a fleet is a PostgreSQL database URL such as \
                     postgres://celld@fleet-db/fleet"
            .to_string()),
    }
}

/// `[opcua]`: the OPC UA server a plant's PLC or SCADA connects to (`opcua::server`). Its
/// certificates live in `opcua-pki/` beside the database.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OpcUaConfig {
    /// `"host:port"` (port 0 picks a free port) or `"off"`.
    pub listen: OpcUaListen,
    /// The cell's maker and serial number on its name plate (OPC 40001-1 Identification);
    /// none: `celld` and the cell file's hash.
    pub manufacturer: Option<String>,
    pub serial_number: Option<String>,
}

impl Default for OpcUaConfig {
    fn default() -> Self {
        OpcUaConfig {
            listen: OpcUaListen::Address(SocketAddr::from(([127, 0, 0, 1], 4840))),
            manufacturer: None,
            serial_number: None,
        }
    }
}

/// `opcua.listen`: an address, or no OPC UA server.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OpcUaListen {
    Off,
    Address(SocketAddr),
}

impl std::str::FromStr for OpcUaListen {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        match text.trim() {
            "off" => Ok(OpcUaListen::Off),
            address => address
                .parse()
                .map(OpcUaListen::Address)
                .map_err(|_| format!("`{text}` is not off or an address such as 127.0.0.1:4840")),
        }
    }
}

impl fmt::Display for OpcUaListen {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            OpcUaListen::Off => f.write_str("off"),
            OpcUaListen::Address(address) => write!(f, "{address}"),
        }
    }
}

/// In TOML: `"off"` or `"host:port"`.
impl<'de> Deserialize<'de> for OpcUaListen {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        String::deserialize(deserializer)?
            .parse()
            .map_err(serde::de::Error::custom)
    }
}

/// `[access]`: how many refused tokens one client address may send before it is answered 429.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AccessConfig {
    /// Refused tokens from one address within a window before it is limited.
    pub auth_failure_limit: u32,
    /// The window, s: it starts at an address's first refused token; a limited address waits
    /// until it ends.
    pub auth_failure_window_s: u64,
    /// Addresses whose failures are remembered at most (the oldest are forgotten first).
    pub auth_failure_addresses: usize,
}

impl Default for AccessConfig {
    fn default() -> Self {
        AccessConfig {
            auth_failure_limit: 20,
            auth_failure_window_s: 60,
            auth_failure_addresses: 10_000,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ControlConfig {
    /// What `"controller": "active"` runs until the policy registry names an active policy.
    pub active_controller: String,
    /// Control period, ms; none means one camera cycle (1000 / camera.rate_hz). Ignored with
    /// `fast`.
    pub step_period_ms: Option<f64>,
    /// A step whose decision, supervision and execution take longer than this stops the job
    /// with `missed_deadline`.
    pub deadline_ms: f64,
    /// This many steps in a row without a fresh camera measurement stop the job with
    /// `stale_camera`.
    pub max_stale_steps: u32,
    /// Steps per SQLite transaction while a job runs (also flushed every 100 ms).
    pub step_batch: usize,
    /// Telemetry events buffered per subscriber; a subscriber further behind skips ahead and
    /// is counted as lagging.
    pub telemetry_buffer: usize,
    /// The CPU the control thread keeps to itself (`cell::cpu`).
    pub cpu: ControlCpu,
}

/// `control.cpu`: which CPU the control thread gets to itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ControlCpu {
    /// The last CPU this process may use, when it may use two or more
    /// (`cell::cpu::AUTO_FROM_CPUS`).
    #[default]
    Auto,
    /// No placement: every thread may run anywhere.
    Off,
    /// This CPU (as the kernel numbers them).
    Cpu(usize),
}

impl std::str::FromStr for ControlCpu {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        match text.trim() {
            "auto" => Ok(ControlCpu::Auto),
            "off" => Ok(ControlCpu::Off),
            number => number
                .parse()
                .map(ControlCpu::Cpu)
                .map_err(|_| format!("`{text}` is not auto, off or a CPU number")),
        }
    }
}

impl fmt::Display for ControlCpu {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ControlCpu::Auto => f.write_str("auto"),
            ControlCpu::Off => f.write_str("off"),
            ControlCpu::Cpu(cpu) => write!(f, "{cpu}"),
        }
    }
}

/// In TOML: `"auto"`, `"off"` or a CPU number.
impl<'de> Deserialize<'de> for ControlCpu {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Number(usize),
            Text(String),
        }
        match Raw::deserialize(deserializer)? {
            Raw::Number(cpu) => Ok(ControlCpu::Cpu(cpu)),
            Raw::Text(text) => text.parse().map_err(serde::de::Error::custom),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HttpConfig {
    /// Largest request body accepted, bytes (larger is 413).
    pub body_limit_bytes: usize,
    /// Open connections at most; at the cap the oldest one without a request in progress is
    /// closed for a new one (`http::server`).
    pub max_connections: usize,
    /// From a request's first byte to its complete head, ms; a slower client is closed.
    pub header_timeout_ms: u64,
    /// A connection with no request in progress and no byte of the next is closed after
    /// this, s.
    pub idle_timeout_s: u64,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PolicyConfig {
    /// Largest policy upload or demonstration import, bytes (larger is 413).
    pub max_upload_bytes: usize,
    /// Success rate an evaluation on this cell must reach before a policy may be activated.
    pub activation_threshold: f64,
    /// Episodes of an evaluation when the request does not say (and of the bundled policy's
    /// evaluation at first start).
    pub evaluation_episodes: u32,
    /// Most episodes one evaluation request may ask for (more is 422).
    pub max_evaluation_episodes: u32,
    /// Most numbers (parameters) an uploaded policy file may hold; more is 422. A queued job
    /// keeps its policy's parameters in memory (4 bytes each) until it ends.
    pub max_parameters: usize,
}

/// `[work]`: the one queue evaluations and training runs wait in (`workflows::queue`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WorkConfig {
    /// Pieces of background work computing at once, each on one thread at nice 10.
    pub concurrency: usize,
    /// Pieces that may wait behind them; one more is refused (429).
    pub queue_length: usize,
}

impl Default for WorkConfig {
    fn default() -> Self {
        WorkConfig {
            concurrency: 1,
            queue_length: 16,
        }
    }
}

/// Most pieces of background work computing at once (`work.concurrency`).
pub const MAX_WORK_CONCURRENCY: usize = 64;
/// Longest work queue (`work.queue_length`).
pub const MAX_WORK_QUEUE_LENGTH: usize = 10_000;
/// Highest `policies.max_evaluation_episodes`.
pub const MAX_EVALUATION_EPISODES: u32 = 1_000_000;

impl Default for PolicyConfig {
    fn default() -> Self {
        PolicyConfig {
            max_upload_bytes: 64 << 20,
            activation_threshold: 0.95,
            evaluation_episodes: 1000,
            max_evaluation_episodes: 10_000,
            max_parameters: DEFAULT_MAX_POLICY_PARAMETERS,
        }
    }
}

/// `policies.max_parameters` by default: a million, 14 times the largest bundled policy (the
/// flat TD3 baseline, 70,686; the hierarchical ones hold 30,561).
pub const DEFAULT_MAX_POLICY_PARAMETERS: usize = 1_000_000;

/// The longest `control.deadline_ms` and `control.step_period_ms`: a minute. A control step
/// is a camera cycle (250 ms at 4 Hz); one that may take a minute has stopped being control.
pub const MAX_CONTROL_MS: f64 = 60_000.0;

impl Default for ServiceConfig {
    fn default() -> Self {
        ServiceConfig {
            listen: "127.0.0.1:8080".parse().expect("valid address"),
            db: PathBuf::from("data/celld.db"),
            cell: None,
            fast: false,
            control: ControlConfig::default(),
            http: HttpConfig::default(),
            policies: PolicyConfig::default(),
            work: WorkConfig::default(),
            robot: RobotDriverConfig::default(),
            camera: CameraDriverConfig::default(),
            access: AccessConfig::default(),
            opcua: OpcUaConfig::default(),
            service: IdentityConfig::default(),
            fleet: FleetConfig::default(),
        }
    }
}

impl Default for ControlConfig {
    fn default() -> Self {
        ControlConfig {
            active_controller: "expert".to_string(),
            step_period_ms: None,
            deadline_ms: 50.0,
            max_stale_steps: 4,
            step_batch: 256,
            telemetry_buffer: 1024,
            cpu: ControlCpu::Auto,
        }
    }
}

impl Default for HttpConfig {
    fn default() -> Self {
        HttpConfig {
            body_limit_bytes: 1 << 20,
            max_connections: 1024,
            header_timeout_ms: 10_000,
            idle_timeout_s: 30,
        }
    }
}

impl ServiceConfig {
    /// Defaults, then the file if given.
    pub fn load(path: Option<&Path>) -> Result<Self, ServiceConfigError> {
        let Some(path) = path else {
            return Ok(ServiceConfig::default());
        };
        let text = std::fs::read_to_string(path).map_err(|source| ServiceConfigError::Io {
            path: path.display().to_string(),
            source,
        })?;
        toml::from_str(&text).map_err(|e| ServiceConfigError::Parse {
            path: path.display().to_string(),
            message: e.to_string(),
        })
    }

    /// Applies `CELLD_*` variables from `vars` (the process environment in `celld serve`).
    pub fn apply_env(
        &mut self,
        vars: impl IntoIterator<Item = (String, String)>,
    ) -> Result<(), ServiceConfigError> {
        for (key, value) in vars {
            let Some(name) = key.strip_prefix("CELLD_") else {
                continue;
            };
            let invalid = |key: &'static str, reason: &str| ServiceConfigError::Invalid {
                origin: "environment".to_string(),
                key,
                value: value.clone(),
                reason: reason.to_string(),
            };
            match name {
                "LISTEN" => {
                    self.listen = value
                        .parse()
                        .map_err(|_| invalid("CELLD_LISTEN", "not an address"))?
                }
                "DB" => self.db = PathBuf::from(&value),
                "CELL" => self.cell = Some(PathBuf::from(&value)),
                "FAST" => {
                    self.fast = parse_bool(&value)
                        .ok_or_else(|| invalid("CELLD_FAST", "expected true or false"))?
                }
                "ACTIVE_CONTROLLER" => self.control.active_controller = value.clone(),
                "STEP_PERIOD_MS" => {
                    self.control.step_period_ms = Some(
                        value
                            .parse()
                            .map_err(|_| invalid("CELLD_STEP_PERIOD_MS", "not a number"))?,
                    )
                }
                "CONTROL_CPU" => {
                    self.control.cpu = value
                        .parse()
                        .map_err(|reason: String| invalid("CELLD_CONTROL_CPU", &reason))?
                }
                "DEADLINE_MS" => {
                    self.control.deadline_ms = value
                        .parse()
                        .map_err(|_| invalid("CELLD_DEADLINE_MS", "not a number"))?
                }
                "BODY_LIMIT_BYTES" => {
                    self.http.body_limit_bytes = value
                        .parse()
                        .map_err(|_| invalid("CELLD_BODY_LIMIT_BYTES", "not a whole number"))?
                }
                "MAX_CONNECTIONS" => {
                    self.http.max_connections = value
                        .parse()
                        .map_err(|_| invalid("CELLD_MAX_CONNECTIONS", "not a whole number"))?
                }
                "HEADER_TIMEOUT_MS" => {
                    self.http.header_timeout_ms = value
                        .parse()
                        .map_err(|_| invalid("CELLD_HEADER_TIMEOUT_MS", "not a whole number"))?
                }
                "IDLE_TIMEOUT_S" => {
                    self.http.idle_timeout_s = value
                        .parse()
                        .map_err(|_| invalid("CELLD_IDLE_TIMEOUT_S", "not a whole number"))?
                }
                "MAX_POLICY_BYTES" => {
                    self.policies.max_upload_bytes = value
                        .parse()
                        .map_err(|_| invalid("CELLD_MAX_POLICY_BYTES", "not a whole number"))?
                }
                "ACTIVATION_THRESHOLD" => {
                    self.policies.activation_threshold = value
                        .parse()
                        .map_err(|_| invalid("CELLD_ACTIVATION_THRESHOLD", "not a number"))?
                }
                "MAX_POLICY_PARAMETERS" => {
                    self.policies.max_parameters = value
                        .parse()
                        .map_err(|_| invalid("CELLD_MAX_POLICY_PARAMETERS", "not a whole number"))?
                }
                "EVALUATION_EPISODES" => {
                    self.policies.evaluation_episodes = value
                        .parse()
                        .map_err(|_| invalid("CELLD_EVALUATION_EPISODES", "not a whole number"))?
                }
                "MAX_EVALUATION_EPISODES" => {
                    self.policies.max_evaluation_episodes = value.parse().map_err(|_| {
                        invalid("CELLD_MAX_EVALUATION_EPISODES", "not a whole number")
                    })?
                }
                "WORK_CONCURRENCY" => {
                    self.work.concurrency = value
                        .parse()
                        .map_err(|_| invalid("CELLD_WORK_CONCURRENCY", "not a whole number"))?
                }
                "WORK_QUEUE_LENGTH" => {
                    self.work.queue_length = value
                        .parse()
                        .map_err(|_| invalid("CELLD_WORK_QUEUE_LENGTH", "not a whole number"))?
                }
                "ROBOT_DRIVER" => {
                    self.robot.driver = match value.as_str() {
                        "twin" => RobotDriver::Twin,
                        "gcs" => RobotDriver::Gcs,
                        _ => return Err(invalid("CELLD_ROBOT_DRIVER", "expected twin or gcs")),
                    }
                }
                "ROBOT_ADDRESS" => self.robot.address = value.clone(),
                "ROBOT_PORT" => {
                    self.robot.port = value
                        .parse()
                        .map_err(|_| invalid("CELLD_ROBOT_PORT", "not a port number"))?
                }
                "ROBOT_ANSWER_TIMEOUT_MS" => {
                    self.robot.answer_timeout_ms = value.parse().map_err(|_| {
                        invalid("CELLD_ROBOT_ANSWER_TIMEOUT_MS", "not a whole number")
                    })?
                }
                "ROBOT_ON_TARGET_DEADLINE_MS" => {
                    self.robot.on_target_deadline_ms = value.parse().map_err(|_| {
                        invalid("CELLD_ROBOT_ON_TARGET_DEADLINE_MS", "not a whole number")
                    })?
                }
                "CAMERA_FRAME_TIMEOUT_MS" => {
                    self.camera.frame_timeout_ms = value.parse().map_err(|_| {
                        invalid("CELLD_CAMERA_FRAME_TIMEOUT_MS", "not a whole number")
                    })?
                }
                "ROBOT_REHEARSAL" => {
                    self.robot.rehearsal = parse_bool(&value)
                        .ok_or_else(|| invalid("CELLD_ROBOT_REHEARSAL", "expected true or false"))?
                }
                "CAMERA_DRIVER" => {
                    self.camera.driver = match value.as_str() {
                        "twin" => CameraDriver::Twin,
                        "igtl" => CameraDriver::Igtl,
                        _ => return Err(invalid("CELLD_CAMERA_DRIVER", "expected twin or igtl")),
                    }
                }
                "CAMERA_ADDRESS" => self.camera.address = value.clone(),
                "CAMERA_PORT" => {
                    self.camera.port = value
                        .parse()
                        .map_err(|_| invalid("CELLD_CAMERA_PORT", "not a port number"))?
                }
                "AUTH_FAILURE_LIMIT" => {
                    self.access.auth_failure_limit = value
                        .parse()
                        .map_err(|_| invalid("CELLD_AUTH_FAILURE_LIMIT", "not a whole number"))?
                }
                "AUTH_FAILURE_WINDOW_S" => {
                    self.access.auth_failure_window_s = value
                        .parse()
                        .map_err(|_| invalid("CELLD_AUTH_FAILURE_WINDOW_S", "not a whole number"))?
                }
                "AUTH_FAILURE_ADDRESSES" => {
                    self.access.auth_failure_addresses = value.parse().map_err(|_| {
                        invalid("CELLD_AUTH_FAILURE_ADDRESSES", "not a whole number")
                    })?
                }
                "OPCUA_LISTEN" => {
                    self.opcua.listen = value
                        .parse()
                        .map_err(|reason: String| invalid("CELLD_OPCUA_LISTEN", &reason))?
                }
                "CELL_ID" => self.service.cell_id = Some(value.clone()),
                "FLEET_URL" => self.fleet.url = Some(value.clone()).filter(|v| !v.is_empty()),
                // Other CELLD_ variables (CELLD_LOG, CELLD_TOKEN for clients) are not ours.
                _ => {}
            }
        }
        Ok(())
    }

    /// Checks values no type can: positive periods and sizes.
    pub fn validate(&self) -> Result<(), ServiceConfigError> {
        let invalid =
            |key: &'static str, value: String, reason: &str| ServiceConfigError::Invalid {
                origin: "configuration".to_string(),
                key,
                value,
                reason: reason.to_string(),
            };
        if let Some(period) = self.control.step_period_ms
            && !(period.is_finite() && (0.0..=MAX_CONTROL_MS).contains(&period))
        {
            return Err(invalid(
                "control.step_period_ms",
                format!("{period:?}"),
                &format!("must be a number in [0, {MAX_CONTROL_MS}] ms"),
            ));
        }
        let deadline = self.control.deadline_ms;
        if !(deadline.is_finite() && deadline > 0.0 && deadline <= MAX_CONTROL_MS) {
            return Err(invalid(
                "control.deadline_ms",
                format!("{deadline:?}"),
                &format!("must be > 0 and at most {MAX_CONTROL_MS} ms"),
            ));
        }
        if self.control.step_batch == 0 {
            return Err(invalid("control.step_batch", "0".into(), "must be ≥ 1"));
        }
        if self.control.telemetry_buffer == 0 {
            return Err(invalid(
                "control.telemetry_buffer",
                "0".into(),
                "must be ≥ 1",
            ));
        }
        if let Some((key, value, reason)) = super::drivers::check(&self.robot, &self.camera) {
            return Err(invalid(key, value, reason));
        }
        let waits_ms = self.robot.on_target_deadline_ms + self.camera.frame_timeout_ms;
        if self.robot.driver == RobotDriver::Gcs && waits_ms as f64 > self.control.deadline_ms {
            return Err(invalid(
                "robot.on_target_deadline_ms",
                self.robot.on_target_deadline_ms.to_string(),
                &format!(
                    "with camera.frame_timeout_ms ({} ms) it must not exceed control.deadline_ms \
                     ({} ms), which both add to each move's allowed time: raise the deadline \
                     for a hexapod that settles or a camera that answers more slowly",
                    self.camera.frame_timeout_ms, self.control.deadline_ms
                ),
            ));
        }
        let threshold = self.policies.activation_threshold;
        if !(0.0..=1.0).contains(&threshold) {
            return Err(invalid(
                "policies.activation_threshold",
                threshold.to_string(),
                "must lie in [0, 1]",
            ));
        }
        if self.policies.max_parameters == 0 {
            return Err(invalid(
                "policies.max_parameters",
                "0".into(),
                "must be ≥ 1",
            ));
        }
        let (episodes, most) = (
            self.policies.evaluation_episodes,
            self.policies.max_evaluation_episodes,
        );
        if !(1..=MAX_EVALUATION_EPISODES).contains(&most) {
            return Err(invalid(
                "policies.max_evaluation_episodes",
                most.to_string(),
                &format!("must lie in 1..={MAX_EVALUATION_EPISODES}"),
            ));
        }
        if episodes == 0 {
            return Err(invalid(
                "policies.evaluation_episodes",
                "0".into(),
                "must be ≥ 1",
            ));
        }
        if episodes > most {
            return Err(invalid(
                "policies.evaluation_episodes",
                episodes.to_string(),
                &format!("must not exceed policies.max_evaluation_episodes ({most})"),
            ));
        }
        if !(1..=MAX_WORK_CONCURRENCY).contains(&self.work.concurrency) {
            return Err(invalid(
                "work.concurrency",
                self.work.concurrency.to_string(),
                &format!("must lie in 1..={MAX_WORK_CONCURRENCY}"),
            ));
        }
        if self.work.queue_length > MAX_WORK_QUEUE_LENGTH {
            return Err(invalid(
                "work.queue_length",
                self.work.queue_length.to_string(),
                &format!("must lie in 0..={MAX_WORK_QUEUE_LENGTH}"),
            ));
        }
        if self.policies.max_upload_bytes == 0 {
            return Err(invalid(
                "policies.max_upload_bytes",
                "0".into(),
                "must be ≥ 1",
            ));
        }
        if self.http.body_limit_bytes == 0 {
            return Err(invalid("http.body_limit_bytes", "0".into(), "must be ≥ 1"));
        }
        for (key, value) in [
            (
                "access.auth_failure_limit",
                self.access.auth_failure_limit as u64,
            ),
            (
                "access.auth_failure_window_s",
                self.access.auth_failure_window_s,
            ),
            (
                "access.auth_failure_addresses",
                self.access.auth_failure_addresses as u64,
            ),
        ] {
            if value == 0 {
                return Err(invalid(key, "0".into(), "must be ≥ 1"));
            }
        }
        if self.access.auth_failure_window_s > 86_400 {
            return Err(invalid(
                "access.auth_failure_window_s",
                self.access.auth_failure_window_s.to_string(),
                "must be at most 86400 (a day)",
            ));
        }
        if self.http.max_connections < 2 {
            return Err(invalid(
                "http.max_connections",
                self.http.max_connections.to_string(),
                "must be ≥ 2",
            ));
        }
        if !(1..=600_000).contains(&self.http.header_timeout_ms) {
            return Err(invalid(
                "http.header_timeout_ms",
                self.http.header_timeout_ms.to_string(),
                "must lie in 1..=600000 (10 min)",
            ));
        }
        if !(1..=86_400).contains(&self.http.idle_timeout_s) {
            return Err(invalid(
                "http.idle_timeout_s",
                self.http.idle_timeout_s.to_string(),
                "must lie in 1..=86400 (a day)",
            ));
        }
        if let Some(cell_id) = &self.service.cell_id {
            check_cell_id(cell_id)
                .map_err(|reason| invalid("service.cell_id", cell_id.clone(), &reason))?;
        }
        if let Some(url) = &self.fleet.url {
            // The URL may hold a password: name the scheme, not the whole value.
            let shown = url.split_once("://").map_or("…", |(scheme, _)| scheme);
            check_fleet_url(url)
                .map_err(|reason| invalid("fleet.url", format!("{shown}://…"), &reason))?;
        }
        Ok(())
    }

    /// The cell's id in a fleet: `service.cell_id`, else the cell file's name.
    pub fn cell_id(&self) -> String {
        if let Some(cell_id) = &self.service.cell_id {
            return cell_id.clone();
        }
        let stem = self
            .cell
            .as_deref()
            .and_then(|path| path.file_stem())
            .and_then(|stem| stem.to_str());
        match stem {
            Some(stem) if check_cell_id(stem).is_ok() => stem.to_string(),
            Some(stem) => stem
                .chars()
                .map(|c| {
                    if check_cell_id(&c.to_string()).is_ok() {
                        c
                    } else {
                        '-'
                    }
                })
                .take(MAX_CELL_ID_CHARS)
                .collect(),
            None => "phi170".to_string(),
        }
    }

    /// The control period, s: none in fast mode, else the configured one or a camera cycle.
    pub fn step_period_s(&self, camera_rate_hz: f64) -> Option<f64> {
        if self.fast {
            None
        } else {
            Some(
                self.control
                    .step_period_ms
                    .map_or(1.0 / camera_rate_hz, |ms| ms / 1000.0),
            )
        }
    }
}

fn parse_bool(text: &str) -> Option<bool> {
    match text.to_ascii_lowercase().as_str() {
        "1" | "true" | "yes" | "on" => Some(true),
        "0" | "false" | "no" | "off" => Some(false),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vars(pairs: &[(&str, &str)]) -> Vec<(String, String)> {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect()
    }

    #[test]
    fn file_then_environment_override_defaults_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("celld.toml");
        std::fs::write(
            &path,
            "listen = \"0.0.0.0:9000\"\nfast = true\n[control]\ndeadline_ms = 20\n",
        )
        .unwrap();
        let mut config = ServiceConfig::load(Some(&path)).unwrap();
        assert_eq!(config.listen.port(), 9000);
        assert!(config.fast);
        assert_eq!(config.control.deadline_ms, 20.0);
        assert_eq!(
            config.db,
            PathBuf::from("data/celld.db"),
            "untouched default"
        );

        config
            .apply_env(vars(&[
                ("CELLD_LISTEN", "127.0.0.1:7000"),
                ("CELLD_FAST", "false"),
                ("PATH", "/bin"),
            ]))
            .unwrap();
        assert_eq!(config.listen.port(), 7000);
        assert!(!config.fast);
        assert_eq!(config.control.deadline_ms, 20.0, "the file's value stays");
    }

    #[test]
    fn bad_values_are_named() {
        let mut config = ServiceConfig::default();
        let error = config
            .apply_env(vars(&[("CELLD_DEADLINE_MS", "soon")]))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("CELLD_DEADLINE_MS") && error.contains("soon"),
            "{error}"
        );

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("celld.toml");
        std::fs::write(&path, "listen_on = \"x\"\n").unwrap();
        let error = ServiceConfig::load(Some(&path)).unwrap_err().to_string();
        assert!(error.contains("listen_on"), "{error}");

        let error = ServiceConfig::default()
            .apply_env(vars(&[("CELLD_ROBOT_DRIVER", "kuka")]))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("CELLD_ROBOT_DRIVER") && error.contains("kuka"),
            "{error}"
        );
        config = ServiceConfig::default();
        config.robot.driver = RobotDriver::Gcs;
        let error = config.validate().unwrap_err().to_string();
        assert!(error.contains("camera.driver"), "{error}");
        config.camera.driver = CameraDriver::Igtl;
        config.validate().unwrap();
        config.robot.on_target_deadline_ms = 40;
        let error = config.validate().unwrap_err().to_string();
        assert!(
            error.contains("robot.on_target_deadline_ms") && error.contains("control.deadline_ms"),
            "{error}"
        );
        config.control.deadline_ms = 100.0;
        config.validate().unwrap();
        config.camera.frame_timeout_ms = 0;
        let error = config.validate().unwrap_err().to_string();
        assert!(error.contains("camera.frame_timeout_ms"), "{error}");

        // Numbers no cell can use are refused with their key: non-finite, absurd or zero.
        for (variable, value, key) in [
            ("CELLD_DEADLINE_MS", "NaN", "control.deadline_ms"),
            ("CELLD_DEADLINE_MS", "inf", "control.deadline_ms"),
            ("CELLD_DEADLINE_MS", "1e308", "control.deadline_ms"),
            ("CELLD_STEP_PERIOD_MS", "-1", "control.step_period_ms"),
            ("CELLD_STEP_PERIOD_MS", "1e30", "control.step_period_ms"),
            (
                "CELLD_ACTIVATION_THRESHOLD",
                "NaN",
                "policies.activation_threshold",
            ),
            (
                "CELLD_EVALUATION_EPISODES",
                "1000000",
                "policies.evaluation_episodes",
            ),
            (
                "CELLD_MAX_POLICY_PARAMETERS",
                "0",
                "policies.max_parameters",
            ),
        ] {
            let mut config = ServiceConfig::default();
            config.apply_env(vars(&[(variable, value)])).unwrap();
            let error = config.validate().unwrap_err().to_string();
            assert!(error.contains(key) && error.contains(value), "{error}");
        }
        let error = ServiceConfig::default()
            .apply_env(vars(&[("CELLD_MAX_POLICY_PARAMETERS", "-5")]))
            .unwrap_err()
            .to_string();
        assert!(error.contains("CELLD_MAX_POLICY_PARAMETERS"), "{error}");

        config = ServiceConfig::default();
        config.control.deadline_ms = 0.0;
        assert!(
            config
                .validate()
                .unwrap_err()
                .to_string()
                .contains("deadline_ms")
        );
    }

    #[test]
    fn connection_settings_come_from_the_environment_and_are_checked() {
        let mut config = ServiceConfig::default();
        config
            .apply_env(vars(&[
                ("CELLD_MAX_CONNECTIONS", "64"),
                ("CELLD_HEADER_TIMEOUT_MS", "1500"),
                ("CELLD_IDLE_TIMEOUT_S", "2"),
            ]))
            .unwrap();
        assert_eq!(
            (
                config.http.max_connections,
                config.http.header_timeout_ms,
                config.http.idle_timeout_s
            ),
            (64, 1500, 2)
        );
        config.validate().unwrap();
        let error = ServiceConfig::default()
            .apply_env(vars(&[("CELLD_IDLE_TIMEOUT_S", "1.5")]))
            .unwrap_err()
            .to_string();
        assert!(error.contains("CELLD_IDLE_TIMEOUT_S"), "{error}");
        for (setting, value, apply) in [
            (
                "http.max_connections",
                "1",
                (|c: &mut ServiceConfig| c.http.max_connections = 1) as fn(&mut ServiceConfig),
            ),
            ("http.header_timeout_ms", "0", |c| {
                c.http.header_timeout_ms = 0
            }),
            ("http.idle_timeout_s", "86401", |c| {
                c.http.idle_timeout_s = 86_401
            }),
        ] {
            let mut config = ServiceConfig::default();
            apply(&mut config);
            let error = config.validate().unwrap_err().to_string();
            assert!(
                error.contains(setting) && error.contains(&format!("`{value}`")),
                "{error}"
            );
        }
    }

    #[test]
    fn the_documented_example_is_the_defaults() {
        let example = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/celld.example.toml");
        assert_eq!(
            ServiceConfig::load(Some(&example)).unwrap(),
            ServiceConfig::default()
        );
    }

    #[test]
    fn a_fleet_is_joined_with_a_postgres_url_and_a_cell_id() {
        let mut config = ServiceConfig::default();
        assert_eq!(
            (config.fleet.url.as_deref(), config.cell_id().as_str()),
            (None, "phi170")
        );
        config.cell = Some(PathBuf::from("cells/line 3.toml"));
        assert_eq!(config.cell_id(), "line-3");
        config
            .apply_env(vars(&[
                ("CELLD_FLEET_URL", "postgresql://celld:secret@db:5432/fleet"),
                ("CELLD_CELL_ID", "line-3.cell_2"),
            ]))
            .unwrap();
        config.validate().unwrap();
        assert_eq!(config.cell_id(), "line-3.cell_2");

        config.fleet.url = Some("mysql://celld:secret@db/fleet".into());
        let error = config.validate().unwrap_err().to_string();
        assert!(
            error.contains("fleet.url") && error.contains("mysql"),
            "{error}"
        );
        assert!(!error.contains("secret"), "the password stays out: {error}");
        config.fleet.url = Some("db:5432".into());
        assert!(
            config
                .validate()
                .unwrap_err()
                .to_string()
                .contains("postgres://")
        );

        config.fleet.url = None;
        for (cell_id, why) in [
            ("cell 7", "` `"),
            ("", "1 to 64"),
            (&"c".repeat(65), "1 to 64"),
        ] {
            config.service.cell_id = Some(cell_id.to_string());
            let error = config.validate().unwrap_err().to_string();
            assert!(
                error.contains("service.cell_id") && error.contains(why),
                "{error}"
            );
        }
    }

    #[test]
    fn opcua_listens_on_loopback_unless_told_otherwise() {
        let config = ServiceConfig::default();
        assert_eq!(config.opcua.listen.to_string(), "127.0.0.1:4840");

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("celld.toml");
        std::fs::write(
            &path,
            "[opcua]\nlisten = \"off\"\nmanufacturer = \"Acme\"\nserial_number = \"C-17\"\n",
        )
        .unwrap();
        let mut config = ServiceConfig::load(Some(&path)).unwrap();
        assert_eq!(config.opcua.listen, OpcUaListen::Off);
        assert_eq!(config.opcua.manufacturer.as_deref(), Some("Acme"));
        assert_eq!(config.opcua.serial_number.as_deref(), Some("C-17"));
        config
            .apply_env(vars(&[("CELLD_OPCUA_LISTEN", "0.0.0.0:4841")]))
            .unwrap();
        assert_eq!(
            config.opcua.listen,
            OpcUaListen::Address("0.0.0.0:4841".parse().unwrap())
        );

        std::fs::write(&path, "[opcua]\nlisten = \"plc:4840\"\n").unwrap();
        let error = ServiceConfig::load(Some(&path)).unwrap_err().to_string();
        assert!(
            error.contains("`plc:4840` is not off or an address"),
            "{error}"
        );
        let error = config
            .apply_env(vars(&[("CELLD_OPCUA_LISTEN", "on")]))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("CELLD_OPCUA_LISTEN") && error.contains("`on`"),
            "{error}"
        );
    }

    #[test]
    fn period_is_a_camera_cycle_unless_set_or_fast() {
        let mut config = ServiceConfig::default();
        assert_eq!(config.step_period_s(4.0), Some(0.25));
        config.control.step_period_ms = Some(20.0);
        assert_eq!(config.step_period_s(4.0), Some(0.02));
        config.fast = true;
        assert_eq!(config.step_period_s(4.0), None);
    }

    #[test]
    fn background_work_settings_are_read_and_bounded() {
        let mut config = ServiceConfig::default();
        config
            .apply_env(vars(&[
                ("CELLD_WORK_CONCURRENCY", "2"),
                ("CELLD_WORK_QUEUE_LENGTH", "0"),
                ("CELLD_MAX_EVALUATION_EPISODES", "500"),
            ]))
            .unwrap();
        assert_eq!((config.work.concurrency, config.work.queue_length), (2, 0));
        assert_eq!(config.policies.max_evaluation_episodes, 500);
        // The default evaluation (1000 episodes) would be refused by its own bound.
        let error = config.validate().unwrap_err().to_string();
        assert!(
            error.contains("policies.evaluation_episodes") && error.contains("(500)"),
            "{error}"
        );
        config.policies.evaluation_episodes = 500;
        config.validate().unwrap();
        for (key, set) in [
            (
                "work.concurrency",
                (|c: &mut ServiceConfig| c.work.concurrency = 0) as fn(&mut _),
            ),
            ("work.concurrency", |c| c.work.concurrency = 65),
            ("work.queue_length", |c| c.work.queue_length = 10_001),
            ("policies.max_evaluation_episodes", |c| {
                c.policies.max_evaluation_episodes = 0
            }),
        ] {
            let mut bad = config.clone();
            set(&mut bad);
            let error = bad.validate().unwrap_err().to_string();
            assert!(error.contains(key), "{error}");
        }
        let error = config
            .apply_env(vars(&[("CELLD_WORK_QUEUE_LENGTH", "many")]))
            .unwrap_err()
            .to_string();
        assert!(error.contains("CELLD_WORK_QUEUE_LENGTH"), "{error}");
    }
}
