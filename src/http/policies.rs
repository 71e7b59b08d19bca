//! `/api/policies`: upload (admin), list, read and download (viewer), evaluate in the twin and
//! activate behind the evaluation gate (admin).

use super::Context;
use super::auth::Auth;
use super::error::{ApiError, ApiResult, Items, Json, Path, Query, off_the_runtime};
use crate::policy::eval;
use crate::policy::learned::{LearnedPolicy, LearnedPolicyFile};
use crate::policy::{Controller, ControllerFactory};
use crate::sim::EnvOptions;
use crate::storage::policies::{self, Evaluation, NewPolicy, Policy};
use crate::storage::tokens::{self, Role};
use crate::storage::{Db, audit};
use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{DefaultBodyLimit, State};
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::{OpenApiRouter, UtoipaMethodRouterExt};
use utoipa_axum::routes;

pub fn router(max_upload_bytes: usize) -> OpenApiRouter<Context> {
    OpenApiRouter::new()
        .routes(routes!(upload, list).layer(DefaultBodyLimit::max(max_upload_bytes)))
        .routes(routes!(read))
        .routes(routes!(download))
        .routes(routes!(evaluate))
        .routes(routes!(activate))
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
pub struct UploadQuery {
    /// The policy's name; spaces around it are dropped.
    #[param(min_length = 1, max_length = 100, pattern = r"\S")]
    name: String,
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

/// Uploads a policy file (admin): the raw safetensors bytes of a hierarchical or a flat TD3
/// policy, told apart by the `format` metadata. It is checked whole before anything is
/// stored (422 names the tensor or key at fault); the same bytes again find the stored one.
#[utoipa::path(post, path = "/api/policies", tag = "policies", params(UploadQuery),
    request_body(content = Vec<u8>, content_type = "application/octet-stream"),
    responses(
        (status = 201, description = "Stored", body = Policy),
        (status = 200, description = "The same file was stored already", body = Policy),
    ))]
async fn upload(
    State(context): State<Context>,
    auth: Auth,
    Query(query): Query<UploadQuery>,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<(StatusCode, Json<Policy>)> {
    let caller = auth.require(Role::Admin)?;
    let name = Some(query.name.trim())
        .filter(|n| !n.is_empty() && n.chars().count() <= 100)
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

/// Every policy, with its latest evaluation (viewer).
#[utoipa::path(get, path = "/api/policies", tag = "policies",
    responses((status = 200, description = "The policies", body = Items<Policy>)))]
async fn list(State(context): State<Context>, auth: Auth) -> ApiResult<Json<Items<Policy>>> {
    auth.require(Role::Viewer)?;
    Ok(Json(Items {
        items: policies::list(&context.db).await?,
    }))
}

async fn find(context: &Context, id: i64) -> ApiResult<Policy> {
    policies::get(&context.db, id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("no policy with id {id}")))
}

/// One policy (viewer).
#[utoipa::path(get, path = "/api/policies/{id}", tag = "policies", params(("id" = i64, Path)),
    responses((status = 200, description = "The policy", body = Policy)))]
async fn read(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
) -> ApiResult<Json<Policy>> {
    auth.require(Role::Viewer)?;
    Ok(Json(find(&context, id).await?))
}

/// The policy file as uploaded (viewer).
#[utoipa::path(get, path = "/api/policies/{id}/file", tag = "policies",
    params(("id" = i64, Path)),
    responses((status = 200, description = "The safetensors file", body = Vec<u8>,
        content_type = "application/octet-stream")))]
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

/// A JSON body that may also be left out or be `null`.
fn optional_body<T: serde::de::DeserializeOwned + Default>(bytes: &[u8]) -> ApiResult<T> {
    if bytes.iter().all(u8::is_ascii_whitespace) {
        return Ok(T::default());
    }
    serde_json::from_slice::<Option<T>>(bytes)
        .map(Option::unwrap_or_default)
        .map_err(|e| ApiError::unprocessable(format!("body: {e}")))
}

#[derive(Debug, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct EvaluateBody {
    /// Episodes (default: the service's `policies.evaluation_episodes`).
    #[schema(minimum = 1, maximum = 100_000)]
    #[serde(default, deserialize_with = "crate::integer::optional_integer")]
    episodes: Option<u32>,
    /// The evaluation's seed (default 1).
    #[serde(default, deserialize_with = "crate::integer::optional_integer")]
    seed: Option<u64>,
}

const MAX_EVALUATION_EPISODES: u32 = 100_000;

/// Evaluates the policy in the twin of this cell (admin), in the background at low priority;
/// the answer is the evaluation as it starts. The body may be left out.
#[utoipa::path(post, path = "/api/policies/{id}/evaluate", tag = "policies",
    params(("id" = i64, Path)), request_body(content = Option<EvaluateBody>),
    responses((status = 202, description = "Started", body = Evaluation)))]
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

#[derive(Debug, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ActivateBody {
    /// Activate past the gate; needs a `reason`.
    force: Option<bool>,
    /// Why the gate is passed by (kept in the audit log).
    reason: Option<String>,
}

#[derive(Serialize, ToSchema)]
pub struct Activated {
    policy: Policy,
    /// The policy that was active before, now retired.
    retired: Option<i64>,
    /// Whether the gate was passed by.
    forced: bool,
}

/// Makes the policy the one `"controller": "active"` runs (admin). The gate: only after an
/// evaluation on this cell's current configuration reached `policies.activation_threshold`,
/// unless forced with a reason (409 says why it is shut). The body may be left out.
#[utoipa::path(post, path = "/api/policies/{id}/activate", tag = "policies",
    params(("id" = i64, Path)), request_body(content = Option<ActivateBody>),
    responses((status = 200, description = "Active", body = Activated)))]
async fn activate(
    State(context): State<Context>,
    auth: Auth,
    Path(id): Path<i64>,
    body: Bytes,
) -> ApiResult<Json<Activated>> {
    let caller = auth.require(Role::Admin)?;
    let body: ActivateBody = optional_body(&body)?;
    let policy = find(&context, id).await?;
    let force = body.force.unwrap_or(false);
    let reason = body
        .reason
        .as_deref()
        .map(str::trim)
        .filter(|r| !r.is_empty());
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
            (false, _) => return Err(ApiError::conflict(why.clone())),
            (true, None) => {
                return Err(ApiError::conflict(format!(
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
    Ok(Json(Activated {
        policy: find(&context, id).await?,
        retired,
        forced: force && gate.is_err(),
    }))
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
