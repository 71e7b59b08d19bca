//! Policies: registered after the file checks, evaluated in the twin in the background,
//! activated behind the evaluation gate; the bundled policy registered and evaluated at start.

use super::{Context, Error, Result, off_the_runtime};
use crate::policy::eval;
use crate::policy::learned::{LearnedPolicy, LearnedPolicyFile};
use crate::policy::{Controller, ControllerFactory};
use crate::sim::randomise::CellRanges;
use crate::sim::{EnvOptions, MAX_MISMATCH_SCALE, Mismatch};
use crate::storage::policies::{self, EvaluatedOn, Evaluation, NewPolicy, Policy};
use crate::storage::{Db, audit, tokens};
use serde_json::{Value, json};
use std::sync::Arc;

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

/// Most episodes one evaluation may ask for.
const MAX_EVALUATION_EPISODES: u32 = 100_000;

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
    let (policy, created) = register(&context.db, name, bytes, by).await?;
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

/// An evaluation an admin asked for: `episodes` (default: `policies.evaluation_episodes`),
/// `seed` (default 1) and what it runs on (on this cell, the twin's mismatch: noise and
/// calibration scales in 0..=[`MAX_MISMATCH_SCALE`]) checked, the evaluation started and audited.
pub async fn evaluate(
    context: &Context,
    id: i64,
    episodes: Option<u32>,
    seed: Option<u64>,
    on: EvaluatedOn,
    by: &str,
) -> Result<Evaluation> {
    find(context, id).await?;
    let episodes = episodes.unwrap_or(context.settings.policies.evaluation_episodes);
    if !(1..=MAX_EVALUATION_EPISODES).contains(&episodes) {
        return Err(Error::unprocessable(format!(
            "episodes = {episodes} is outside 1..={MAX_EVALUATION_EPISODES}"
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
    let evaluation = spawn_evaluation(context, id, episodes, seed.unwrap_or(1), on, by).await?;
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

/// Starts an evaluation of policy `id` on the cell's twin, departing from the cell file by a
/// mismatch, or on cells drawn around it, in the background and returns its record. It runs on
/// one low-priority thread of its own, so a running job keeps its timing.
pub async fn spawn_evaluation(
    context: &Context,
    id: i64,
    episodes: u32,
    seed: u64,
    on: EvaluatedOn,
    requested_by: &str,
) -> Result<Evaluation> {
    let cell = context.cell_config.clone();
    let evaluation = policies::start_evaluation(
        &context.db,
        id,
        i64::from(episodes),
        seed,
        &cell.config_hash(),
        &on,
        requested_by,
    )
    .await?;
    let bytes = policies::file(&context.db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no policy with id {id}")))?;
    let db = context.db.clone();
    let evaluation_id = evaluation.id;
    tokio::spawn(async move {
        let work = tokio::task::spawn_blocking(move || -> std::result::Result<_, String> {
            let file = LearnedPolicyFile::from_bytes(&bytes).map_err(|e| e.to_string())?;
            let policy = LearnedPolicy::from_file(&file).map_err(|e| e.to_string())?;
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .start_handler(|_| crate::cell::task::lower_priority())
                .build()
                .map_err(|e| e.to_string())?;
            let (summary, _) = pool.install(|| {
                // Kept robots, as `celld eval` by default: the cell remembers each one's drift.
                let kept = EnvOptions {
                    kept_robots: eval::DEFAULT_KEPT_ROBOTS,
                    ..EnvOptions::from_cell(&cell)
                };
                match on {
                    EvaluatedOn::Cell(mismatch) => {
                        let factory: ControllerFactory =
                            Box::new(move || Box::new(policy.clone()) as Box<dyn Controller>);
                        eval::evaluate(
                            &cell,
                            mismatch.apply(kept),
                            episodes as usize,
                            seed,
                            &factory,
                            &|_| {},
                        )
                    }
                    // A learned policy reads each drawn cell from its observations.
                    EvaluatedOn::DrawnCells { fault } => eval::evaluate_on_drawn_cells(
                        &cell,
                        &CellRanges::default(),
                        EnvOptions { fault, ..kept },
                        episodes as usize,
                        seed,
                        &|_| Box::new(policy.clone()) as Box<dyn Controller>,
                        &|_| {},
                    ),
                }
            });
            Ok((
                summary.success_rate,
                summary.avg_steps,
                json!(summary.failures),
            ))
        });
        let result = match work.await {
            Ok(result) => result,
            Err(panic) => Err(format!("the evaluation stopped: {panic}")),
        };
        if let Err(error) = policies::finish_evaluation(&db, evaluation_id, result).await {
            tracing::error!(%error, evaluation_id, "could not store an evaluation's result");
        }
    });
    Ok(evaluation)
}

/// What an activation did.
#[derive(Debug, Clone, PartialEq)]
pub struct Activation {
    /// The policy that was active before, now retired.
    pub retired: Option<i64>,
    /// Whether the gate was shut and passed by with a reason.
    pub forced: bool,
}

/// The gate: a policy drives the robot only after an evaluation on this cell's current
/// configuration reached `policies.activation_threshold`, unless an admin forces it with a
/// reason (kept in the audit log).
pub async fn activate(
    context: &Context,
    id: i64,
    force: bool,
    reason: Option<&str>,
    by: &str,
) -> Result<Activation> {
    let policy = find(context, id).await?;
    let reason = reason.map(str::trim).filter(|r| !r.is_empty());
    let cell_hash = context.cell_config.config_hash();
    let threshold = context.settings.policies.activation_threshold;
    let evaluation = policies::latest_evaluation_on(&context.db, id, &cell_hash).await?;
    let gate = match &evaluation {
        None => Err(format!(
            "policy {id} has no finished evaluation on this cell (config {cell_hash}): \
             POST /api/policies/{id}/evaluate first"
        )),
        Some(e) if e.success_rate.unwrap_or(0.0) < threshold => Err(format!(
            "policy {id} reached success {:.3} over {} episodes on this cell; activation needs ≥ {threshold}",
            e.success_rate.unwrap_or(0.0),
            e.episodes
        )),
        Some(_) => Ok(()),
    };
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

/// The policy with `id`, or [`Error::NotFound`].
pub async fn find(context: &Context, id: i64) -> Result<Policy> {
    policies::get(&context.db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no policy with id {id}")))
}

/// Registers the bundled default policy (idempotent, by its bytes). Until it has a finished
/// evaluation on this cell (its first registration, or a service stopped during that
/// evaluation) it is evaluated, and activated if it passes the gate and nothing else is active.
pub async fn register_bundled(context: &Context) -> Result<()> {
    let Some(bytes) = crate::policy::bundled_policy("hierarchical") else {
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
                Ok(Some(e)) if e.id == evaluation.id && e.status == "running" => continue,
                Ok(Some(e)) if e.success_rate.unwrap_or(0.0) >= threshold => {
                    if let Ok(true) = policies::activate_if_none_active(db, policy.id).await {
                        let _ = audit::record(
                            db,
                            "celld",
                            "policy.activate",
                            json!({"policy_id": policy.id, "bundled": true, "evaluation_id": e.id}),
                        )
                        .await;
                    }
                    return;
                }
                _ => return,
            }
        }
    });
    Ok(())
}
