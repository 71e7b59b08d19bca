//! The running service as the OPC UA server sees it: [`Plant`] over the service's context.
//! Its view follows the control thread's status; its events come from the telemetry stream
//! (job ends) and from changes of the alarms; its methods are the same workflows the HTTP
//! API calls, under the caller's token.

use super::plant::{
    Identification, Plant, PlantAlarm, PlantEvent, PlantJob, PlantMethod, PlantUser, PlantView,
    Refused,
};
use crate::cell::CellStatus;
use crate::cell::packml::{Command, PackMlState, UNIT_MODE};
use crate::storage::tokens::{self, Caller, Role};
use crate::workflows::jobs::JobRequest;
use crate::workflows::{self, Context, Error};
use std::time::Duration;
use tokio::sync::{broadcast, watch};

/// How often the view looks at what the status does not announce (a storage fault).
const RESAMPLE: Duration = Duration::from_secs(1);

#[derive(Clone)]
pub struct CellPlant {
    context: Context,
    view: watch::Receiver<PlantView>,
    events: broadcast::Sender<PlantEvent>,
}

impl CellPlant {
    /// Starts the task that keeps the view and the events current; it ends at shutdown.
    pub fn start(context: Context) -> CellPlant {
        let (view_tx, view) = watch::channel(view_of(&context, &context.cell.status()));
        let (events, _) = broadcast::channel(256);
        tokio::spawn(follow(context.clone(), view_tx, events.clone()));
        CellPlant {
            context,
            view,
            events,
        }
    }
}

/// Follows the status, the telemetry and a slow tick until the service stops.
async fn follow(
    context: Context,
    view_tx: watch::Sender<PlantView>,
    events: broadcast::Sender<PlantEvent>,
) {
    let mut status = context.cell.watch();
    let mut telemetry = context.telemetry.subscribe();
    let mut shutdown = context.shutdown.clone();
    let mut tick = tokio::time::interval(RESAMPLE);
    loop {
        tokio::select! {
            changed = status.changed() => if changed.is_err() { return },
            message = telemetry.recv() => match message {
                Ok(message) if message.event == "job" => {
                    if let Some(event) = job_end(&context, &message.data) {
                        let _ = events.send(event);
                    }
                    continue;
                }
                Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => continue,
                Err(broadcast::error::RecvError::Closed) => return,
            },
            _ = tick.tick() => {}
            _ = shutdown.changed() => return,
        }
        let now = view_of(&context, &status.borrow_and_update().clone());
        let before = view_tx.borrow().alarms.clone();
        for alarm in &now.alarms {
            if !before.contains(alarm) {
                let _ = events.send(PlantEvent::Alarm {
                    alarm: alarm.clone(),
                    active: true,
                });
            }
        }
        for alarm in before {
            if !now.alarms.contains(&alarm) {
                let _ = events.send(PlantEvent::Alarm {
                    alarm,
                    active: false,
                });
            }
        }
        view_tx.send_if_modified(|view| {
            let changed = *view != now;
            *view = now;
            changed
        });
    }
}

/// A job's end from its telemetry event (none for a start, or text that does not parse).
fn job_end(context: &Context, data: &str) -> Option<PlantEvent> {
    let event: serde_json::Value = serde_json::from_str(data).ok()?;
    let status = event["status"].as_str()?.to_string();
    if matches!(status.as_str(), "queued" | "running") {
        return None;
    }
    // The control thread counts a job before it reports its end: a good part's cycle time is
    // the counters' last.
    let cycle_time_s = if status == "succeeded" {
        context.cell.status().machine.counters.last_cycle_time_s
    } else {
        None
    };
    Some(PlantEvent::JobEnded {
        id: event["job_id"].as_i64()?,
        status,
        reason: event["failure_reason"].as_str().map(str::to_string),
        steps: event["steps"].as_u64().unwrap_or(0) as u32,
        cycle_time_s,
    })
}

/// The view of the cell now.
fn view_of(context: &Context, status: &CellStatus) -> PlantView {
    let machine = &status.machine;
    let counters = &machine.counters;
    let (stop_reason_code, stop_reason) = machine
        .stop_reason
        .as_ref()
        .map_or((0, String::new()), |r| (r.id, r.message.clone()));
    PlantView {
        state: machine.state.name().to_string(),
        state_number: machine.state.number(),
        unit_mode: UNIT_MODE.0.to_string(),
        unit_mode_number: UNIT_MODE.1,
        stop_reason_code,
        stop_reason,
        processed_count: counters.processed,
        defective_count: counters.defective,
        estop_count: counters.estops,
        last_cycle_time_s: counters.last_cycle_time_s.unwrap_or(0.0),
        mean_cycle_time_s: counters.mean_cycle_time_s().unwrap_or(0.0),
        emergency_stop: status.estop_latched,
        driver_latched: status.driver_latch.is_some(),
        driver_latch_reason: status
            .driver_latch
            .as_ref()
            .map_or(String::new(), |l| format!("{}: {}", l.code, l.reason)),
        job: status.job.as_ref().map(|job| PlantJob {
            id: job.id,
            controller: job.controller.clone(),
            step: job.step,
            pose_error_mm: job.pose_error_mm,
            sigma_mm: job.sigma_mm,
        }),
        alarms: alarms(context, status),
    }
}

/// The alarms standing now, gravest first: the e-stop latch, the driver's latch, a storage
/// fault; and the warning of a job waiting for its camera.
fn alarms(context: &Context, status: &CellStatus) -> Vec<PlantAlarm> {
    let mut alarms = Vec::new();
    if status.estop_latched {
        alarms.push(PlantAlarm {
            code: "estop".into(),
            severity: 1000,
            message: "the e-stop is latched: reset the cell once it is safe".into(),
            warning: false,
        });
    }
    if let Some(latch) = &status.driver_latch {
        alarms.push(PlantAlarm {
            code: latch.code.clone(),
            severity: 900,
            message: format!("the robot driver is latched: {}", latch.reason),
            warning: false,
        });
    }
    if let Some(fault) = context.db.health.fault() {
        alarms.push(PlantAlarm {
            code: "storage".into(),
            severity: 800,
            message: format!(
                "the database takes no writes since {}: {}",
                fault.since, fault.error
            ),
            warning: false,
        });
    }
    if status.machine.state == PackMlState::Suspended {
        alarms.push(PlantAlarm {
            code: "camera_stale".into(),
            severity: 300,
            message: "the running job waits for a fresh camera frame".into(),
            warning: true,
        });
    }
    alarms
}

impl Plant for CellPlant {
    fn watch(&self) -> watch::Receiver<PlantView> {
        self.view.clone()
    }

    fn events(&self) -> broadcast::Receiver<PlantEvent> {
        self.events.subscribe()
    }

    fn identification(&self) -> Identification {
        let cell = &self.context.cell_config;
        let plate = &self.context.settings.opcua;
        Identification {
            manufacturer: plate.manufacturer.clone().unwrap_or_else(|| "celld".into()),
            model: "6-SPS shaft-in-bore assembly cell".into(),
            product_instance_uri: format!("urn:celld:cell:{}", cell.name),
            serial_number: plate
                .serial_number
                .clone()
                .unwrap_or_else(|| cell.config_hash()),
            software_revision: env!("CARGO_PKG_VERSION").into(),
            cell_name: cell.name.clone(),
        }
    }

    /// The password is an API token; the user name is not checked (the token names its
    /// holder, and that name goes to the audit log).
    async fn sign_in(&self, _user: &str, password: &str) -> Result<PlantUser, Refused> {
        let key = tokens::hash(password.trim());
        let caller = caller(&self.context, &key).await?;
        Ok(PlantUser {
            name: caller.name,
            may_operate: caller.role >= Role::Operator,
            key,
        })
    }

    /// Each call checks the token again (cached as for HTTP): one revoked or expired since the
    /// session signed in calls nothing.
    async fn call(&self, user: &PlantUser, method: PlantMethod) -> Result<Option<i64>, Refused> {
        let now = caller(&self.context, &user.key).await?;
        let user = PlantUser {
            name: now.name,
            may_operate: now.role >= Role::Operator,
            key: user.key.clone(),
        };
        if !user.may_operate {
            return Err(Refused::NotAllowed(format!(
                "this needs the operator role; token `{}` may only watch",
                user.name
            )));
        }
        let context = &self.context;
        let by = user.name.as_str();
        let done = match method {
            PlantMethod::Start { controller, seed } => {
                let request = JobRequest {
                    controller,
                    seed,
                    initial: None,
                    demonstration: false,
                    override_gate: None,
                };
                return workflows::jobs::create(context, request, by)
                    .await
                    .map(|job| Some(job.id))
                    .map_err(refused);
            }
            PlantMethod::Stop => workflows::cell::command(context, by, Command::Stop).await,
            PlantMethod::Abort => workflows::cell::estop(context, by).await,
            PlantMethod::Reset => workflows::cell::command(context, by, Command::Reset).await,
            PlantMethod::Clear => workflows::cell::command(context, by, Command::Clear).await,
        };
        done.map(|()| None).map_err(refused)
    }
}

/// The caller a token's hash names, if the token stands.
async fn caller(context: &Context, key: &str) -> Result<Caller, Refused> {
    use workflows::tokens::AuthError;
    match workflows::tokens::authenticate_hash(context, key).await {
        Ok(caller) => Ok(caller),
        Err(AuthError::Storage(e)) => Err(Refused::Unavailable(e)),
        Err(refused) => Err(Refused::BadIdentity(refused.to_string())),
    }
}

/// A workflow's refusal as OPC UA tells it.
fn refused(error: Error) -> Refused {
    let message = error.to_string();
    match error {
        Error::Conflict(_) => Refused::InvalidState(message),
        Error::BadRequest(_) | Error::Invalid { .. } | Error::NotFound(_) => {
            Refused::InvalidArgument(message)
        }
        Error::Unavailable(_)
        | Error::Busy { .. }
        | Error::Storage(_)
        | Error::StorageUnavailable(_)
        | Error::NoFleet(_)
        | Error::FleetUnavailable(_)
        | Error::Internal(_) => Refused::Unavailable(message),
    }
}
