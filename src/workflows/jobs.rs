//! Jobs: queued on the cell after the checks a job must pass, cancelled, waited for.

use super::{Context, Error, Result, gate};
use crate::cell::{CellCommand, ControllerSource, JobEnd, JobSpec, JobStatus};
use crate::policy;
use crate::sim::InitialConditions;
use crate::storage::jobs::{self, Job, NewJob};
use crate::storage::{audit, policies};
use rand::Rng;
use serde_json::json;
use std::time::Duration;

/// Largest initial offset and orientation error a job may ask for (the workspace the twin's
/// protocol covers; Table 2's widest is 50 mm and 9 deg).
const MAX_INITIAL_POS_MM: f64 = 200.0;
const MAX_INITIAL_ORI_DEG: f64 = 20.0;

/// Jobs waiting at most: each holds its controller (a policy's weights) in memory until it runs.
const MAX_QUEUED_JOBS: usize = 100;

/// What an operator asks of a new job.
#[derive(Debug, Clone, PartialEq)]
pub struct JobRequest {
    /// `active`, a built-in controller, a bundled policy or `policy:<id>`.
    pub controller: String,
    /// None: a random seed, stored with the job.
    pub seed: Option<u64>,
    /// Initial offset (mm) and orientation error (deg); none: the cell file's.
    pub initial: Option<(f64, f64)>,
    pub demonstration: bool,
    /// An admin's reason to run a policy the gate ([`gate`]) refuses; the caller has checked
    /// the role. Kept in the audit log when the gate was shut.
    pub override_gate: Option<String>,
}

/// Longest reason an override may give, characters.
const MAX_OVERRIDE_REASON: usize = 500;

/// Checks a job, stores it and queues it on the control thread.
pub async fn create(context: &Context, request: JobRequest, by: &str) -> Result<Job> {
    if context.shutting_down() {
        return Err(Error::unavailable("the service is shutting down"));
    }
    let status = context.cell.status();
    if status.estop_latched {
        return Err(Error::conflict(
            "the e-stop is latched: reset the cell (POST /api/cell/reset) first",
        ));
    }
    if let Some(latch) = &status.driver_latch {
        return Err(Error::conflict(format!(
            "the robot driver is latched ({}: {}): reset the cell (POST /api/cell/reset) once the \
             hardware is ready",
            latch.code, latch.reason
        )));
    }
    if !status.machine.state.accepts_jobs() {
        return Err(Error::conflict(format!(
            "the cell is {}: reset it (POST /api/cell/reset) first",
            status.machine.state.name()
        )));
    }
    let queued = status.queue.len();
    if queued >= MAX_QUEUED_JOBS {
        return Err(Error::conflict(format!(
            "{queued} jobs are waiting already (at most {MAX_QUEUED_JOBS}): wait or cancel some"
        )));
    }
    let reason = match &request.override_gate {
        None => None,
        Some(reason) => {
            let reason = reason.trim();
            if reason.is_empty() || reason.chars().count() > MAX_OVERRIDE_REASON {
                return Err(Error::unprocessable(format!(
                    "override_gate.reason must be 1 to {MAX_OVERRIDE_REASON} characters"
                )));
            }
            Some(reason)
        }
    };
    let resolved = resolve_controller(context, &request.controller).await?;
    let (name, source, policy_id) = (resolved.name, resolved.source, resolved.policy_id);
    if let (Some(why), None) = (&resolved.gate_shut, reason) {
        return Err(Error::conflict(format!(
            "{why}; until then it may not drive a job (an admin may override: \
             \"override_gate\": {{\"reason\": \"...\"}})"
        )));
    }
    let defaults = InitialConditions::from_cell(&context.cell_config);
    let initial = match request.initial {
        None => defaults,
        Some((pos_mm, ori_deg)) => {
            check_range("initial.pos_mm", pos_mm, MAX_INITIAL_POS_MM)?;
            check_range("initial.ori_deg", ori_deg, MAX_INITIAL_ORI_DEG)?;
            InitialConditions {
                offset_mm: pos_mm,
                orientation_deg: ori_deg,
            }
        }
    };
    let seed = request.seed.unwrap_or_else(|| rand::rng().random());
    let job = jobs::insert(
        &context.db,
        &NewJob {
            controller: name,
            policy_id,
            seed,
            initial_pos_mm: initial.offset_mm,
            initial_ori_deg: initial.orientation_deg,
            demonstration: request.demonstration,
            created_by: by.to_string(),
        },
    )
    .await?;
    if let (Some(why), Some(reason)) = (&resolved.gate_shut, reason) {
        audit::record(
            &context.db,
            by,
            "job.override_gate",
            json!({
                "job_id": job.id,
                "policy_id": policy_id,
                "controller": job.controller,
                "reason": reason,
                "gate": why,
            }),
        )
        .await?;
    }
    let sent = context.cell.send(CellCommand::Enqueue(JobSpec {
        id: job.id,
        controller: source,
        seed,
        initial,
        demonstration: job.demonstration,
    }));
    if let Err(stopped) = sent {
        // No thread will ever run it: close it now rather than leave it `queued`.
        let end = JobEnd::unstarted(JobStatus::Failed, "control_stopped");
        jobs::mark_ended(&context.db.writer, job.id, &end).await?;
        return Err(stopped.into());
    }
    Ok(job)
}

/// Cancels a queued or running job; answers with the job once its end is stored.
pub async fn cancel(context: &Context, id: i64) -> Result<Job> {
    let job = find(context, id).await?;
    let found = context
        .cell
        .ask(|reply| CellCommand::Cancel { job_id: id, reply })
        .await?;
    if !found {
        return Err(Error::conflict(format!(
            "job {id} is {} and can no longer be cancelled",
            job.status
        )));
    }
    wait_until_final(context, id).await
}

/// The job with `id`, or [`Error::NotFound`].
pub async fn find(context: &Context, id: i64) -> Result<Job> {
    jobs::get(&context.db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no job with id {id}")))
}

/// The job once the storage writer has recorded its end (it does so within milliseconds of
/// the control thread's answer), or as it stands after two seconds.
pub async fn wait_until_final(context: &Context, id: i64) -> Result<Job> {
    for _ in 0..200 {
        let job = find(context, id).await?;
        if JobStatus::parse(&job.status).is_some_and(|s| s.is_final()) {
            return Ok(job);
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    find(context, id).await
}

fn check_range(field: &str, value: f64, max: f64) -> Result<()> {
    if value.is_finite() && (0.0..=max).contains(&value) {
        Ok(())
    } else {
        Err(Error::unprocessable(format!(
            "{field} = {value} is outside 0..={max}"
        )))
    }
}

/// The controller a job names, resolved.
struct Resolved {
    /// As stored with the job.
    name: String,
    /// What the control thread builds it from.
    source: ControllerSource,
    /// When it is a registered policy.
    policy_id: Option<i64>,
    /// Why the gate refuses that policy, if it does.
    gate_shut: Option<String>,
}

/// The controller a job names, with the gate's word on a registered policy: `active` is the
/// active policy (it passed the gate, or an admin forced it), else `control.active_controller`,
/// which, naming `policy:<id>`, goes through the gate as a job naming it does.
async fn resolve_controller(context: &Context, requested: &str) -> Result<Resolved> {
    let configured = requested == "active";
    let name = if configured {
        match policies::active(&context.db).await? {
            Some((id, bytes)) => {
                return Ok(Resolved {
                    name: format!("policy:{id}"),
                    source: ControllerSource::Policy { id, bytes },
                    policy_id: Some(id),
                    gate_shut: None,
                });
            }
            None => context.settings.control.active_controller.clone(),
        }
    } else {
        requested.to_string()
    };
    if let Some(id) = name.strip_prefix("policy:") {
        let id: i64 = id.parse().map_err(|_| {
            Error::unprocessable(format!("controller `{name}`: `policy:` takes a policy id"))
        })?;
        let policy = policies::get(&context.db, id)
            .await?
            .ok_or_else(|| Error::not_found(format!("no policy with id {id}")))?;
        let gate_shut = gate::may_drive(context, &policy).await?.err().map(|why| {
            if configured {
                format!("no policy is active and control.active_controller names {name}: {why}")
            } else {
                why
            }
        });
        let bytes = policies::file(&context.db, id)
            .await?
            .ok_or_else(|| Error::not_found(format!("no policy with id {id}")))?;
        return Ok(Resolved {
            name,
            source: ControllerSource::Policy { id, bytes },
            policy_id: Some(id),
            gate_shut,
        });
    }
    policy::check_known(&name).map_err(|e| Error::unprocessable(e.to_string()))?;
    Ok(Resolved {
        name: name.clone(),
        source: ControllerSource::Builtin(name),
        policy_id: None,
        gate_shut: None,
    })
}

/// At start: why the gate would refuse the policy `control.active_controller` names, if it
/// names one and the gate is shut for it now (a job asking for `active` while no policy is
/// active would be refused for that reason).
pub async fn configured_policy_refused(context: &Context) -> Result<Option<String>> {
    let name = &context.settings.control.active_controller;
    if !name.starts_with("policy:") || policies::active(&context.db).await?.is_some() {
        return Ok(None);
    }
    match resolve_controller(context, "active").await {
        Ok(resolved) => Ok(resolved.gate_shut),
        Err(Error::NotFound(why) | Error::Invalid { message: why, .. }) => {
            Ok(Some(format!("control.active_controller = {name}: {why}")))
        }
        Err(other) => Err(other),
    }
}
