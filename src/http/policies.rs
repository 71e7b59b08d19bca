//! `/api/policies`: upload (admin), list, read and download (viewer), evaluate in the twin and
//! activate behind the evaluation gate (admin).

use super::Context;
use super::auth::Auth;
use super::error::{ApiError, ApiResult, Json, Path, Query, off_the_runtime};
use crate::policy::eval;
use crate::policy::learned::{LearnedPolicy, LearnedPolicyFile};
use crate::policy::{Controller, ControllerFactory};
use crate::sim::EnvOptions;
use crate::storage::policies::{self, Evaluation, NewPolicy, Policy};
use crate::storage::tokens::{self, Role};
use crate::storage::{Db, audit};
use axum::Router;
use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{DefaultBodyLimit, State};
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use axum::routing::{get, post};
use serde::Deserialize;
use serde_json::{Value, json};

pub fn router(max_upload_bytes: usize) -> Router<Context> {
    Router::new()
        .route(
            "/api/policies",
            post(upload)
                .get(list)
                .layer(DefaultBodyLimit::max(max_upload_bytes)),
        )
        .route("/api/policies/{id}", get(read))
        .route("/api/policies/{id}/file", get(download))
        .route("/api/policies/{id}/evaluate", post(evaluate))
        .route("/api/policies/{id}/activate", post(activate))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UploadQuery {
    name: Option<String>,
}

/// Checks a policy file (hierarchical or flat, by its `format` metadata) as an upload is checked,
/// and stores it (or finds the same bytes).
pub async fn register(db: &Db, name: &str, bytes: Bytes, by: &str) -> ApiResult<(Policy, bool)> {
    let checked = bytes.clone();
    let (metadata, shapes, sha256) = off_the_runtime(move || {
        let file = LearnedPolicyFile::from_bytes(&checked).map_err(|e| {
            ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, e.code(), e.to_string())
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

async fn upload(
    State(context): State<Context>,
    auth: Auth,
    Query(query): Query<UploadQuery>,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<(StatusCode, Json<Policy>)> {
    let caller = auth.require(Role::Admin)?;
    let name = query
        .name
        .as_deref()
        .map(str::trim)
        .filter(|n| !n.is_empty() && n.len() <= 100)
        .ok_or_else(|| ApiError::bad_request("`?name=` (1 to 100 characters) names the policy"))?;
    let bytes = body?;
    let (policy, created) = register(&context.db, name, bytes, &caller.name).await?;
    if created {
        audit::record(
            &context.db,
            &caller.name,
            "policy.upload",
            json!({"policy_id": policy.id, "name": name, "sha256": policy.sha256}),
        )
        .await?;
    }
    let status = if created {
        StatusCode::CREATED
    } else {
        StatusCode::OK
    };
    Ok((status, Json(policy)))
}

async fn list(State(context): State<Context>, auth: Auth) -> ApiResult<Json<Value>> {
    auth.require(Role::Viewer)?;
    Ok(Json(json!({"items": policies::list(&context.db).await?})))
}

async fn find(context: &Context, id: i64) -> ApiResult<Policy> {
    policies::get(&context.db, id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("no policy with id {id}")))
}

async fn read(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
) -> ApiResult<Json<Policy>> {
    auth.require(Role::Viewer)?;
    Ok(Json(find(&context, id).await?))
}

async fn download(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
) -> ApiResult<impl IntoResponse> {
    auth.require(Role::Viewer)?;
    let bytes = policies::file(&context.db, id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("no policy with id {id}")))?;
    Ok((
        [
            (header::CONTENT_TYPE, "application/octet-stream".to_string()),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"policy-{id}.safetensors\""),
            ),
        ],
        bytes,
    ))
}

/// A JSON body that may also be left out.
fn optional_body<T: serde::de::DeserializeOwned + Default>(bytes: &[u8]) -> ApiResult<T> {
    if bytes.iter().all(u8::is_ascii_whitespace) {
        return Ok(T::default());
    }
    serde_json::from_slice(bytes).map_err(|e| ApiError::unprocessable(format!("body: {e}")))
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvaluateBody {
    episodes: Option<u32>,
    seed: Option<u64>,
}

const MAX_EVALUATION_EPISODES: u32 = 100_000;

async fn evaluate(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
    body: Bytes,
) -> ApiResult<(StatusCode, Json<Evaluation>)> {
    let caller = auth.require(Role::Admin)?;
    let body: EvaluateBody = optional_body(&body)?;
    find(&context, id).await?;
    let episodes = body
        .episodes
        .unwrap_or(context.settings.policies.evaluation_episodes);
    if !(1..=MAX_EVALUATION_EPISODES).contains(&episodes) {
        return Err(ApiError::unprocessable(format!(
            "episodes = {episodes} is outside 1..={MAX_EVALUATION_EPISODES}"
        )));
    }
    let evaluation =
        spawn_evaluation(&context, id, episodes, body.seed.unwrap_or(1), &caller.name).await?;
    audit::record(
        &context.db,
        &caller.name,
        "policy.evaluate",
        json!({"policy_id": id, "evaluation_id": evaluation.id, "episodes": episodes}),
    )
    .await?;
    Ok((StatusCode::ACCEPTED, Json(evaluation)))
}

/// Starts an evaluation of policy `id` on the cell's twin in the background and returns its
/// record. It runs on one low-priority thread of its own, so a running job keeps its timing.
pub async fn spawn_evaluation(
    context: &Context,
    id: i64,
    episodes: u32,
    seed: u64,
    requested_by: &str,
) -> ApiResult<Evaluation> {
    let cell = context.cell_config.clone();
    let evaluation = policies::start_evaluation(
        &context.db,
        id,
        i64::from(episodes),
        seed,
        &cell.config_hash(),
        requested_by,
    )
    .await?;
    let bytes = policies::file(&context.db, id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("no policy with id {id}")))?;
    let db = context.db.clone();
    let evaluation_id = evaluation.id;
    tokio::spawn(async move {
        let work = tokio::task::spawn_blocking(move || -> Result<_, String> {
            let file = LearnedPolicyFile::from_bytes(&bytes).map_err(|e| e.to_string())?;
            let policy = LearnedPolicy::from_file(&file).map_err(|e| e.to_string())?;
            let factory: ControllerFactory =
                Box::new(move || Box::new(policy.clone()) as Box<dyn Controller>);
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .start_handler(|_| crate::cell::task::lower_priority())
                .build()
                .map_err(|e| e.to_string())?;
            let (summary, _) = pool.install(|| {
                eval::evaluate(
                    &cell,
                    EnvOptions::from_cell(&cell),
                    episodes as usize,
                    seed,
                    &factory,
                    &|_| {},
                )
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

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ActivateBody {
    force: Option<bool>,
    reason: Option<String>,
}

/// The gate: a policy drives the robot only after an evaluation on this cell's current
/// configuration reached the configured success rate, unless an admin forces it with a reason.
async fn activate(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
    body: Bytes,
) -> ApiResult<Json<Value>> {
    let caller = auth.require(Role::Admin)?;
    let body: ActivateBody = optional_body(&body)?;
    let policy = find(&context, id).await?;
    let force = body.force.unwrap_or(false);
    let reason = body
        .reason
        .as_deref()
        .map(str::trim)
        .filter(|r| !r.is_empty());
    if force && reason.is_none() {
        return Err(ApiError::unprocessable(
            "force needs a reason: {\"force\": true, \"reason\": \"...\"}",
        ));
    }
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
    if let Err(why) = &gate
        && !force
    {
        return Err(ApiError::conflict(why.clone()));
    }
    let retired = if policy.status == "active" {
        None
    } else {
        policies::activate(&context.db, id).await?
    };
    audit::record(
        &context.db,
        &caller.name,
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
    Ok(Json(json!({
        "policy": find(&context, id).await?,
        "retired": retired,
        "forced": force && gate.is_err(),
    })))
}

/// Registers the bundled default policy (idempotent, by its bytes). Until it has a finished
/// evaluation on this cell (its first registration, or a service stopped during that
/// evaluation) it is evaluated, and activated if it passes the gate and nothing else is active.
pub async fn register_bundled(context: &Context) -> ApiResult<()> {
    let Some(bytes) = crate::policy::bundled_policy("hierarchical") else {
        return Ok(());
    };
    let (policy, _) = register(
        &context.db,
        "bundled-default",
        Bytes::from_static(bytes),
        "celld",
    )
    .await?;
    let cell_hash = context.cell_config.config_hash();
    if policies::latest_evaluation_on(&context.db, policy.id, &cell_hash)
        .await?
        .is_some()
    {
        return Ok(());
    }
    let episodes = context.settings.policies.evaluation_episodes;
    let evaluation = spawn_evaluation(context, policy.id, episodes, 1, "celld").await?;
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
