//! The error responses of the API's operations, in one place. Each is an [`ApiError`] with what
//! it means on that route: its status is the one `ApiError::status` gives it, so the document
//! cannot drift from error.rs. A handler's annotation names its family
//! (`responses((status = 200, ...), RenderRefusals)`), and the test below checks every error
//! each operation can answer with against the document.

use std::collections::BTreeMap;

use utoipa::openapi::content::ContentBuilder;
use utoipa::openapi::response::{Response, ResponseBuilder};
use utoipa::openapi::{Ref, RefOr};
use utoipa::{IntoResponses, ToSchema};

use crate::error::{ApiError, ErrorBody};

/// An error as documented: the error, and what it means on the route.
type Documented = (ApiError, &'static str);

const UNAUTHORIZED: Documented = (ApiError::Unauthorized { message: String::new() }, "Missing or wrong bearer token");
const FORBIDDEN: Documented = (
    ApiError::Forbidden { field: String::new(), message: String::new() },
    "A browser page of another site than the server's own and --allowed-origin's (`field`: `origin` or \
     `sec-fetch-site`)",
);
const NOT_ACCEPTABLE: Documented = (ApiError::NotAcceptable { message: String::new() }, "Accept cannot be satisfied");
const BODY_TIMEOUT: Documented = (ApiError::BodyTimeout { message: String::new() }, "The body arrived too slowly");
const TOO_MANY_REQUESTS: Documented = (
    ApiError::TooManyRequests { message: String::new(), retry_after_secs: 0 },
    "This client has too many requests in flight, or the work admitted ahead of the request would make it wait \
     too long or miss its deadline (Retry-After)",
);
const UNAVAILABLE: Documented = (
    ApiError::Unavailable { message: String::new(), retry_after_secs: 0 },
    "Warming up, overloaded, the memory budget in use, or the request cannot finish by its deadline even alone \
     (Retry-After)",
);
/// Readiness's 503: the probe's expected answer until the warm-up render is done, not a fault.
const WARMING_UP: Documented =
    (ApiError::Unavailable { message: String::new(), retry_after_secs: 0 }, "Warming up or shutting down");
const DEADLINE_EXCEEDED: Documented = (ApiError::DeadlineExceeded { ms: 0 }, "Deadline exceeded");
const INTERNAL: Documented = (
    ApiError::Internal(String::new()),
    "A failure of the server's own (the inference backend, an unexpected graph output), never caused by the request",
);
const SCENE_NOT_FOUND: Documented = (
    ApiError::SceneNotFound { id: String::new() },
    "No such scene here (unknown, expired, evicted, another token's, or on another replica): `hint: reupload`",
);

const MODEL_NOT_FOUND: Documented = (
    ApiError::ModelNotFound { name: String::new() },
    "`model` names no model this server serves (`GET /v1/models` lists them)",
);
const MODEL_MISMATCH: Documented = (
    ApiError::ModelMismatch { scene: String::new(), scene_model: String::new(), requested: String::new() },
    "`model` names another model than the scene's (the message names both)",
);

const fn malformed(description: &'static str) -> Documented {
    (ApiError::Malformed { field: None, message: String::new() }, description)
}

const fn too_large(description: &'static str) -> Documented {
    (ApiError::TooLarge { field: None, message: String::new() }, description)
}

const fn unsupported(description: &'static str) -> Documented {
    (ApiError::UnsupportedMediaType { field: None, message: String::new() }, description)
}

const fn invalid(description: &'static str) -> Documented {
    (ApiError::Invalid { field: String::new(), message: String::new() }, description)
}

/// The responses as utoipa puts them in an operation: by status, each with the error body. Two
/// errors of one status (404: no such scene, no such model) share it, their descriptions joined.
fn responses(documented: &[Documented]) -> BTreeMap<String, RefOr<Response>> {
    let body = ContentBuilder::new().schema(Some(Ref::from_schema_name(ErrorBody::name()))).build();
    let mut descriptions: BTreeMap<String, Vec<&str>> = BTreeMap::new();
    for (error, description) in documented {
        descriptions.entry(error.status().as_str().to_string()).or_default().push(description);
    }
    descriptions
        .into_iter()
        .map(|(status, said)| {
            let response =
                ResponseBuilder::new().description(said.join("; or ")).content("application/json", body.clone());
            (status, response.build().into())
        })
        .collect()
}

/// Error responses of the routes behind the bearer token that read no body: `GET /v1/model`
/// and `GET /v1/limits`.
pub struct TokenRefusals;

impl IntoResponses for TokenRefusals {
    fn responses() -> BTreeMap<String, RefOr<Response>> {
        responses(&[UNAUTHORIZED])
    }
}

/// Error responses of `POST /v1/models/reload`.
pub struct ReloadRefusals;

impl IntoResponses for ReloadRefusals {
    fn responses() -> BTreeMap<String, RefOr<Response>> {
        responses(&[UNAUTHORIZED, FORBIDDEN])
    }
}

/// Error responses of `GET /readyz` (public: orchestrators probe it without a token).
pub struct ReadinessRefusals;

impl IntoResponses for ReadinessRefusals {
    fn responses() -> BTreeMap<String, RefOr<Response>> {
        responses(&[WARMING_UP])
    }
}

/// Error responses of `POST /v1/render`.
pub struct RenderRefusals;

impl IntoResponses for RenderRefusals {
    fn responses() -> BTreeMap<String, RefOr<Response>> {
        responses(&[
            malformed("Malformed request"),
            UNAUTHORIZED,
            FORBIDDEN,
            NOT_ACCEPTABLE,
            BODY_TIMEOUT,
            too_large("Body or JSON document too large"),
            unsupported("Unsupported content type or image format"),
            invalid("Semantically invalid (camera, view count, sizes, near/far...)"),
            MODEL_NOT_FOUND,
            TOO_MANY_REQUESTS,
            UNAVAILABLE,
            DEADLINE_EXCEEDED,
            INTERNAL,
        ])
    }
}

/// Error responses of `POST /v1/scenes` and `PUT /v1/scenes/{id}`.
pub struct SceneUploadRefusals;

impl IntoResponses for SceneUploadRefusals {
    fn responses() -> BTreeMap<String, RefOr<Response>> {
        responses(&[
            malformed("Malformed request or scene id"),
            UNAUTHORIZED,
            FORBIDDEN,
            BODY_TIMEOUT,
            too_large("Body or JSON document too large"),
            unsupported("Unsupported content type or image format"),
            invalid("Semantically invalid"),
            MODEL_NOT_FOUND,
            TOO_MANY_REQUESTS,
            UNAVAILABLE,
            DEADLINE_EXCEEDED,
            INTERNAL,
        ])
    }
}

/// Error responses of `POST /v1/scenes/{id}/render`.
pub struct SceneRenderRefusals;

impl IntoResponses for SceneRenderRefusals {
    fn responses() -> BTreeMap<String, RefOr<Response>> {
        responses(&[
            malformed("Malformed request or scene id"),
            UNAUTHORIZED,
            FORBIDDEN,
            SCENE_NOT_FOUND,
            NOT_ACCEPTABLE,
            BODY_TIMEOUT,
            too_large("JSON document too large"),
            unsupported("Unsupported content type"),
            invalid("Semantically invalid target, or bad `sources`"),
            MODEL_NOT_FOUND,
            MODEL_MISMATCH,
            TOO_MANY_REQUESTS,
            UNAVAILABLE,
            DEADLINE_EXCEEDED,
            INTERNAL,
        ])
    }
}

/// Error responses of `DELETE /v1/scenes/{id}`.
pub struct SceneDeleteRefusals;

impl IntoResponses for SceneDeleteRefusals {
    fn responses() -> BTreeMap<String, RefOr<Response>> {
        responses(&[malformed("Malformed scene id"), UNAUTHORIZED, FORBIDDEN, SCENE_NOT_FOUND])
    }
}

/// Error responses of `POST /v1/captures`.
pub struct CaptureRefusals;

impl IntoResponses for CaptureRefusals {
    fn responses() -> BTreeMap<String, RefOr<Response>> {
        responses(&[
            malformed(
                "Malformed body, a part not named `file`, a file without a filename or sent twice, or a malformed \
                 scene id",
            ),
            UNAUTHORIZED,
            FORBIDDEN,
            BODY_TIMEOUT,
            too_large(
                "Body over --max-capture-bytes, or files other than images over --max-capture-metadata-bytes \
                 (`field` names the file)",
            ),
            unsupported("Not multipart/form-data, or an image format other than PNG/JPEG"),
            invalid(
                "Not a usable capture; `field` names the file (missing poses, unknown format, distorted camera, \
                 too few images, ...)",
            ),
            MODEL_NOT_FOUND,
            TOO_MANY_REQUESTS,
            UNAVAILABLE,
            DEADLINE_EXCEEDED,
            INTERNAL,
        ])
    }
}

/// Error responses of `POST /v1/captures/plan`.
pub struct CapturePlanRefusals;

impl IntoResponses for CapturePlanRefusals {
    fn responses() -> BTreeMap<String, RefOr<Response>> {
        responses(&[
            malformed("Malformed JSON or an unknown field (`field` names it), or a malformed deadline header"),
            UNAUTHORIZED,
            FORBIDDEN,
            BODY_TIMEOUT,
            too_large("The listing is larger than --max-json-bytes"),
            unsupported("Not application/json"),
            invalid(
                "A listing that cannot be planned; `field` names the entry (`files[3]`: not a path inside the \
                 folder, or listed twice; `sizes[0]`: not a listed image, given twice, or no pixels), `files` (no \
                 capture files, or no format the readers know) or `downscale` (no such image set)",
            ),
            TOO_MANY_REQUESTS,
            UNAVAILABLE,
            DEADLINE_EXCEEDED,
            INTERNAL,
        ])
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    use serde_json::Value;

    use super::*;
    use crate::http::openapi::document;

    /// Every operation of the document, by its id.
    const OPERATIONS: [&str; 15] = [
        "render",
        "create_scene",
        "put_scene",
        "render_scene",
        "delete_scene",
        "create_capture_scene",
        "plan_capture",
        "model",
        "limits",
        "models",
        "reload_models",
        "healthz",
        "readyz",
        "metrics",
        "openapi",
    ];
    /// Behind the bearer token (all but the public paths of `auth::PUBLIC_PATHS`).
    const AUTHENTICATED: &[&str] = &[
        "render",
        "create_scene",
        "put_scene",
        "render_scene",
        "delete_scene",
        "create_capture_scene",
        "plan_capture",
        "model",
        "limits",
        "models",
        "reload_models",
    ];
    /// POST and PUT: the in-flight limit, a `Deadline` (readiness, the deadline header), a body
    /// read and validated, then work on the executor or a blocking thread.
    const WITH_BODY: &[&str] =
        &["render", "create_scene", "put_scene", "render_scene", "create_capture_scene", "plan_capture"];
    /// Answers in the format that Accept asks for.
    const RENDERING: &[&str] = &["render", "render_scene"];
    /// Needs a scene that exists.
    const OF_A_SCENE: &[&str] = &["render_scene", "delete_scene"];
    /// May name a model.
    const NAMING_A_MODEL: &[&str] = &["render", "create_scene", "put_scene", "render_scene", "create_capture_scene"];

    /// One error of each kind of `ApiError` (add a new kind here and to `answering`).
    fn one_of_each() -> Vec<ApiError> {
        let message = String::new;
        vec![
            ApiError::Malformed { field: None, message: message() },
            ApiError::TooLarge { field: None, message: message() },
            ApiError::UnsupportedMediaType { field: None, message: message() },
            ApiError::NotAcceptable { message: message() },
            ApiError::Invalid { field: message(), message: message() },
            ApiError::Unauthorized { message: message() },
            ApiError::Forbidden { field: message(), message: message() },
            ApiError::NotFound { path: message() },
            ApiError::SceneNotFound { id: message() },
            ApiError::ModelNotFound { name: message() },
            ApiError::ModelMismatch { scene: message(), scene_model: message(), requested: message() },
            ApiError::MethodNotAllowed,
            ApiError::BodyTimeout { message: message() },
            ApiError::TooManyRequests { message: message(), retry_after_secs: 1 },
            ApiError::Unavailable { message: message(), retry_after_secs: 1 },
            ApiError::DeadlineExceeded { ms: 1 },
            ApiError::Internal(message()),
        ]
    }

    /// The operations that can answer with `error`. The match is exhaustive: a new kind of
    /// error does not compile until it is placed here.
    fn answering(error: &ApiError) -> Vec<&'static str> {
        match error {
            ApiError::Unauthorized { .. } => AUTHENTICATED.to_vec(),
            // From a browser page of another site: everything but reading.
            ApiError::Forbidden { .. } => [WITH_BODY, &["delete_scene", "reload_models"]].concat(),
            // A bad body, deadline header or scene id (in the path or the proxy's header).
            ApiError::Malformed { .. } => [WITH_BODY, &["delete_scene"]].concat(),
            // Internal: a failure of the executor, a graph or a blocking thread, which the body's work runs.
            ApiError::TooLarge { .. }
            | ApiError::UnsupportedMediaType { .. }
            | ApiError::Invalid { .. }
            | ApiError::BodyTimeout { .. }
            | ApiError::TooManyRequests { .. }
            | ApiError::DeadlineExceeded { .. }
            | ApiError::Internal(_) => WITH_BODY.to_vec(),
            ApiError::NotAcceptable { .. } => RENDERING.to_vec(),
            ApiError::SceneNotFound { .. } => OF_A_SCENE.to_vec(),
            ApiError::ModelNotFound { .. } => NAMING_A_MODEL.to_vec(),
            // Only a scene's render can name another model than the scene's.
            ApiError::ModelMismatch { .. } => vec!["render_scene"],
            // Warming up or overloaded; the readiness probe's answer while warming up.
            ApiError::Unavailable { .. } => [WITH_BODY, &["readyz"]].concat(),
            // The router's answers to a path or a method that no operation has.
            ApiError::NotFound { .. } | ApiError::MethodNotAllowed => vec![],
        }
    }

    /// The error statuses (4xx, 5xx) that the document gives each operation, by operation id.
    fn documented_errors(doc: &Value) -> BTreeMap<String, BTreeSet<u16>> {
        let operations = doc["paths"].as_object().unwrap().values().flat_map(|path| path.as_object().unwrap().values());
        operations
            .map(|op| {
                let statuses = op["responses"].as_object().unwrap().keys().map(|s| s.parse::<u16>().unwrap());
                (op["operationId"].as_str().unwrap().to_string(), statuses.filter(|&s| s >= 400).collect())
            })
            .collect()
    }

    /// Every status that error.rs gives an error an operation can answer with is in the
    /// document, and the document promises no other error.
    #[test]
    fn every_error_an_operation_can_answer_with_is_documented() {
        let mut expected: BTreeMap<String, BTreeSet<u16>> =
            OPERATIONS.iter().map(|op| (op.to_string(), BTreeSet::new())).collect();
        for error in one_of_each() {
            for op in answering(&error) {
                expected.get_mut(op).unwrap().insert(error.status().as_u16());
            }
        }
        let documented = documented_errors(&document());
        let operations: BTreeSet<&String> = documented.keys().chain(expected.keys()).collect();
        let wrong: Vec<String> = operations
            .into_iter()
            .filter_map(|op| {
                let (said, can) = (documented.get(op).cloned().unwrap_or_default(), expected.get(op));
                let can = can.cloned().unwrap_or_default();
                (said != can).then(|| {
                    let missing: Vec<_> = can.difference(&said).collect();
                    let extra: Vec<_> = said.difference(&can).collect();
                    format!("{op}: undocumented {missing:?}, documented but never answered {extra:?}")
                })
            })
            .collect();
        assert!(wrong.is_empty(), "the document's errors differ from error.rs's:\n{}", wrong.join("\n"));
    }

    /// What the document says of a family: the error body, and the description given.
    #[test]
    fn refusals_carry_the_error_body_and_their_routes_description() {
        let doc = document();
        let cases = [
            ("/v1/scenes/{id}", "delete", "404", SCENE_NOT_FOUND.1),
            ("/v1/model", "get", "401", UNAUTHORIZED.1),
            ("/readyz", "get", "503", WARMING_UP.1),
        ];
        for (path, method, status, description) in cases {
            let response = &doc["paths"][path][method]["responses"][status];
            assert_eq!(response["content"]["application/json"]["schema"]["$ref"], "#/components/schemas/Error");
            assert_eq!(response["description"], description, "{method} {path} {status}");
        }
    }

    /// `AUTHENTICATED` is auth.rs's rule, not a second one: the token guards exactly the
    /// operations off `auth::PUBLIC_PATHS`, and each of them declares the bearer scheme.
    #[test]
    fn the_operations_behind_the_token_are_those_auth_guards() {
        let doc = document();
        for (path, operations) in doc["paths"].as_object().unwrap() {
            let guarded = !crate::auth::PUBLIC_PATHS.contains(&path.as_str());
            for op in operations.as_object().unwrap().values() {
                let id = op["operationId"].as_str().unwrap();
                assert_eq!(AUTHENTICATED.contains(&id), guarded, "{id}: listed as authenticated");
                let bearer = op["security"].as_array().is_some_and(|s| s.iter().any(|r| r.get("bearer").is_some()));
                assert_eq!(bearer, guarded, "{id}: declares the bearer scheme");
            }
        }
    }
}
