//! The scene endpoints: `POST /v1/scenes` (a new scene under a random id), `PUT /v1/scenes/{id}`
//! (under the client's id, replacing one of that id), `POST /v1/scenes/{id}/render` (a view of
//! it: the renderer alone once its sources' volume is cached) and `DELETE /v1/scenes/{id}`.

use std::sync::Arc;

use axum::extract::rejection::PathRejection;
use axum::extract::{Path, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use utoipa::openapi::path::{Parameter, ParameterBuilder, ParameterIn};
use utoipa::openapi::schema::{ObjectBuilder, Type};
use utoipa::openapi::Required;

use super::body::{read_scene_request, read_target_request};
use super::deadline::Deadline;
use super::negotiate::{request_format, response_format};
use super::openapi::refusals::{SceneDeleteRefusals, SceneRenderRefusals, SceneUploadRefusals};
use super::respond::rfc3339;
use super::respond::{finish, set_common_headers, Rendered};
use super::state::AppState;
use crate::cache::{is_valid_id, NewScene, Owner, Stored, ID_PATTERN};
use crate::error::ApiError;
use crate::models::Model;
use crate::pipeline::scene::Timings;
use crate::pipeline::views::choose;
use crate::request::ValidScene;

/// Header with which a routing proxy names a scene that `POST /v1/scenes` or `POST /v1/captures`
/// creates: the proxy picks the id, routes the request by its hash, and every later request for
/// the scene (its id in the path) hashes to the same replica (docs/deploy.md).
pub const SCENE_ID_HEADER: &str = "x-scnerf-scene-id";

/// The scene id in the path of `/v1/scenes/{id}` and `/v1/scenes/{id}/render`, as the
/// annotations of their handlers document it (`params(SceneIdInPath)`).
pub struct SceneIdInPath;

impl utoipa::IntoParams for SceneIdInPath {
    fn into_params(_: impl Fn() -> Option<ParameterIn>) -> Vec<Parameter> {
        let description = "The scene's id (the client's own, given with PUT, or the random one from POST), private \
                           to the client's token";
        vec![scene_id_parameter("id", ParameterIn::Path, Required::True, description)]
    }
}

/// [`SCENE_ID_HEADER`], as the annotations of the handlers that create a scene document it.
pub struct SceneIdHeader;

impl utoipa::IntoParams for SceneIdHeader {
    fn into_params(_: impl Fn() -> Option<ParameterIn>) -> Vec<Parameter> {
        let description =
            "Set by a routing proxy: the id to give the new scene (replacing this client's scene of that id)";
        vec![scene_id_parameter(SCENE_ID_HEADER, ParameterIn::Header, Required::False, description)]
    }
}

fn scene_id_parameter(name: &str, at: ParameterIn, required: Required, description: &str) -> Parameter {
    let id = ObjectBuilder::new().schema_type(Type::String).pattern(Some(ID_PATTERN));
    let parameter = ParameterBuilder::new().name(name).parameter_in(at).required(required);
    parameter.description(Some(description)).schema(Some(id)).build()
}

/// `201 Created` (or `200 OK`: replaced) body of `POST /v1/scenes` and `PUT /v1/scenes/{id}`.
#[derive(Debug, Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct SceneCreated {
    /// The scene's id: the client's (PUT), else 32 random hex digits. Use it in
    /// `/v1/scenes/{id}/render` and `DELETE /v1/scenes/{id}`.
    pub scene_id: String,
    /// RFC 3339 UTC. The scene expires this long after its last use; every render extends it
    /// (the new time is in the render response's `x-scene-expires-at` header).
    pub expires_at: String,
    /// The model the scene belongs to: its renders use it.
    pub model: String,
}

/// Who is asking (set by the auth layer; `None` when auth is off).
pub(super) fn owner_of(req: &Request) -> Owner {
    req.extensions().get::<crate::auth::Principal>().and_then(|p| p.owner())
}

fn valid_id(id: String, field: &str) -> Result<String, ApiError> {
    if !is_valid_id(&id) {
        return Err(ApiError::malformed(
            Some(field.to_string()),
            "a scene id is 1 to 64 characters of A-Z, a-z, 0-9, '.', '_' and '-' (not '.' or '..')",
        ));
    }
    Ok(id)
}

fn scene_id(path: Result<Path<String>, PathRejection>) -> Result<String, ApiError> {
    let Path(id) = path.map_err(|e| ApiError::malformed(Some("scene_id".to_string()), e.body_text()))?;
    valid_id(id, "scene_id")
}

/// The id a routing proxy chose for a new scene, if it sent one (see [`SCENE_ID_HEADER`]).
pub(super) fn proxy_scene_id(headers: &HeaderMap) -> Result<Option<String>, ApiError> {
    let Some(value) = headers.get(SCENE_ID_HEADER) else { return Ok(None) };
    let id = value.to_str().map_err(|_| ApiError::malformed(Some(SCENE_ID_HEADER.to_string()), "not ASCII"))?;
    valid_id(id.to_string(), SCENE_ID_HEADER).map(Some)
}

/// Decodes a validated scene's views (and, for 3 views, builds its volume) and caches it under
/// `id` (`None`: a random id).
pub(super) async fn store_scene(
    state: &AppState,
    model: &Model,
    valid: ValidScene,
    id: Option<String>,
    owner: Owner,
    deadline: &Deadline,
    timings: &mut Timings,
) -> Result<Stored, ApiError> {
    // A scene larger than the whole cache is refused before its images are decoded.
    state.scenes.check_fits(model.pipeline.scene_bytes(&valid))?;
    let (views, volume) = model.pipeline.encode_scene(&valid, deadline.due(), timings).await?;
    let new = NewScene { views, volume, background: valid.background, model: model.name.clone() };
    let stored = state.scenes.insert(id, owner, new, state.clock.now())?;
    timings.add("total", deadline.started().elapsed());
    tracing::info!(scene_id = %stored.id, model = %model.name, replaced = stored.replaced,
                   views = valid.sources.len(), timings = ?timings.millis(), "scene cached");
    state.metrics.observe_stages(model, timings);
    Ok(stored)
}

/// A scene endpoint's success: `body` with `Location: /v1/scenes/{id}` and the common headers.
pub(super) fn scene_response(
    model: &Model,
    status: StatusCode,
    id: &str,
    body: impl Serialize,
    timings: &Timings,
) -> Response {
    let mut response = (status, axum::Json(body)).into_response();
    if let Ok(v) = HeaderValue::from_str(&format!("/v1/scenes/{id}")) {
        response.headers_mut().insert(header::LOCATION, v);
    }
    set_common_headers(&mut response, timings, model);
    response
}

/// `POST /v1/scenes`: decode the sources (3 views: and build their volume) and keep them.
#[utoipa::path(
    post, path = "/v1/scenes", tag = "render", operation_id = "create_scene",
    request_body(content(
        (crate::http::schema::SceneMultipart = "multipart/form-data"),
        (crate::request::wire::JsonSceneRequest = "application/json"),
        (crate::http::schema::Binary = "application/x-protobuf"),
    ), description = "Source views + cameras, near/far (no target): 3 views, or a capture of up to max_scene_views (GET /v1/model); protobuf: scnerf.v1.SceneRequest"),
    params(Deadline, SceneIdHeader),
    responses(
        (status = 201, description = "Scene cached", body = SceneCreated,
         headers(("location" = String, description = "/v1/scenes/{scene_id}")),
         links(
             ("RenderScene" = (operation_id = "render_scene", parameters(("id" = "$response.body#/scene_id")))),
             ("DeleteScene" = (operation_id = "delete_scene", parameters(("id" = "$response.body#/scene_id")))),
         )),
        SceneUploadRefusals,
    ),
    security((), ("bearer" = [])),
)]
pub async fn create(State(state): State<AppState>, deadline: Deadline, req: Request) -> Result<Response, ApiError> {
    let id = proxy_scene_id(req.headers())?;
    deadline.run(put_within(state, deadline, id, req)).await
}

/// `PUT /v1/scenes/{id}`: the same as `POST /v1/scenes`, under the client's id.
#[utoipa::path(
    put, path = "/v1/scenes/{id}", tag = "render", operation_id = "put_scene",
    request_body(content(
        (crate::http::schema::SceneMultipart = "multipart/form-data"),
        (crate::request::wire::JsonSceneRequest = "application/json"),
        (crate::http::schema::Binary = "application/x-protobuf"),
    ), description = "As for POST /v1/scenes"),
    params(SceneIdInPath, Deadline),
    responses(
        (status = 201, description = "Scene cached under a new id", body = SceneCreated,
         headers(("location" = String, description = "/v1/scenes/{scene_id}"))),
        (status = 200, description = "Scene cached, replacing the scene of this id", body = SceneCreated,
         headers(("location" = String, description = "/v1/scenes/{scene_id}"))),
        SceneUploadRefusals,
    ),
    security((), ("bearer" = [])),
)]
pub async fn put(
    State(state): State<AppState>,
    deadline: Deadline,
    path: Result<Path<String>, PathRejection>,
    req: Request,
) -> Result<Response, ApiError> {
    let id = scene_id(path)?;
    deadline.run(put_within(state, deadline, Some(id), req)).await
}

async fn put_within(
    state: AppState,
    deadline: Deadline,
    id: Option<String>,
    req: Request,
) -> Result<Response, ApiError> {
    let format = request_format(req.headers())?;
    let owner = owner_of(&req);
    let parsed = read_scene_request(format, req, state.pipeline().limits()).await?;
    let model = state.models.get(parsed.model.as_deref())?;
    let valid = parsed.validate(model.pipeline.config(), model.pipeline.limits())?;
    let mut timings = Timings::default();
    let stored = store_scene(&state, &model, valid, id, owner, &deadline, &mut timings).await?;
    let status = if stored.replaced { StatusCode::OK } else { StatusCode::CREATED };
    let body = SceneCreated {
        scene_id: stored.id.clone(),
        expires_at: rfc3339(stored.expires_at),
        model: model.name.to_string(),
    };
    Ok(scene_response(&model, status, &stored.id, body, &timings))
}

/// `POST /v1/scenes/{id}/render`: a target view of a cached scene, answered exactly like
/// `/v1/render`, from the views the request pins or the server chooses.
#[utoipa::path(
    post, path = "/v1/scenes/{id}/render", tag = "render", operation_id = "render_scene",
    request_body(content(
        (crate::request::wire::JsonTargetRequest = "application/json"),
        (crate::http::schema::Binary = "application/x-protobuf"),
    ), description = "Target camera, outputs and optionally the views to render from; protobuf: scnerf.v1.SceneRenderRequest"),
    params(SceneIdInPath, Deadline),
    responses(
        (status = 200, description = "The rendered view, as for /v1/render", content(
            (crate::http::schema::Binary = "image/png"),
            (crate::http::respond::RenderResponseJson = "application/json"),
            (crate::http::schema::Binary = "application/x-protobuf"),
        ), headers(
            ("x-scene-expires-at" = String, description = "New expiry of the scene (RFC 3339)"),
            ("x-scnerf-sources" = String, description = "The views rendered from, i,j,k (the volume's reference first)"),
        )),
        SceneRenderRefusals,
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
    let parsed = read_target_request(format, req, state.pipeline().limits()).await?;
    let requested = parsed.model.clone();
    let valid = parsed.validate(state.pipeline().limits())?;
    let out_format = response_format(&headers, valid.outputs)?;
    let hit =
        state.scenes.get(&id, &owner, state.clock.now()).ok_or_else(|| ApiError::SceneNotFound { id: id.clone() })?;
    let scene = &hit.scene;
    let model = scene_model(&state, &id, &scene.model, requested)?;
    let pipeline = &model.pipeline;
    let sources = choose(&scene.views.cameras, &valid.target, valid.sources.as_deref(), pipeline.config().views)?;
    let cached = state.scenes.volume(scene, &sources);
    let mut timings = Timings::default();
    let (view, built) = pipeline
        .render_sources(
            &scene.views,
            &sources,
            cached,
            &valid.target,
            valid.sampling,
            scene.background,
            deadline.due(),
            &mut timings,
        )
        .await?;
    if let Some(volume) = built {
        state.scenes.insert_volume(scene, sources.clone(), volume);
    }
    let rendered = Rendered { view, sources, model: model.clone() };
    let mut response = finish(&state, rendered, valid.outputs, out_format, timings, deadline.started()).await?;
    if let Ok(v) = HeaderValue::from_str(&rfc3339(hit.expires_at)) {
        response.headers_mut().insert("x-scene-expires-at", v);
    }
    Ok(response)
}

/// The model a scene is rendered with: its own. A request naming another is refused (409
/// `model_mismatch`, naming both) rather than rendered with a model the scene's volumes do not
/// belong to.
fn scene_model(state: &AppState, id: &str, own: &Arc<str>, requested: Option<String>) -> Result<Arc<Model>, ApiError> {
    match requested {
        Some(name) if *name != **own => {
            // An unknown name is the client's typo, whatever the scene: say so first.
            state.models.get(Some(&name))?;
            Err(ApiError::ModelMismatch { scene: id.to_string(), scene_model: own.to_string(), requested: name })
        }
        _ => state.models.get(Some(own)),
    }
}

/// `DELETE /v1/scenes/{id}`: 204, or 404 when there is no such scene (for this client).
#[utoipa::path(
    delete, path = "/v1/scenes/{id}", tag = "render", operation_id = "delete_scene",
    params(SceneIdInPath),
    responses(
        (status = 204, description = "Deleted"),
        SceneDeleteRefusals,
    ),
    security((), ("bearer" = [])),
)]
pub async fn delete(
    State(state): State<AppState>,
    path: Result<Path<String>, PathRejection>,
    req: Request,
) -> Result<StatusCode, ApiError> {
    let id = scene_id(path)?;
    if state.scenes.remove(&id, &owner_of(&req), state.clock.now()) {
        Ok(StatusCode::NO_CONTENT)
    } else {
        Err(ApiError::SceneNotFound { id })
    }
}
