//! `/api/policies`: upload (admin), list, read and download (viewer), evaluate in the twin and
//! activate behind the evaluation gate (admin).

use super::Context;
use super::auth::{Admin, Auth};
use super::error::{ApiError, ApiResult, Items, Json, Path, Query};
use crate::policy::shield::{RuleId, RuleSelection};
use crate::sim::{Fault, Mismatch, UnknownFault};
use crate::storage::policies::{self, EvaluatedOn, Evaluation, Policy};
use crate::storage::tokens::Role;
use crate::workflows;
use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{DefaultBodyLimit, State};
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use serde::{Deserialize, Serialize};
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
    Admin(caller): Admin,
    Query(query): Query<UploadQuery>,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<(StatusCode, Json<Policy>)> {
    let name = Some(query.name.trim())
        .filter(|n| !n.is_empty() && n.chars().count() <= 100)
        .ok_or_else(|| ApiError::bad_request("`?name=` (1 to 100 characters) names the policy"))?;
    let bytes = body?;
    let (policy, created) =
        workflows::policies::upload(&context, name, bytes.to_vec(), &caller.name).await?;
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
        items: workflows::policies::list(&context).await?,
    }))
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
    Ok(Json(workflows::policies::find(&context, id).await?))
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
    /// Episodes (default: the service's `policies.evaluation_episodes`); at most
    /// `policies.max_evaluation_episodes` (10,000 unless the service sets another), else 422.
    #[schema(minimum = 1, maximum = 10_000)]
    #[serde(default, deserialize_with = "crate::integer::optional_integer")]
    episodes: Option<u32>,
    /// The evaluation's seed, any u64 (default 1).
    #[schema(minimum = 0, maximum = 18_446_744_073_709_551_615_u64)]
    #[serde(default, deserialize_with = "crate::integer::optional_integer")]
    seed: Option<u64>,
    /// Multiplies the camera's point noise (default 1, the spec; 0 noiseless).
    #[schema(minimum = 0, maximum = 16)]
    noise_scale: Option<f64>,
    /// Multiplies the robot's kinematic calibration error (default 1, the cell file's; 0 a
    /// perfectly calibrated robot).
    #[schema(minimum = 0, maximum = 16)]
    calibration_scale: Option<f64>,
    /// A fault injected in every episode from a step drawn in 5..=35 (default none).
    #[serde(default, deserialize_with = "optional_fault")]
    fault: Option<Fault>,
    /// Run on cells drawn around this one over the ranges the product is specified for, as
    /// `celld eval --randomise-cells`: each kept robot on a cell of its own, its camera noise and
    /// calibration error drawn too, so `noise_scale` and `calibration_scale` must be left out
    /// (default false).
    randomise_cells: Option<bool>,
    /// The rules between the policy's proposal and the supervisor to run with
    /// (docs/policy-rules.md): `"all"` (the cell file's, the default), `"none"`, or only those
    /// named, as a list or a comma-separated string. Only an evaluation with `"all"` counts for
    /// the activation gate.
    #[schema(schema_with = rule_selection)]
    #[serde(default)]
    rules: Option<RuleSelection>,
}

/// `rules`' schema: null, `all`, `none` or rule names comma-separated, or a list of names.
fn rule_selection() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
    use utoipa::openapi::schema::{ArrayBuilder, ObjectBuilder, OneOfBuilder, Type};
    let names: Vec<&str> = RuleId::ALL.iter().map(|id| id.name()).collect();
    let one = names.join("|");
    OneOfBuilder::new()
        .item(ObjectBuilder::new().schema_type(Type::Null))
        .item(
            ObjectBuilder::new()
                .schema_type(Type::String)
                .pattern(Some(format!("^(all|none|({one})(,({one}))*)$"))),
        )
        .item(
            ArrayBuilder::new().items(
                ObjectBuilder::new()
                    .schema_type(Type::String)
                    .enum_values(Some(names)),
            ),
        )
        .into()
}

/// `EvaluateBody` as described: one of two shapes, so that no request the description allows
/// is refused. On this cell (`randomise_cells` false, null or left out) every field may be
/// given; on drawn cells (`randomise_cells: true`) `noise_scale` and `calibration_scale` may
/// only be null or left out, each drawn cell bringing its own camera noise and calibration
/// error.
struct EvaluateRequest;

impl utoipa::PartialSchema for EvaluateRequest {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        use utoipa::openapi::RefOr;
        use utoipa::openapi::schema::{ObjectBuilder, OneOfBuilder, Schema, Type};
        let RefOr::T(Schema::Object(fields)) = <EvaluateBody as utoipa::PartialSchema>::schema()
        else {
            unreachable!("EvaluateBody derives an object schema")
        };
        let mut on_cell = fields.clone();
        on_cell.properties.insert(
            "randomise_cells".into(),
            ObjectBuilder::new()
                .schema_type(utoipa::openapi::schema::SchemaType::from_iter([
                    Type::Boolean,
                    Type::Null,
                ]))
                .enum_values(Some([serde_json::json!(false), serde_json::Value::Null]))
                .description(Some("False or left out: on this cell."))
                .into(),
        );
        on_cell.description = Some("On this cell, under an optional mismatch.".into());
        let mut drawn = fields;
        drawn.properties.insert(
            "randomise_cells".into(),
            ObjectBuilder::new()
                .schema_type(Type::Boolean)
                .enum_values(Some([true]))
                .description(Some(
                    "On cells drawn around this one, as `celld eval --randomise-cells`.",
                ))
                .into(),
        );
        for drawn_per_cell in ["noise_scale", "calibration_scale"] {
            drawn.properties.insert(
                drawn_per_cell.into(),
                ObjectBuilder::new()
                    .schema_type(Type::Null)
                    .description(Some("Drawn for each cell: null or left out."))
                    .into(),
            );
        }
        drawn.required.push("randomise_cells".into());
        drawn.description = Some("On drawn cells, each with its own noise and calibration.".into());
        OneOfBuilder::new()
            .item(on_cell)
            .item(drawn)
            .description(Some(
                "What the evaluation runs on: this cell (under an optional mismatch) or cells \
                 drawn around it (`randomise_cells: true`, which draws each cell's camera \
                 noise and calibration error, so `noise_scale` and `calibration_scale` stay \
                 out).",
            ))
            .into()
    }
}

impl ToSchema for EvaluateRequest {
    fn name() -> std::borrow::Cow<'static, str> {
        "EvaluateBody".into()
    }

    fn schemas(
        schemas: &mut Vec<(
            String,
            utoipa::openapi::RefOr<utoipa::openapi::schema::Schema>,
        )>,
    ) {
        <EvaluateBody as ToSchema>::schemas(schemas);
    }
}

/// A fault by name; an unknown one is refused naming the field and the names there are.
fn optional_fault<'de, D: serde::Deserializer<'de>>(
    deserializer: D,
) -> std::result::Result<Option<Fault>, D::Error> {
    Option::<String>::deserialize(deserializer)?
        .map(|name| {
            name.parse()
                .map_err(|e: UnknownFault| serde::de::Error::custom(format!("fault: {e}")))
        })
        .transpose()
}

/// Evaluates the policy in the twin of this cell (admin), in the background at low priority;
/// the answer is the evaluation as it is stored: `running`, or `queued` with its
/// `queue_position` behind other evaluations and training runs (`work.concurrency` compute at
/// once). Past `work.queue_length` waiting, 429 with `Retry-After`. The body may be left out. An evaluation under a
/// mismatch (`noise_scale` or `calibration_scale` other than 1, or a `fault`) or on drawn cells
/// (`randomise_cells`) is stored and shown like any other, but the activation gate reads only
/// those on this cell without a mismatch.
#[utoipa::path(post, path = "/api/policies/{id}/evaluate", tag = "policies",
    params(("id" = i64, Path)), request_body(content = Option<EvaluateRequest>),
    responses(
        (status = 202, description = "Started, or queued", body = Evaluation),
        (status = 429, description = "The work queue is full (`work.queue_length`)",
            body = crate::http::document::ErrorBody,
            headers(("Retry-After" = u64, description = "Seconds worth waiting first"))),
    ))]
async fn evaluate(
    State(context): State<Context>,
    Admin(caller): Admin,
    Path(id): Path<i64>,
    body: Bytes,
) -> ApiResult<(StatusCode, Json<Evaluation>)> {
    let body: EvaluateBody = optional_body(&body)?;
    let on = if body.randomise_cells.unwrap_or(false) {
        if body.noise_scale.is_some() || body.calibration_scale.is_some() {
            return Err(ApiError::unprocessable(
                "randomise_cells draws each cell's camera noise and calibration error: \
                 leave out noise_scale and calibration_scale",
            ));
        }
        EvaluatedOn::DrawnCells { fault: body.fault }
    } else {
        EvaluatedOn::Cell(Mismatch {
            noise_scale: body.noise_scale.unwrap_or(1.0),
            calibration_scale: body.calibration_scale.unwrap_or(1.0),
            fault: body.fault,
        })
    };
    let evaluation = workflows::policies::evaluate(
        &context,
        id,
        body.episodes,
        body.seed,
        on,
        body.rules.unwrap_or_default(),
        &caller.name,
    )
    .await?;
    Ok((StatusCode::ACCEPTED, Json(evaluation)))
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
    Admin(caller): Admin,
    Path(id): Path<i64>,
    body: Bytes,
) -> ApiResult<Json<Activated>> {
    let body: ActivateBody = optional_body(&body)?;
    let gate = workflows::policies::activate(
        &context,
        id,
        body.force.unwrap_or(false),
        body.reason.as_deref(),
        &caller.name,
    )
    .await?;
    Ok(Json(Activated {
        policy: workflows::policies::find(&context, id).await?,
        retired: gate.retired,
        forced: gate.forced,
    }))
}
