//! HTTP API (axum): routes, shared state, health, model, metrics and OpenAPI endpoints.

pub mod body;
pub mod middleware;
pub mod negotiate;
pub mod openapi;
pub mod render;
pub mod scenes;
pub mod serve;
pub mod viewer;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::{DefaultBodyLimit, State};
use axum::http::{header, HeaderValue, Uri};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post};
use axum::{Json, Router};
use serde_json::json;
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::TraceLayer;

use crate::auth::Auth;
use crate::cache::{CacheConfig, SceneCache};
use crate::error::ApiError;
use crate::metrics::Metrics;
use crate::pipeline::Pipeline;

/// State shared by all handlers.
#[derive(Clone)]
pub struct AppState {
    pub pipeline: Pipeline,
    /// Set once the warm-up render succeeded; cleared again when shutting down.
    pub ready: Arc<AtomicBool>,
    pub request_timeout: Duration,
    pub scenes: Arc<SceneCache>,
    pub metrics: Arc<Metrics>,
    pub auth: Arc<Auth>,
    /// Slots for POST requests being handled at once (bodies in memory included).
    pub in_flight: Arc<middleware::Slots>,
    /// How slowly a request body may arrive.
    pub uploads: body::UploadPolicy,
}

/// Service settings besides the pipeline (from the command line, or set by tests).
#[derive(Debug, Clone)]
pub struct ServiceOptions {
    pub request_timeout: Duration,
    pub cache: CacheConfig,
    /// POST requests handled at once; beyond it 503 before the body is read.
    pub max_concurrent_requests: usize,
    /// POST requests handled at once from one peer address (0: no cap); beyond it 429.
    pub max_requests_per_client: usize,
    pub uploads: body::UploadPolicy,
    pub auth: Auth,
}

impl Default for ServiceOptions {
    fn default() -> Self {
        ServiceOptions {
            request_timeout: Duration::from_secs(900),
            cache: CacheConfig::default(),
            max_concurrent_requests: 256,
            max_requests_per_client: 32,
            uploads: body::UploadPolicy::default(),
            auth: Auth::disabled(),
        }
    }
}

impl AppState {
    /// Not ready until `set_ready` (after the warm-up render).
    pub fn new(pipeline: Pipeline, options: ServiceOptions) -> AppState {
        let scenes = Arc::new(SceneCache::new(options.cache));
        let metrics = Arc::new(Metrics::new(pipeline.backend.clone(), scenes.clone()));
        AppState {
            pipeline,
            ready: Arc::new(AtomicBool::new(false)),
            request_timeout: options.request_timeout,
            scenes,
            metrics,
            auth: Arc::new(options.auth),
            in_flight: Arc::new(middleware::Slots::new(
                options.max_concurrent_requests,
                options.max_requests_per_client,
            )),
            uploads: options.uploads,
        }
    }

    pub fn is_ready(&self) -> bool {
        self.ready.load(Ordering::Acquire)
    }

    pub fn set_ready(&self) {
        self.ready.store(true, Ordering::Release);
    }

    pub fn set_draining(&self) {
        self.ready.store(false, Ordering::Release);
    }

    fn check_ready(&self) -> Result<(), ApiError> {
        if self.is_ready() {
            Ok(())
        } else {
            Err(ApiError::Unavailable { message: "the model is warming up".into(), retry_after_secs: 5 })
        }
    }
}

/// The API with its layers. Outermost first, a request passes: request-id sanitising, request id
/// (set or kept, echoed in the response), tracing span, panic catcher, metrics, auth, the
/// in-flight limit, the body limit, the handler.
pub fn router(state: AppState) -> Router {
    let body_limit = state.pipeline.limits.max_body_bytes;
    Router::new()
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/openapi.json", get(openapi::serve))
        .route("/v1/model", get(model))
        .route("/v1/render", post(render::render))
        .route("/v1/scenes", post(scenes::create))
        .route("/v1/scenes/{id}", delete(scenes::delete))
        .route("/v1/scenes/{id}/render", post(scenes::render))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        // Multipart reads this limit; JSON and protobuf bodies are read with the same limit.
        .layer(DefaultBodyLimit::max(body_limit))
        .layer(axum::middleware::from_fn_with_state(state.clone(), middleware::limit_in_flight))
        .layer(axum::middleware::from_fn_with_state(state.clone(), crate::auth::require_token))
        .layer(axum::middleware::from_fn_with_state(state.clone(), middleware::record_metrics))
        .layer(CatchPanicLayer::custom(middleware::panic_response))
        .layer(TraceLayer::new_for_http().make_span_with(middleware::request_span))
        .layer(PropagateRequestIdLayer::x_request_id())
        .layer(SetRequestIdLayer::x_request_id(MakeRequestUuid))
        .layer(axum::middleware::from_fn(middleware::sanitize_request_id))
        .with_state(state)
}

/// Liveness: the process serves HTTP.
#[utoipa::path(get, path = "/healthz", tag = "service", operation_id = "healthz", responses((status = 200, description = "Alive")))]
async fn healthz() -> Json<serde_json::Value> {
    Json(json!({"status": "ok"}))
}

/// Readiness: bundle loaded and warm-up render done (503 while warming up or shutting down).
/// Public for orchestrators, so it names no model: `/v1/model` does, behind the token.
#[utoipa::path(get, path = "/readyz", tag = "service", operation_id = "readyz", responses(
    (status = 200, description = "Ready"),
    (status = 503, description = "Warming up or shutting down", body = crate::error::ErrorBody),
))]
async fn readyz(State(state): State<AppState>) -> Result<Json<serde_json::Value>, ApiError> {
    state.check_ready()?;
    Ok(Json(json!({"status": "ready"})))
}

/// Prometheus metrics (OpenMetrics text).
#[utoipa::path(get, path = "/metrics", tag = "service", operation_id = "metrics", responses(
    (status = 200, description = "Metrics", content_type = "application/openmetrics-text", body = String),
))]
async fn metrics(State(state): State<AppState>) -> Response {
    let mut response = state.metrics.render().into_response();
    response.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(crate::metrics::CONTENT_TYPE));
    response
}

/// The served model: id, variant, hyper-parameters and provenance from the manifest.
#[utoipa::path(get, path = "/v1/model", tag = "render", operation_id = "model", responses(
    (status = 200, description = "Model description", body = Object),
    (status = 401, description = "Missing or wrong bearer token", body = crate::error::ErrorBody),
), security((), ("bearer" = [])))]
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
    // The path is echoed in the message: keep a hostile one short.
    let path: String = uri.path().chars().take(200).collect();
    ApiError::NotFound { path }.into_response()
}

async fn method_not_allowed() -> Response {
    ApiError::MethodNotAllowed.into_response()
}
