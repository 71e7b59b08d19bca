//! Policies: registered after the file checks, evaluated in the twin in the background,
//! activated behind the evaluation gate; the bundled policy registered and evaluated at start.

use super::queue::{NoTurn, Ticket, WorkId, WorkKind};
use super::{Context, Error, Result, off_the_runtime};
use crate::policy::Controller;
use crate::policy::eval;
use crate::policy::learned::{LearnedPolicy, LearnedPolicyFile};
use crate::policy::shield::RuleSelection;
use crate::sim::randomise::CellRanges;
use crate::sim::{EnvOptions, MAX_MISMATCH_SCALE, Mismatch};
use crate::storage::policies::{self, EvaluatedOn, Evaluation, NewPolicy, Policy};
use crate::storage::{Db, audit, tokens};
use serde_json::{Value, json};
use std::sync::Arc;
use std::sync::atomic::Ordering;

/// Checks a policy file (hierarchical or flat, by its `format` metadata) as an upload is checked,
/// and stores it (or finds the same bytes).
pub async fn register(db: &Db, name: &str, bytes: Vec<u8>, by: &str) -> Result<(Policy, bool)> {
    let bytes: Arc<[u8]> = bytes.into();
    let checked = bytes.clone();
    let (metadata, shapes, sha256) = off_the_runtime(move || {
        let file = LearnedPolicyFile::from_bytes(&checked).map_err(|e| Error::Invalid {
            code: e.code(),
            message: e.to_string(),
        })?;
        let shapes: serde_json::Map<String, Value> = file
            .shapes()
            .into_iter()
            .map(|(name, shape)| (name, json!(shape)))
            .collect();
        Ok((
            json!(file.raw_metadata()),
            Value::Object(shapes),
            tokens::hash_bytes(&checked),
        ))
    })
    .await?;
    Ok(policies::insert_or_find(
        db,
        &NewPolicy {
            name,
            sha256: &sha256,
            file: &bytes,
            metadata,
            shapes,
            uploaded_by: by,
        },
    )
    .await?)
}

/// Every policy, newest first, each with its latest evaluation and that evaluation's place in
/// the work queue while it waits.
pub async fn list(context: &Context) -> Result<Vec<Policy>> {
    let mut listed = policies::list(&context.db).await?;
    let positions = context.work.positions(WorkKind::Evaluation);
    for policy in &mut listed {
        if let Some(evaluation) = &mut policy.evaluation {
            evaluation.queue_position = positions.get(&evaluation.id).copied();
        }
    }
    Ok(listed)
}

/// `evaluation` with its place in the work queue while it waits.
fn placed(context: &Context, mut evaluation: Evaluation) -> Evaluation {
    evaluation.queue_position = context.work.position(WorkId::evaluation(evaluation.id));
    evaluation
}

/// An upload: [`register`]ed, and audited when the bytes are new; says whether they were.
pub async fn upload(
    context: &Context,
    name: &str,
    bytes: Vec<u8>,
    by: &str,
) -> Result<(Policy, bool)> {
    // From the header alone, before the values are read: a queued job holds them all.
    crate::policy::file::check_parameter_count(&bytes, context.settings.policies.max_parameters)
        .map_err(|e| Error::Invalid {
            code: e.code(),
            message: e.to_string(),
        })?;
    let (mut policy, created) = register(&context.db, name, bytes, by).await?;
    policy.evaluation = policy.evaluation.map(|e| placed(context, e));
    if created {
        audit::record(
            &context.db,
            by,
            "policy.upload",
            json!({"policy_id": policy.id, "name": name, "sha256": policy.sha256}),
        )
        .await?;
    }
    Ok((policy, created))
}

/// An evaluation an admin asked for: `episodes` (default: `policies.evaluation_episodes`, at
/// most `policies.max_evaluation_episodes`), `seed` (default 1) and what it runs on (on this
/// cell, the twin's mismatch: noise and calibration scales in 0..=[`MAX_MISMATCH_SCALE`])
/// checked, the evaluation queued (or started) and audited.
pub async fn evaluate(
    context: &Context,
    id: i64,
    episodes: Option<u32>,
    seed: Option<u64>,
    on: EvaluatedOn,
    rules: RuleSelection,
    by: &str,
) -> Result<Evaluation> {
    find(context, id).await?;
    let episodes = episodes.unwrap_or(context.settings.policies.evaluation_episodes);
    let most = context.settings.policies.max_evaluation_episodes;
    if !(1..=most).contains(&episodes) {
        return Err(Error::unprocessable(format!(
            "episodes = {episodes} is outside 1..={most} (policies.max_evaluation_episodes)"
        )));
    }
    let mismatch = on.mismatch();
    for (field, value) in [
        ("noise_scale", mismatch.noise_scale),
        ("calibration_scale", mismatch.calibration_scale),
    ] {
        if !(value.is_finite() && (0.0..=MAX_MISMATCH_SCALE).contains(&value)) {
            return Err(Error::unprocessable(format!(
                "{field} = {value} is outside 0..={MAX_MISMATCH_SCALE}"
            )));
        }
    }
    let evaluation =
        spawn_evaluation(context, id, episodes, seed.unwrap_or(1), on, rules, by).await?;
    audit::record(
        &context.db,
        by,
        "policy.evaluate",
        json!({
            "policy_id": id,
            "evaluation_id": evaluation.id,
            "episodes": episodes,
            "mismatch": mismatch,
            "randomise_cells": on.is_drawn(),
        }),
    )
    .await?;
    Ok(evaluation)
}

/// Queues an evaluation of policy `id` on the cell's twin, departing from the cell file by a
/// mismatch, or on cells drawn around it, and returns its record: `running` when a place in the
/// work queue was free, else `queued` with its position. It computes on one of the queue's
/// low-priority threads, so a running job keeps its timing; a full queue refuses it
/// ([`Error::Busy`]) before anything is stored.
pub async fn spawn_evaluation(
    context: &Context,
    id: i64,
    episodes: u32,
    seed: u64,
    on: EvaluatedOn,
    rules: RuleSelection,
    requested_by: &str,
) -> Result<Evaluation> {
    // The cell with the rules asked for: its hash differs from the cell's unless they are the
    // cell's own, so only an evaluation with the cell's rules counts for the gate.
    let mut cell = (*context.cell_config).clone();
    cell.rules = cell.rules.selected(&rules);
    let cell = Arc::new(cell);
    let bytes = policies::file(&context.db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no policy with id {id}")))?;
    let admitting = context.work.admissions().await;
    let ticket = context.work.reserve()?;
    let evaluation = policies::start_evaluation(
        &context.db,
        !ticket.is_running(),
        id,
        i64::from(episodes),
        seed,
        &cell.config_hash(),
        &on,
        &rules.label(),
        requested_by,
    )
    .await?;
    ticket.assign(WorkId::evaluation(evaluation.id));
    drop(admitting);
    let job = EvaluationJob {
        id: evaluation.id,
        cell,
        bytes,
        episodes,
        seed,
        on,
    };
    tokio::spawn(run_evaluation(context.clone(), ticket, job));
    Ok(placed(context, evaluation))
}

/// What one evaluation computes.
struct EvaluationJob {
    id: i64,
    cell: Arc<crate::config::cell::CellConfig>,
    bytes: Vec<u8>,
    episodes: u32,
    seed: u64,
    on: EvaluatedOn,
}

/// Waits for the evaluation's turn, computes it and stores what came of it; its place in the
/// queue is freed (the ticket dropped) once that is stored, under the queue's admissions lock.
async fn run_evaluation(context: Context, ticket: Ticket, job: EvaluationJob) {
    let (db, id) = (&context.db, job.id);
    let result = match ticket.turn().await {
        Err(NoTurn::Closed) => Err("the service stopped before the evaluation started".into()),
        Err(NoTurn::Removed) => Err("taken out of the work queue".into()),
        Ok(()) => {
            if let Err(error) = policies::run_evaluation(db, id).await {
                tracing::warn!(%error, evaluation_id = id, "could not store an evaluation's start");
            }
            let stop = ticket.cancel_flag();
            let work = move || evaluate_now(&job, &|| stop.load(Ordering::SeqCst));
            match context.work.compute(work).await {
                Ok(Ok(Some(figures))) => Ok(figures),
                Ok(Ok(None)) => Err("the service stopped during the evaluation".into()),
                Ok(Err(error)) | Err(error) => Err(error),
            }
        }
    };
    let ending = context.work.admissions().await;
    if context.work.is_closed() {
        // Stopping: `app` marks what waited or ran, and storage may be closing.
        return;
    }
    if let Err(error) = policies::finish_evaluation(db, id, result).await {
        tracing::error!(%error, evaluation_id = id, "could not store an evaluation's result");
    }
    drop(ticket);
    drop(ending);
}

/// The evaluation itself, on the calling thread's rayon pool: success rate, mean steps and
/// failures by reason; `None` once `stop` says so.
fn evaluate_now(
    job: &EvaluationJob,
    stop: &(dyn Fn() -> bool + Sync),
) -> std::result::Result<Option<(f64, Option<f64>, Value)>, String> {
    let file = LearnedPolicyFile::from_bytes(&job.bytes).map_err(|e| e.to_string())?;
    let cell = &job.cell;
    let policy = LearnedPolicy::from_file(&file)
        .map_err(|e| e.to_string())?
        .with_rules(&cell.rules);
    // Kept robots, as `celld eval` by default: the cell remembers each one's drift.
    let kept = EnvOptions {
        kept_robots: eval::DEFAULT_KEPT_ROBOTS,
        ..EnvOptions::from_cell(cell)
    };
    let (episodes, seed) = (job.episodes as usize, job.seed);
    let summary = match job.on {
        EvaluatedOn::Cell(mismatch) => eval::evaluate_until(
            cell,
            None,
            mismatch.apply(kept),
            episodes,
            seed,
            &|_| Box::new(policy.clone()) as Box<dyn Controller>,
            &|_| {},
            stop,
        ),
        // A learned policy reads each drawn cell from its observations.
        EvaluatedOn::DrawnCells { fault } => eval::evaluate_until(
            cell,
            Some(&CellRanges::default()),
            EnvOptions { fault, ..kept },
            episodes,
            seed,
            &|_| Box::new(policy.clone()) as Box<dyn Controller>,
            &|_| {},
            stop,
        ),
    };
    Ok(summary.map(|(summary, _)| {
        (
            summary.success_rate,
            summary.avg_steps,
            json!(summary.failures),
        )
    }))
}

/// What an activation did.
#[derive(Debug, Clone, PartialEq)]
pub struct Activation {
    /// The policy that was active before, now retired.
    pub retired: Option<i64>,
    /// Whether the gate was shut and passed by with a reason.
    pub forced: bool,
}

/// Activation behind the gate ([`super::gate`]): a policy becomes active only after an
/// evaluation on this cell's current configuration reached `policies.activation_threshold`,
/// unless an admin forces it with a reason (kept in the audit log).
pub async fn activate(
    context: &Context,
    id: i64,
    force: bool,
    reason: Option<&str>,
    by: &str,
) -> Result<Activation> {
    let policy = find(context, id).await?;
    let reason = reason.map(str::trim).filter(|r| !r.is_empty());
    let (evaluation, gate) = super::gate::evaluated(context, id, "activation").await?;
    if let Err(why) = &gate {
        match (force, reason) {
            (false, _) => return Err(Error::conflict(why.clone())),
            (true, None) => {
                return Err(Error::conflict(format!(
                    "{why}; forcing it needs a reason: {{\"force\": true, \"reason\": \"...\"}}"
                )));
            }
            (true, Some(_)) => {}
        }
    }
    let retired = if policy.status == "active" {
        None
    } else {
        policies::activate(&context.db, id).await?
    };
    audit::record(
        &context.db,
        by,
        "policy.activate",
        json!({
            "policy_id": id,
            "retired": retired,
            "force": force,
            "reason": reason,
            "gate": gate.as_ref().err(),
            "evaluation_id": evaluation.as_ref().map(|e| e.id),
        }),
    )
    .await?;
    Ok(Activation {
        retired,
        forced: force && gate.is_err(),
    })
}

/// The policy with `id` (its latest evaluation with its place in the work queue while it
/// waits), or [`Error::NotFound`].
pub async fn find(context: &Context, id: i64) -> Result<Policy> {
    let mut policy = policies::get(&context.db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no policy with id {id}")))?;
    policy.evaluation = policy.evaluation.map(|e| placed(context, e));
    Ok(policy)
}

/// Registers the bundled default policy ([`crate::policy::DEFAULT_POLICY`]) as `bundled-default`
/// (idempotent, by its bytes). Until it has a finished evaluation on this cell (its first
/// registration, or a service stopped during that evaluation) it is evaluated, and activated if
/// it passes the gate and nothing else is active. So on a database from an earlier default, that
/// policy keeps its row, its evaluations and its status: if it is active it stays active, and the
/// new default waits, evaluated, for an admin to activate it (which retires the earlier one; its
/// rollback is to activate that again), and the audit log says so
/// (`policy.bundled_not_activated`).
pub async fn register_bundled(context: &Context) -> Result<()> {
    let Some(bytes) = crate::policy::bundled_policy(crate::policy::DEFAULT_POLICY) else {
        return Ok(());
    };
    let (policy, _) = register(&context.db, "bundled-default", bytes.to_vec(), "celld").await?;
    let cell_hash = context.cell_config.config_hash();
    if policies::latest_evaluation_on(&context.db, policy.id, &cell_hash)
        .await?
        .is_some()
    {
        return Ok(());
    }
    let episodes = context.settings.policies.evaluation_episodes;
    let evaluation = spawn_evaluation(
        context,
        policy.id,
        episodes,
        1,
        EvaluatedOn::Cell(Mismatch::NONE),
        RuleSelection::All,
        "celld",
    )
    .await?;
    let (context, threshold) = (
        context.clone(),
        context.settings.policies.activation_threshold,
    );
    tokio::spawn(async move {
        let db = &context.db;
        loop {
            tokio::time::sleep(std::time::Duration::from_millis(200)).await;
            match policies::latest_evaluation(db, policy.id).await {
                Ok(Some(e))
                    if e.id == evaluation.id
                        && matches!(e.status.as_str(), "queued" | "running") =>
                {
                    continue;
                }
                Ok(Some(e)) if e.success_rate.unwrap_or(0.0) >= threshold => {
                    match policies::activate_if_none_active(db, policy.id).await {
                        Ok(true) => {
                            let _ = audit::record(
                                db,
                                "celld",
                                "policy.activate",
                                json!({"policy_id": policy.id, "bundled": true, "evaluation_id": e.id}),
                            )
                            .await;
                        }
                        Ok(false) => {
                            // Another policy is active: it stays so, and the record says why
                            // the new default waits.
                            let active =
                                policies::active(db).await.ok().flatten().map(|(id, _)| id);
                            let _ = audit::record(
                                db,
                                "celld",
                                "policy.bundled_not_activated",
                                json!({
                                    "policy_id": policy.id,
                                    "evaluation_id": e.id,
                                    "active_policy_id": active,
                                }),
                            )
                            .await;
                        }
                        Err(error) => {
                            tracing::warn!(%error, policy_id = policy.id, "could not activate the bundled default");
                        }
                    }
                    return;
                }
                _ => return,
            }
        }
    });
    Ok(())
}
