//! The service endpoints: health, readiness, metrics, the model description, and the answers
//! to unknown routes and methods.

use axum::extract::State;
use axum::http::{header, HeaderValue, Uri};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde_json::json;

use super::state::AppState;
use crate::error::ApiError;

/// Liveness: the process serves HTTP.
#[utoipa::path(get, path = "/healthz", tag = "service", operation_id = "healthz", responses((status = 200, description = "Alive")))]
pub async fn healthz() -> Json<serde_json::Value> {
    Json(json!({"status": "ok"}))
}

/// Readiness: bundle loaded and warm-up render done (503 while warming up or shutting down).
/// Public for orchestrators, so it names no model: `/v1/model` does, behind the token.
#[utoipa::path(get, path = "/readyz", tag = "service", operation_id = "readyz", responses(
    (status = 200, description = "Ready"),
    (status = 503, description = "Warming up or shutting down", body = crate::error::ErrorBody),
))]
pub async fn readyz(State(state): State<AppState>) -> Result<Json<serde_json::Value>, ApiError> {
    state.check_ready()?;
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

/// The served model: id, variant, hyper-parameters and provenance from the manifest, and the
/// most views a scene may hold (`max_scene_views`: clients thin larger captures to it).
#[utoipa::path(get, path = "/v1/model", tag = "render", operation_id = "model", responses(
    (status = 200, description = "Model description", body = Object),
    (status = 401, description = "Missing or wrong bearer token", body = crate::error::ErrorBody),
), security((), ("bearer" = [])))]
pub async fn model(State(state): State<AppState>) -> Json<serde_json::Value> {
    let m = state.pipeline.manifest();
    Json(json!({
        "model_id": m.model_id,
        "variant": m.variant,
        "format_version": m.format_version,
        "config": m.config,
        "provenance": m.provenance,
        "max_scene_views": state.pipeline.limits().max_scene_views,
    }))
}

pub async fn not_found(uri: Uri) -> Response {
    // The path is echoed in the message: keep a hostile one short.
    let path: String = uri.path().chars().take(200).collect();
    ApiError::NotFound { path }.into_response()
}

pub async fn method_not_allowed() -> Response {
    ApiError::MethodNotAllowed.into_response()
}
