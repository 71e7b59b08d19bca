//! The service's workflows: what happens when an operator or an admin asks for something, and
//! what runs in the background afterwards: jobs queued on the cell, the e-stop latch kept in
//! storage, policies registered, evaluated and activated behind the gate, demonstrations
//! imported, training runs driven to a candidate policy, tokens made. They know storage, the control
//! thread's handle and the pure libraries, and nothing of HTTP: `http` translates requests
//! into these calls and [`Error`] into statuses; `app` starts the background ones.

pub mod cell;
pub mod demonstrations;
pub mod fleet;
pub mod gate;
pub mod jobs;
pub mod policies;
pub mod queue;
pub mod tokens;
pub mod training;

use crate::cell::CellHandle;
use crate::config::cell::CellConfig;
use crate::config::service::ServiceConfig;
use crate::metrics::Metrics;
use crate::storage::Db;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};
use tokio::sync::{broadcast, watch};

/// One telemetry event, serialised once for every subscriber.
#[derive(Debug, Clone)]
pub struct TelemetryMessage {
    /// SSE event name: `step`, `job`, `cell`, `machine` or `lagged`.
    pub event: &'static str,
    pub data: Arc<str>,
}

/// Everything a workflow may need, cheap to clone: the service's one shared state.
#[derive(Clone)]
pub struct Context {
    pub db: Db,
    pub cell: CellHandle,
    pub cell_config: Arc<CellConfig>,
    pub settings: Arc<ServiceConfig>,
    pub metrics: Metrics,
    pub telemetry: broadcast::Sender<TelemetryMessage>,
    /// False once shutdown began: no new jobs.
    pub accepting: Arc<AtomicBool>,
    /// Becomes true at shutdown, so open streams end.
    pub shutdown: watch::Receiver<bool>,
    /// Callers already looked up, by token hash; a revocation evicts its token
    /// ([`tokens::authenticate`] rereads each entry's row after [`tokens::RECHECK`]).
    pub known_callers: Arc<RwLock<HashMap<String, tokens::KnownCaller>>>,
    /// The one queue evaluations and training runs wait in, and their compute threads.
    pub work: queue::WorkQueue,
    /// Held while the e-stop latch is stored (see [`cell::store_latch`]).
    pub latch_writes: Arc<tokio::sync::Mutex<()>>,
    /// The fleet this cell replicates to, if it is in one.
    pub fleet: Option<Arc<fleet::FleetLink>>,
}

impl Context {
    /// Whether a new job would be taken: the service is not shutting down, neither the
    /// e-stop nor the driver is latched, and the machine state takes jobs (not Stopped or
    /// Aborted).
    pub fn accepting_jobs(&self) -> bool {
        let status = self.cell.status();
        !self.shutting_down()
            && !status.estop_latched
            && status.driver_latch.is_none()
            && status.machine.state.accepts_jobs()
    }

    pub fn shutting_down(&self) -> bool {
        !self.accepting.load(Ordering::SeqCst)
    }
}

/// Why a workflow refused or failed, with the numbers and names that say what is wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// The request itself is malformed (a bad name or query value).
    #[error("{0}")]
    BadRequest(String),
    /// Well formed, but a value is out of its range or the content fails its checks; `code`
    /// names the check (`invalid`, or a policy file's own code such as `missing_tensor`).
    #[error("{message}")]
    Invalid { code: &'static str, message: String },
    #[error("{0}")]
    NotFound(String),
    /// The cell's or the service's state does not allow it now.
    #[error("{0}")]
    Conflict(String),
    /// The service cannot do it at all now (shutting down, the control thread gone).
    #[error("{0}")]
    Unavailable(String),
    /// Too much is waiting already; worth asking again in about `retry_after_s` seconds.
    #[error("{message}")]
    Busy { message: String, retry_after_s: u64 },
    #[error("storage: {0}")]
    Storage(String),
    /// The database takes no writes now (a full disk, an I/O error): nothing was stored; the
    /// same request may pass once the fault clears.
    #[error("{0}")]
    StorageUnavailable(String),
    /// The cell is in no fleet (no `fleet.url`).
    #[error("{0}")]
    NoFleet(String),
    /// The fleet's database cannot be reached or refused; the cell itself goes on.
    #[error("{0}")]
    FleetUnavailable(String),
    #[error("{0}")]
    Internal(String),
}

impl Error {
    pub fn bad_request(message: impl Into<String>) -> Self {
        Error::BadRequest(message.into())
    }

    /// [`Error::Invalid`] with the plain `invalid` code.
    pub fn unprocessable(message: impl Into<String>) -> Self {
        Error::Invalid {
            code: "invalid",
            message: message.into(),
        }
    }

    pub fn not_found(message: impl Into<String>) -> Self {
        Error::NotFound(message.into())
    }

    pub fn conflict(message: impl Into<String>) -> Self {
        Error::Conflict(message.into())
    }

    pub fn unavailable(message: impl Into<String>) -> Self {
        Error::Unavailable(message.into())
    }
}

impl From<sqlx::Error> for Error {
    fn from(error: sqlx::Error) -> Self {
        if crate::storage::is_fault(&error) {
            Error::StorageUnavailable(crate::storage::unavailable_message(&error))
        } else {
            Error::Storage(error.to_string())
        }
    }
}

impl From<queue::QueueError> for Error {
    fn from(error: queue::QueueError) -> Self {
        match error {
            queue::QueueError::Full { retry_after_s, .. } => Error::Busy {
                message: error.to_string(),
                retry_after_s,
            },
            queue::QueueError::Closed => Error::Unavailable(error.to_string()),
        }
    }
}

impl From<crate::cell::task::CellStopped> for Error {
    fn from(error: crate::cell::task::CellStopped) -> Self {
        Error::Unavailable(error.to_string())
    }
}

pub type Result<T> = std::result::Result<T, Error>;

/// Runs CPU-bound work of a request (parsing an uploaded file of up to the body limit) on
/// tokio's blocking pool. The async workers may be a single thread when `control.cpu` keeps
/// the service off the control CPU, and an e-stop request must not wait behind a parse.
pub async fn off_the_runtime<T: Send + 'static>(
    work: impl FnOnce() -> Result<T> + Send + 'static,
) -> Result<T> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| Error::Internal(format!("the request's work stopped: {e}")))?
}
