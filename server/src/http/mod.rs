//! HTTP API (axum): routes, shared state, health and model endpoints.

pub mod body;
pub mod negotiate;
pub mod render;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::{DefaultBodyLimit, State};
use axum::http::Uri;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde_json::json;
use tower_http::trace::TraceLayer;

use crate::error::ApiError;
use crate::pipeline::Pipeline;

/// State shared by all handlers.
#[derive(Clone)]
pub struct AppState {
    pub pipeline: Pipeline,
    /// Set once the warm-up render succeeded.
    pub ready: Arc<AtomicBool>,
    pub request_timeout: Duration,
}

impl AppState {
    pub fn is_ready(&self) -> bool {
        self.ready.load(Ordering::Acquire)
    }

    pub fn set_ready(&self) {
        self.ready.store(true, Ordering::Release);
    }

    fn check_ready(&self) -> Result<(), ApiError> {
        if self.is_ready() {
            Ok(())
        } else {
            Err(ApiError::Unavailable { message: "the model is warming up".into(), retry_after_secs: 5 })
        }
    }
}

pub fn router(state: AppState) -> Router {
    let body_limit = state.pipeline.limits.max_body_bytes;
    Router::new()
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/v1/model", get(model))
        .route("/v1/render", post(render::render))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        // Multipart reads this limit; JSON and protobuf bodies are read with the same limit.
        .layer(DefaultBodyLimit::max(body_limit))
        .layer(TraceLayer::new_for_http())
        .with_state(state)
}

/// Liveness: the process serves HTTP.
async fn healthz() -> Json<serde_json::Value> {
    Json(json!({"status": "ok"}))
}

/// Readiness: bundle loaded and warm-up render done.
async fn readyz(State(state): State<AppState>) -> Result<Json<serde_json::Value>, ApiError> {
    state.check_ready()?;
    Ok(Json(json!({"status": "ready", "model_id": state.pipeline.bundle.manifest.model_id})))
}

/// The served model: id, variant, hyper-parameters and provenance from the manifest.
async fn model(State(state): State<AppState>) -> Json<serde_json::Value> {
    let m = &state.pipeline.bundle.manifest;
    Json(json!({
        "model_id": m.model_id,
        "variant": m.variant,
        "format_version": m.format_version,
        "config": m.config,
        "provenance": m.provenance,
    }))
}

async fn not_found(uri: Uri) -> Response {
    ApiError::NotFound { path: uri.path().to_string() }.into_response()
}

async fn method_not_allowed() -> Response {
    ApiError::MethodNotAllowed.into_response()
}
