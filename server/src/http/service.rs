//! The service endpoints: health, readiness, metrics, the model description, and the answers
//! to unknown routes and methods.

use axum::extract::State;
use axum::http::{header, HeaderValue, Uri};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Serialize;
use serde_json::json;

use super::openapi::refusals::{ReadinessRefusals, TokenRefusals};
use super::state::AppState;
use crate::error::ApiError;
use crate::request::Limits;

/// Liveness: the process serves HTTP.
#[utoipa::path(get, path = "/healthz", tag = "service", operation_id = "healthz", responses((status = 200, description = "Alive")))]
pub async fn healthz() -> Json<serde_json::Value> {
    Json(json!({"status": "ok"}))
}

/// The readiness probe's path. Its 503 while warming up is the expected answer, not a failure.
pub(super) const READINESS_PATH: &str = "/readyz";

/// Readiness: bundle loaded and warm-up render done (503 while warming up or shutting down, and
/// while the executor is stuck on a graph run long past its request's deadline).
/// Public for orchestrators, so it names no model: `/v1/model` does, behind the token.
#[utoipa::path(get, path = "/readyz", tag = "service", operation_id = "readyz", responses(
    (status = 200, description = "Ready"),
    ReadinessRefusals,
))]
pub async fn readyz(State(state): State<AppState>) -> Result<Json<serde_json::Value>, ApiError> {
    state.check_ready()?;
    let stuck = state.pipeline().executor().check_not_stuck();
    stuck.map_err(|message| ApiError::Unavailable { message, retry_after_secs: 5 })?;
    Ok(Json(json!({"status": "ready"})))
}

/// Prometheus metrics (OpenMetrics text).
#[utoipa::path(get, path = "/metrics", tag = "service", operation_id = "metrics", responses(
    (status = 200, description = "Metrics", content_type = "application/openmetrics-text", body = String),
))]
pub async fn metrics(State(state): State<AppState>) -> Response {
    let mut response = state.metrics.render().into_response();
    response.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(crate::metrics::CONTENT_TYPE));
    response
}

/// The served model: id, variant, hyper-parameters and provenance from the manifest, the most
/// views a scene may hold (`max_scene_views`; all the limits: `GET /v1/limits`), and how views
/// can be sampled (`sampling`: the modes, the default, guided sampling's policy).
#[utoipa::path(get, path = "/v1/model", tag = "render", operation_id = "model", responses(
    (status = 200, description = "Model description", body = Object),
    TokenRefusals,
), security((), ("bearer" = [])))]
pub async fn model(State(state): State<AppState>) -> Json<serde_json::Value> {
    let m = state.pipeline().manifest();
    Json(json!({
        "model_id": m.model_id,
        "variant": m.variant,
        "format_version": m.format_version,
        "config": m.config,
        "provenance": m.provenance,
        "max_scene_views": state.pipeline().limits().max_scene_views,
        "sampling": {
            "modes": state.pipeline().samplings(),
            "default": state.pipeline().default_sampling(),
            "samples_full": state.pipeline().config().samples,
            "guided": state.pipeline().bundle().guided(),
        },
    }))
}

/// `GET /v1/limits`: what the server accepts, for clients to check before they upload anything
/// (the `scnerf` client picks a capture's image set by `max_source_pixels`, thins it to
/// `max_scene_views` and sizes its uploads by the body limits).
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct LimitsBody {
    /// Most pixels (width x height) of one source image (`--max-source-pixels`).
    pub max_source_pixels: u64,
    /// Most pixels of a rendered view (`--max-target-pixels`).
    pub max_target_pixels: u64,
    /// Most views a scene may hold (`--max-scene-views`): larger captures are thinned to it.
    pub max_scene_views: usize,
    /// Largest body of `/v1/render`, `/v1/scenes` and `PUT /v1/scenes/{id}` (`--max-body-bytes`).
    pub max_body_bytes: usize,
    /// Largest body of `POST /v1/captures`: every file of a capture (`--max-capture-bytes`).
    pub max_capture_bytes: usize,
    /// Largest JSON document without images: a multipart `request` part, a scene-render body, a
    /// capture's listing (`--max-json-bytes`).
    pub max_json_bytes: usize,
}

impl From<&Limits> for LimitsBody {
    fn from(l: &Limits) -> Self {
        LimitsBody {
            max_source_pixels: l.max_source_pixels,
            max_target_pixels: l.max_target_pixels,
            max_scene_views: l.max_scene_views,
            max_body_bytes: l.max_body_bytes,
            max_capture_bytes: l.max_capture_bytes,
            max_json_bytes: l.max_json_bytes,
        }
    }
}

/// The server's request limits.
#[utoipa::path(get, path = "/v1/limits", tag = "render", operation_id = "limits", responses(
    (status = 200, description = "What the server accepts", body = LimitsBody),
    TokenRefusals,
), security((), ("bearer" = [])))]
pub async fn limits(State(state): State<AppState>) -> Json<LimitsBody> {
    Json(LimitsBody::from(state.pipeline().limits()))
}

pub async fn not_found(uri: Uri) -> Response {
    // The path is echoed in the message: keep a hostile one short.
    let path: String = uri.path().chars().take(200).collect();
    ApiError::NotFound { path }.into_response()
}

pub async fn method_not_allowed() -> Response {
    ApiError::MethodNotAllowed.into_response()
}
