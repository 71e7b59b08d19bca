//! The seam between the OPC UA server and the cell: what the plant sees ([`PlantView`],
//! [`PlantEvent`], [`Identification`]) and what it may do ([`Plant::sign_in`], [`Plant::call`]).
//! The service implements [`Plant`] over its own state; the server knows nothing else of it.

use std::future::Future;

/// What the plant sees of the cell now; the server mirrors it into variables.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PlantView {
    /// PackML state name as OPC 30050 spells it ("Idle", "Execute", "Aborted", ...) and its
    /// ISA-TR88 number (Clearing 1, Stopped 2, Starting 3, Idle 4, Suspended 5, Execute 6,
    /// Stopping 7, Aborting 8, Aborted 9, Holding 10, Held 11, Unholding 12, Suspending 13,
    /// Unsuspending 14, Resetting 15, Completing 16, Complete 17).
    pub state: String,
    pub state_number: u32,
    /// PackML unit mode name and number ("Production", 1).
    pub unit_mode: String,
    pub unit_mode_number: u32,
    /// Why the cell last stopped or aborted: a code (0: none) and a message.
    pub stop_reason_code: i32,
    pub stop_reason: String,
    /// Parts processed (PackML ProdProcessedCount).
    pub processed_count: u64,
    /// Parts found defective (PackML ProdDefectiveCount).
    pub defective_count: u64,
    pub estop_count: u64,
    /// The last part's cycle time, s; 0 before the first part.
    pub last_cycle_time_s: f64,
    /// Mean cycle time, s.
    pub mean_cycle_time_s: f64,
    /// The e-stop latch.
    pub emergency_stop: bool,
    pub driver_latched: bool,
    pub driver_latch_reason: String,
    pub job: Option<PlantJob>,
    /// Active alarms and warnings.
    pub alarms: Vec<PlantAlarm>,
}

/// The job running now.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PlantJob {
    pub id: i64,
    pub controller: String,
    pub step: u32,
    /// Pose error, mm.
    pub pose_error_mm: f64,
    /// The estimate's standard deviation, mm.
    pub sigma_mm: f64,
}

/// An active alarm or warning.
#[derive(Debug, Clone, PartialEq)]
pub struct PlantAlarm {
    pub code: String,
    /// 1..=1000, OPC UA severity.
    pub severity: u16,
    pub message: String,
    pub warning: bool,
}

/// Something that happened, for OPC UA events.
#[derive(Debug, Clone, PartialEq)]
pub enum PlantEvent {
    JobEnded {
        id: i64,
        status: String,
        reason: Option<String>,
        steps: u32,
        /// s
        cycle_time_s: Option<f64>,
    },
    Alarm {
        alarm: PlantAlarm,
        active: bool,
    },
}

/// The cell's name plate (OPC 40001-1 MachineIdentification).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Identification {
    pub manufacturer: String,
    pub model: String,
    pub product_instance_uri: String,
    pub serial_number: String,
    pub software_revision: String,
    pub cell_name: String,
}

/// A signed-in user.
#[derive(Debug, Clone, PartialEq)]
pub struct PlantUser {
    pub name: String,
    /// Operators may call Start, Stop, Abort, Reset and Clear; others only read.
    pub may_operate: bool,
    /// What the plant knows the credential by, not a secret and without `:` (celld: the
    /// token's hash): the session keeps it and each call hands it back, so that a token
    /// revoked since sign-in calls nothing.
    pub key: String,
}

/// A command from the plant.
#[derive(Debug, Clone, PartialEq)]
pub enum PlantMethod {
    Start {
        controller: String,
        /// None: a random seed.
        seed: Option<u64>,
    },
    Stop,
    Abort,
    Reset,
    Clear,
}

/// Why a call or sign-in was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Refused {
    /// Unknown user or wrong token: BadUserAccessDenied at sign-in.
    #[error("{0}")]
    BadIdentity(String),
    /// Role too low: BadUserAccessDenied.
    #[error("{0}")]
    NotAllowed(String),
    /// The cell's state does not allow it: BadInvalidState.
    #[error("{0}")]
    InvalidState(String),
    /// Bad controller or seed: BadInvalidArgument.
    #[error("{0}")]
    InvalidArgument(String),
    /// Storage or hardware: BadResourceUnavailable.
    #[error("{0}")]
    Unavailable(String),
}

/// The cell as the OPC UA server sees it.
pub trait Plant: Clone + Send + Sync + 'static {
    /// The view now and every change after (a tokio watch channel).
    fn watch(&self) -> tokio::sync::watch::Receiver<PlantView>;
    /// Events as they happen (tokio broadcast; a lagged receiver skips).
    fn events(&self) -> tokio::sync::broadcast::Receiver<PlantEvent>;
    fn identification(&self) -> Identification;
    /// User name and password sign-in; the password is a celld API token.
    fn sign_in(
        &self,
        user: &str,
        password: &str,
    ) -> impl Future<Output = Result<PlantUser, Refused>> + Send;
    /// A method call by a signed-in user (the server has already refused non-operators). Start
    /// answers the job id.
    fn call(
        &self,
        user: &PlantUser,
        method: PlantMethod,
    ) -> impl Future<Output = Result<Option<i64>, Refused>> + Send;
}
