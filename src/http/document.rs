//! The API's own description: the head and the finishing of the OpenAPI document collected
//! from the handlers' annotations ([`super::openapi`], served at `/api/openapi.json`), and
//! Swagger UI over it at `/api/docs` (its files are built into the binary: a cell network
//! has no internet).

use super::Context;
use axum::Router;
use serde::Serialize;
use utoipa::openapi::path::Operation;
use utoipa::openapi::security::{ApiKey, ApiKeyValue, Http, HttpAuthScheme, SecurityScheme};
use utoipa::openapi::{ContentBuilder, OpenApi as Document, Ref, ResponseBuilder};
use utoipa::{Modify, OpenApi, ToSchema};
use utoipa_swagger_ui::SwaggerUi;

/// Every refusal and failure: the HTTP status says what kind, `code` names it for programs
/// and `message` names the problem for people.
#[derive(Serialize, ToSchema)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

#[derive(Serialize, ToSchema)]
pub struct ErrorDetail {
    /// Stable, for programs: `bad_request`, `invalid`, `unauthorized`, `forbidden`,
    /// `not_found`, `conflict`, `too_large`, `unsupported_media_type`, `method_not_allowed`,
    /// `too_many_requests`, `unavailable`, `storage_unavailable` (the database takes no writes
    /// now: nothing was stored), `storage`, `internal`, or a policy file's own check
    /// (`missing_tensor`...).
    pub code: String,
    /// What is wrong, naming the field, value or limit.
    pub message: String,
}

#[derive(OpenApi)]
#[openapi(
    info(
        title = "celld",
        description = "The assembly cell service: jobs on the cell, live telemetry, run \
                       history, policies, demonstrations and training. Every route but health, \
                       metrics and this description takes `Authorization: Bearer TOKEN`; a \
                       token's role (viewer, operator, admin) decides what it may do.",
    ),
    components(schemas(ErrorBody)),
    modifiers(&Security),
    security(("bearer" = [])),
    tags(
        (name = "service", description = "Health, metrics, tokens and the audit log"),
        (name = "cell", description = "The cell's state, e-stop and reset"),
        (name = "jobs", description = "Assembly jobs and their recorded steps"),
        (name = "stats", description = "Run history summarised"),
        (name = "fleet", description = "Every cell of the fleet: cells, jobs, figures, registry"),
        (name = "telemetry", description = "Live steps and job changes (Server-Sent Events)"),
        (name = "policies", description = "Policy files: upload, evaluate, activate"),
        (name = "demonstrations", description = "Recorded expert demonstrations"),
        (name = "training", description = "Training runs that end in a candidate policy"),
    )
)]
struct Base;

struct Security;

impl Modify for Security {
    fn modify(&self, document: &mut Document) {
        let components = document.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(Http::new(HttpAuthScheme::Bearer)),
        );
        // A browser's EventSource cannot send headers: the telemetry stream also takes the
        // token in the query.
        components.add_security_scheme(
            "access_token",
            SecurityScheme::ApiKey(ApiKey::Query(ApiKeyValue::new("access_token"))),
        );
    }
}

/// The document's head: title, security schemes, tags, the error body.
pub fn base() -> Document {
    Base::openapi()
}

/// Completes the collected document: every operation answers its refusals and failures with
/// an [`ErrorBody`], whatever the status (`default`), besides the statuses it lists; and its
/// operationId is its tag and handler (`jobs_list`, `policies_read`), since OpenAPI asks it
/// to be unique across the document and generated clients name their functions by it, while
/// each resource names its handlers `list`, `read`, `cancel`.
pub fn finish(mut document: Document) -> Document {
    let error = ResponseBuilder::new()
        .description("Refused or failed: the status and the body say why")
        .content(
            "application/json",
            ContentBuilder::new()
                .schema(Some(Ref::from_schema_name("ErrorBody")))
                .build(),
        )
        .build();
    for item in document.paths.paths.values_mut() {
        let operations: [&mut Option<Operation>; 4] = [
            &mut item.get,
            &mut item.post,
            &mut item.delete,
            &mut item.put,
        ];
        for operation in operations.into_iter().flatten() {
            if let (Some(tag), Some(id)) = (
                operation.tags.as_ref().and_then(|tags| tags.first()),
                operation.operation_id.as_ref(),
            ) {
                operation.operation_id = Some(format!("{tag}_{id}"));
            }
            operation
                .responses
                .responses
                .entry("default".to_string())
                .or_insert_with(|| error.clone().into());
        }
    }
    document
}

/// Swagger UI at `/api/docs`, reading `/api/openapi.json` (served by `meta`).
pub fn browser() -> Router<Context> {
    SwaggerUi::new("/api/docs")
        .config(utoipa_swagger_ui::Config::from("/api/openapi.json"))
        .into()
}

#[cfg(test)]
mod tests {
    #[test]
    fn every_operation_has_an_error_answer_and_its_own_id_and_every_reference_resolves() {
        let text = crate::http::openapi_json();
        let value: serde_json::Value = serde_json::from_str(text).unwrap();
        let schemas = &value["components"]["schemas"];
        let mut operations = 0;
        let mut ids = std::collections::BTreeSet::new();
        for (path, item) in value["paths"].as_object().unwrap() {
            for (method, operation) in item.as_object().unwrap() {
                operations += 1;
                let id = operation["operationId"].as_str().unwrap();
                let tag = operation["tags"][0].as_str().unwrap();
                assert!(
                    id.starts_with(&format!("{tag}_")),
                    "{method} {path}: {id} is not named by its tag {tag}"
                );
                assert!(ids.insert(id.to_string()), "{method} {path}: {id} twice");
                assert!(
                    operation["responses"]["default"].is_object(),
                    "{method} {path} has no default (error) response"
                );
            }
        }
        // The operations the service serves, counted by hand from the routers.
        assert_eq!(operations, 42);
        for reference in text.split("\"$ref\":\"#/components/schemas/").skip(1) {
            let name = &reference[..reference.find('"').unwrap()];
            assert!(
                schemas[name].is_object(),
                "{name} is referenced, not defined"
            );
        }
    }
}
