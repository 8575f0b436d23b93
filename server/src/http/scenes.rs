//! The scene cache endpoints: `POST /v1/scenes` (encode the sources once),
//! `POST /v1/scenes/{id}/render` (a view of a cached scene: the renderer only) and
//! `DELETE /v1/scenes/{id}`.

use std::time::Instant;

use axum::extract::rejection::PathRejection;
use axum::extract::{Path, Request, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

use super::body::{read_scene_request, read_target_request};
use super::deadline::Deadline;
use super::negotiate::{request_format, response_format};
use super::respond::{finish, set_common_headers};
use super::state::AppState;
use crate::cache::{is_valid_id, rfc3339, Owner};
use crate::error::ApiError;
use crate::pipeline::Timings;

/// `201 Created` body of `POST /v1/scenes`.
#[derive(Debug, Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct SceneCreated {
    /// 32 hex digits; use it in `/v1/scenes/{id}/render` and `DELETE /v1/scenes/{id}`.
    pub scene_id: String,
    /// RFC 3339 UTC. The scene expires this long after its last use; every render extends it
    /// (the new time is in the render response's `x-scene-expires-at` header).
    pub expires_at: String,
}

/// Who is asking (set by the auth layer; `None` when auth is off).
fn owner_of(req: &Request) -> Owner {
    req.extensions().get::<crate::auth::Principal>().and_then(|p| p.owner())
}

fn scene_id(path: Result<Path<String>, PathRejection>) -> Result<String, ApiError> {
    let Path(id) = path.map_err(|e| ApiError::malformed(Some("scene_id".to_string()), e.body_text()))?;
    if !is_valid_id(&id) {
        return Err(ApiError::malformed(Some("scene_id".to_string()), "a scene id is 32 lowercase hex digits"));
    }
    Ok(id)
}

/// `POST /v1/scenes`: decode the sources, run the encoder and the volume net, keep the result.
#[utoipa::path(
    post, path = "/v1/scenes", tag = "render", operation_id = "create_scene",
    request_body(content(
        (crate::http::schema::SceneMultipart = "multipart/form-data"),
        (crate::request::wire::JsonSceneRequest = "application/json"),
        (crate::http::schema::Binary = "application/x-protobuf"),
    ), description = "Source views + cameras, near/far (no target); protobuf: scnerf.v1.SceneRequest"),
    params(
        ("x-scnerf-deadline-ms" = Option<u64>, Header, nullable = false, minimum = 1, description = "Shortens the server's deadline for this request (ms)"),
    ),
    responses(
        (status = 201, description = "Scene cached", body = SceneCreated,
         headers(("location" = String, description = "/v1/scenes/{scene_id}")),
         links(
             ("RenderScene" = (operation_id = "render_scene", parameters(("id" = "$response.body#/scene_id")))),
             ("DeleteScene" = (operation_id = "delete_scene", parameters(("id" = "$response.body#/scene_id")))),
         )),
        (status = 400, description = "Malformed request", body = crate::error::ErrorBody),
        (status = 401, description = "Missing or wrong bearer token", body = crate::error::ErrorBody),
        (status = 408, description = "The body arrived too slowly", body = crate::error::ErrorBody),
        (status = 413, description = "Body or JSON document too large", body = crate::error::ErrorBody),
        (status = 415, description = "Unsupported content type or image format", body = crate::error::ErrorBody),
        (status = 422, description = "Semantically invalid", body = crate::error::ErrorBody),
        (status = 429, description = "This client has too many requests in flight (Retry-After)", body = crate::error::ErrorBody),
        (status = 503, description = "Warming up, overloaded, or the request cannot finish by its deadline (Retry-After)", body = crate::error::ErrorBody),
        (status = 504, description = "Deadline exceeded", body = crate::error::ErrorBody),
    ),
    security((), ("bearer" = [])),
)]
pub async fn create(State(state): State<AppState>, deadline: Deadline, req: Request) -> Result<Response, ApiError> {
    deadline.run(create_within(state, deadline, req)).await
}

async fn create_within(state: AppState, deadline: Deadline, req: Request) -> Result<Response, ApiError> {
    let format = request_format(req.headers())?;
    let owner = owner_of(&req);
    let pipeline = &state.pipeline;
    let parsed = read_scene_request(format, req, pipeline.limits()).await?;
    let valid = parsed.validate(pipeline.config(), pipeline.limits())?;
    let mut timings = Timings::default();
    let scene = pipeline.encode_scene(&valid, deadline.at(), &mut timings).await?;
    let (scene_id, expires) = state.scenes.insert(scene, valid.background, owner, Instant::now())?;
    timings.add("total", deadline.started().elapsed());
    tracing::info!(%scene_id, timings = ?timings.millis(), "scene cached");
    state.metrics.observe_stages(&timings);

    let location = format!("/v1/scenes/{scene_id}");
    let body = SceneCreated { scene_id, expires_at: rfc3339(expires) };
    let mut response = (StatusCode::CREATED, axum::Json(body)).into_response();
    if let Ok(v) = HeaderValue::from_str(&location) {
        response.headers_mut().insert(header::LOCATION, v);
    }
    set_common_headers(&mut response, &timings, &pipeline.manifest().model_id);
    Ok(response)
}

/// `POST /v1/scenes/{id}/render`: a target view of a cached scene, answered exactly like
/// `/v1/render`.
#[utoipa::path(
    post, path = "/v1/scenes/{id}/render", tag = "render", operation_id = "render_scene",
    request_body(content(
        (crate::request::wire::JsonTargetRequest = "application/json"),
        (crate::http::schema::Binary = "application/x-protobuf"),
    ), description = "Target camera and outputs; protobuf: scnerf.v1.SceneRenderRequest"),
    params(
        ("id" = String, Path, description = "scene_id from POST /v1/scenes", pattern = "^[0-9a-f]{32}$"),
        ("x-scnerf-deadline-ms" = Option<u64>, Header, nullable = false, minimum = 1, description = "Shortens the server's deadline for this request (ms)"),
    ),
    responses(
        (status = 200, description = "The rendered view, as for /v1/render", content(
            (crate::http::schema::Binary = "image/png"),
            (crate::http::respond::RenderResponseJson = "application/json"),
            (crate::http::schema::Binary = "application/x-protobuf"),
        ), headers(("x-scene-expires-at" = String, description = "New expiry of the scene (RFC 3339)"))),
        (status = 400, description = "Malformed request or scene id", body = crate::error::ErrorBody),
        (status = 401, description = "Missing or wrong bearer token", body = crate::error::ErrorBody),
        (status = 404, description = "No such scene (unknown, expired, evicted, or another token's)", body = crate::error::ErrorBody),
        (status = 406, description = "Accept cannot be satisfied", body = crate::error::ErrorBody),
        (status = 408, description = "The body arrived too slowly", body = crate::error::ErrorBody),
        (status = 413, description = "JSON document too large", body = crate::error::ErrorBody),
        (status = 415, description = "Unsupported content type", body = crate::error::ErrorBody),
        (status = 422, description = "Semantically invalid target", body = crate::error::ErrorBody),
        (status = 429, description = "This client has too many requests in flight (Retry-After)", body = crate::error::ErrorBody),
        (status = 503, description = "Warming up, overloaded, or the request cannot finish by its deadline (Retry-After)", body = crate::error::ErrorBody),
        (status = 504, description = "Deadline exceeded", body = crate::error::ErrorBody),
    ),
    security((), ("bearer" = [])),
)]
pub async fn render(
    State(state): State<AppState>,
    deadline: Deadline,
    path: Result<Path<String>, PathRejection>,
    req: Request,
) -> Result<Response, ApiError> {
    let id = scene_id(path)?;
    deadline.run(render_within(state, deadline, id, req)).await
}

async fn render_within(state: AppState, deadline: Deadline, id: String, req: Request) -> Result<Response, ApiError> {
    let format = request_format(req.headers())?;
    let headers = req.headers().clone();
    let owner = owner_of(&req);
    let pipeline = &state.pipeline;
    let parsed = read_target_request(format, req, pipeline.limits()).await?;
    let valid = parsed.validate(pipeline.limits())?;
    let out_format = response_format(&headers, valid.outputs)?;
    let hit = state.scenes.get(&id, &owner, Instant::now()).ok_or(ApiError::SceneNotFound { id })?;
    let mut timings = Timings::default();
    let cached = &hit.scene;
    let view =
        pipeline.render_scene(&cached.scene, &valid.target, cached.background, deadline.at(), &mut timings).await?;
    let mut response = finish(&state, view, valid.outputs, out_format, timings, deadline.started()).await?;
    if let Ok(v) = HeaderValue::from_str(&rfc3339(hit.expires_at)) {
        response.headers_mut().insert("x-scene-expires-at", v);
    }
    Ok(response)
}

/// `DELETE /v1/scenes/{id}`: 204, or 404 when there is no such scene (for this client).
#[utoipa::path(
    delete, path = "/v1/scenes/{id}", tag = "render", operation_id = "delete_scene",
    params(("id" = String, Path, description = "scene_id from POST /v1/scenes", pattern = "^[0-9a-f]{32}$")),
    responses(
        (status = 204, description = "Deleted"),
        (status = 400, description = "Malformed scene id", body = crate::error::ErrorBody),
        (status = 401, description = "Missing or wrong bearer token", body = crate::error::ErrorBody),
        (status = 404, description = "No such scene", body = crate::error::ErrorBody),
    ),
    security((), ("bearer" = [])),
)]
pub async fn delete(
    State(state): State<AppState>,
    path: Result<Path<String>, PathRejection>,
    req: Request,
) -> Result<StatusCode, ApiError> {
    let id = scene_id(path)?;
    if state.scenes.remove(&id, &owner_of(&req), Instant::now()) {
        Ok(StatusCode::NO_CONTENT)
    } else {
        Err(ApiError::SceneNotFound { id })
    }
}
