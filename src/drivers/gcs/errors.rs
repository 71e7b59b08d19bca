//! The GCS controller's error codes (what `ERR?` answers) and the driver's typed errors.

use super::protocol::AnswerError;

/// `ERR?`'s answer when nothing went wrong.
pub const NO_ERROR: i32 = 0;
/// Parameter syntax error.
pub const PARAMETER_SYNTAX: i32 = 1;
/// Unknown command.
pub const UNKNOWN_COMMAND: i32 = 2;
/// A move on an unreferenced axis, or with the servo off.
pub const MOVE_WITHOUT_REFERENCE_OR_SERVO: i32 = 5;
/// Position out of limits (for a hexapod: a pose outside its workspace).
pub const POSITION_OUT_OF_LIMITS: i32 = 7;
/// Velocity out of limits.
pub const VELOCITY_OUT_OF_LIMITS: i32 = 8;
/// Pivot point set while U, V and W are not all 0.
pub const PIVOT_WHILE_ROTATED: i32 = 9;
/// The controller was stopped by a command (`STP`, `HLT`, `#24`).
pub const STOPPED: i32 = 10;
/// Invalid axis identifier.
pub const INVALID_AXIS: i32 = 15;
/// Parameter out of range.
pub const PARAMETER_OUT_OF_RANGE: i32 = 17;
/// Incorrect number of parameters.
pub const WRONG_PARAMETER_COUNT: i32 = 24;
/// Invalid floating point number.
pub const INVALID_NUMBER: i32 = 25;
/// A command not allowed for the stage (for a hexapod's axes: `RON`).
pub const NOT_FOR_STAGE: i32 = 34;
/// Referencing failed.
pub const REFERENCING_FAILED: i32 = 45;
/// A command not allowed while the axis is moving.
pub const NOT_WHILE_MOVING: i32 = 53;
/// Unknown parameter id.
pub const UNKNOWN_PARAMETER: i32 = 54;
/// Wrong password for a command level (`CCL`).
pub const INVALID_PASSWORD: i32 = 56;
/// A parameter protected at the current command level.
pub const PARAMETER_PROTECTED: i32 = 60;
/// A command names a coordinate system that does not exist.
pub const COORDINATE_SYSTEM_MISSING: i32 = 530;
/// A coordinate system defined while the hexapod moves.
pub const COORDINATE_SYSTEM_WHILE_MOVING: i32 = 536;
/// A coordinate system that cannot be changed.
pub const COORDINATE_SYSTEM_WRITE_PROTECTED: i32 = 546;

/// What PI's manuals call a code, for the codes a hexapod controller sends in operation.
pub fn describe(code: i32) -> &'static str {
    match code {
        NO_ERROR => "no error",
        PARAMETER_SYNTAX => "parameter syntax error",
        UNKNOWN_COMMAND => "unknown command",
        3 => "command length out of limits or command buffer overrun",
        MOVE_WITHOUT_REFERENCE_OR_SERVO => {
            "unallowable move attempted on unreferenced axis, or move attempted with servo off"
        }
        POSITION_OUT_OF_LIMITS => "position out of limits",
        VELOCITY_OUT_OF_LIMITS => "velocity out of limits",
        PIVOT_WHILE_ROTATED => "attempt to set pivot point while U, V and W not all 0",
        STOPPED => "controller was stopped by command",
        INVALID_AXIS => "invalid axis identifier",
        PARAMETER_OUT_OF_RANGE => "parameter out of range",
        22 => "axis identifier specified more than once",
        WRONG_PARAMETER_COUNT => "incorrect number of parameters",
        INVALID_NUMBER => "invalid floating point number",
        26 => "parameter missing",
        NOT_FOR_STAGE => "command not allowed for selected stage(s)",
        REFERENCING_FAILED => "referencing failed",
        NOT_WHILE_MOVING => "command is not allowed while the affected axis is in motion",
        UNKNOWN_PARAMETER => "unknown parameter",
        INVALID_PASSWORD => "password invalid",
        PARAMETER_PROTECTED => "protected parameter: current command level (CCL) too low",
        COORDINATE_SYSTEM_MISSING => "a command refers to a coordinate system that does not exist",
        COORDINATE_SYSTEM_WHILE_MOVING => {
            "coordinate system cannot be defined as long as the hexapod is in motion"
        }
        COORDINATE_SYSTEM_WRITE_PROTECTED => "coordinate system is write protected",
        -1024 => "motion error: position error too large, servo switched off automatically",
        _ => "unknown controller error",
    }
}

/// Why the GCS driver could not do what it was asked. Every variant names its numbers.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GcsError {
    /// The controller reported an error code (`ERR?`).
    #[error("controller error {code} after `{command}`: {message}")]
    Controller {
        code: i32,
        message: &'static str,
        command: String,
    },
    /// No TCP connection could be made.
    #[error("cannot connect to the controller at {address}: {reason}")]
    Connect { address: String, reason: String },
    /// The controller did not answer in time.
    #[error("`{command}`: no answer within {timeout_ms} ms")]
    Timeout { command: String, timeout_ms: u64 },
    /// The connection broke (closed by the controller, reset, or a write failed).
    #[error("`{command}`: the connection to the controller dropped ({reason})")]
    Dropped { command: String, reason: String },
    /// An answer the driver cannot read.
    #[error("`{command}`: unexpected answer {answer:?}: {problem}")]
    Answer {
        command: String,
        answer: String,
        problem: AnswerError,
    },
    /// The platform was not on target within the deadline; the driver stopped it.
    #[error("not on target within {deadline_ms} ms of `MOV`; stopped")]
    Deadline { deadline_ms: u64 },
    /// An axis is not referenced (`FRF?`) or its servo is off (`SVO?`).
    #[error("axis {axis} is not {what}: reference the hexapod and switch its servos on first")]
    NotReady {
        axis: &'static str,
        what: &'static str,
    },
    /// The controller turns U V W about a pivot point other than the platform's origin; the
    /// driver commands poses about the origin.
    #[error(
        "the pivot point is R={r_mm} S={s_mm} T={t_mm} mm; celld commands poses about 0 0 0: send SPI R 0 S 0 T 0 with U V W at 0"
    )]
    Pivot { r_mm: f64, s_mm: f64, t_mm: f64 },
    /// The controller says the platform is elsewhere than the cell last put it: a move the
    /// cell gave up on may have run, or someone moved it. The driver latches.
    #[error(
        "the platform is {distance_mm:.4} mm and {angle_deg:.4} deg from where the cell last put it \
         (tolerance {tolerance_mm} mm, {tolerance_deg} deg): a move the cell gave up on may have \
         run, or the platform was moved; check the cell, then reset"
    )]
    PositionMismatch {
        distance_mm: f64,
        angle_deg: f64,
        tolerance_mm: f64,
        tolerance_deg: f64,
    },
    /// The driver lost the controller since the last operator reset: it moves nothing until
    /// the next one.
    #[error(
        "the controller connection was lost ({cause}); the robot moves again only after an operator reset"
    )]
    AwaitingReset { cause: String },
}

impl GcsError {
    /// The controller error for `code` after `command`.
    pub fn controller(code: i32, command: &str) -> GcsError {
        GcsError::Controller {
            code,
            message: describe(code),
            command: command.trim().to_string(),
        }
    }

    /// Whether the connection is gone (a reconnect is needed before the next command).
    pub fn is_connection_lost(&self) -> bool {
        matches!(self, GcsError::Dropped { .. } | GcsError::Timeout { .. })
    }

    /// Whether the driver stops trusting the controller until an operator reset: the
    /// connection is gone, or the platform is not where the cell put it.
    pub fn latches(&self) -> bool {
        self.is_connection_lost() || matches!(self, GcsError::PositionMismatch { .. })
    }

    /// A short stable name for telemetry and hold reasons.
    pub fn code(&self) -> &'static str {
        match self {
            GcsError::Controller { .. } => "controller_error",
            GcsError::Connect { .. } => "controller_unreachable",
            GcsError::Timeout { .. } => "controller_timeout",
            GcsError::Dropped { .. } => "controller_dropped",
            GcsError::Answer { .. } => "controller_answer",
            GcsError::Deadline { .. } => "on_target_deadline",
            GcsError::NotReady { .. } | GcsError::Pivot { .. } => "controller_not_ready",
            GcsError::PositionMismatch { .. } => "position_mismatch",
            GcsError::AwaitingReset { .. } => "awaiting_reset",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_controller_error_names_its_code_and_meaning() {
        let error = GcsError::controller(MOVE_WITHOUT_REFERENCE_OR_SERVO, "MOV X 1\n");
        assert_eq!(
            error.to_string(),
            "controller error 5 after `MOV X 1`: unallowable move attempted on unreferenced \
             axis, or move attempted with servo off"
        );
        assert_eq!(describe(12345), "unknown controller error");
        assert!(!error.is_connection_lost());
        assert!(
            GcsError::Timeout {
                command: "POS?".into(),
                timeout_ms: 50
            }
            .is_connection_lost()
        );
    }
}
