//! HTTP API (axum): the router, its layers and its handlers, one module per endpoint family.
//! Handlers read a body (`body`, `negotiate`), validate it (`crate::request`), run the pipeline
//! and answer through `respond`; the schema of everything they read and write is served by
//! `openapi`.

pub mod body;
mod capture_plan;
mod captures;
pub mod connections;
mod deadline;
pub mod middleware;
mod models;
pub mod negotiate;
pub mod openapi;
mod origin;
mod render;
mod respond;
mod scenes;
mod schema;
pub mod serve;
mod service;
mod slots;
mod state;
pub mod viewer;

use axum::extract::DefaultBodyLimit;
use axum::routing::{get, post};
use axum::Router;
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::TraceLayer;

pub use state::{AppState, ServiceOptions};

/// The API with its layers. Outermost first, a request passes: request-id sanitising, request id
/// (set or kept, echoed in the response), tracing span, the response's log line (at a level
/// by status: `middleware::response_level`), panic catcher, metrics, the origin policy (which
/// sites may change state: `origin`), auth, the in-flight limit, the body limit, the handler.
pub fn router(state: AppState) -> Router {
    let body_limit = state.pipeline().limits().max_body_bytes;
    let capture_limit = state.pipeline().limits().max_capture_bytes;
    Router::new()
        .route("/healthz", get(service::healthz))
        .route(service::READINESS_PATH, get(service::readyz))
        .route("/metrics", get(service::metrics))
        .route("/openapi.json", get(openapi::serve))
        .route("/v1/model", get(service::model))
        .route("/v1/limits", get(service::limits))
        .route("/v1/models", get(models::list))
        .route("/v1/models/reload", post(models::reload))
        .route("/v1/render", post(render::render))
        .route("/v1/scenes", post(scenes::create))
        .route(body::CAPTURES_PATH, post(captures::create).layer(DefaultBodyLimit::max(capture_limit)))
        .route(body::CAPTURE_PLAN_PATH, post(capture_plan::plan_capture))
        .route("/v1/scenes/{id}", axum::routing::put(scenes::put).delete(scenes::delete))
        .route("/v1/scenes/{id}/render", post(scenes::render))
        .fallback(service::not_found)
        .method_not_allowed_fallback(service::method_not_allowed)
        // Multipart reads this limit (the captures route its own); JSON and protobuf bodies are
        // read with the same limit.
        .layer(DefaultBodyLimit::max(body_limit))
        .layer(axum::middleware::from_fn_with_state(state.clone(), middleware::limit_in_flight))
        .layer(axum::middleware::from_fn_with_state(state.auth.clone(), crate::auth::require_token))
        .layer(axum::middleware::from_fn_with_state(state.origins.clone(), origin::check_origin))
        .layer(axum::middleware::from_fn_with_state(state.clone(), middleware::record_metrics))
        .layer(CatchPanicLayer::custom(middleware::panic_response))
        .layer(axum::middleware::from_fn(middleware::log_response))
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(middleware::request_span)
                .on_response(())
                .on_failure(middleware::log_stream_failure),
        )
        .layer(PropagateRequestIdLayer::x_request_id())
        .layer(SetRequestIdLayer::x_request_id(MakeRequestUuid))
        .layer(axum::middleware::from_fn(middleware::sanitize_request_id))
        .with_state(state)
}
