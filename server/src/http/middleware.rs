//! Cross-cutting layers: request ids, tracing spans, panics, metrics and the in-flight limit.

use std::time::Instant;

use axum::extract::{MatchedPath, Request, State};
use axum::http::{HeaderValue, Method};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::AppState;
use crate::error::ApiError;

const REQUEST_ID: &str = "x-request-id";

/// A client may choose its request id (to correlate logs), but it is echoed and logged, so only
/// short ids of harmless characters are kept; anything else is replaced by a fresh UUID.
pub async fn sanitize_request_id(mut req: Request, next: Next) -> Response {
    let acceptable = |v: &HeaderValue| {
        let b = v.as_bytes();
        !b.is_empty() && b.len() <= 64 && b.iter().all(|c| c.is_ascii_alphanumeric() || b"-_.:".contains(c))
    };
    if req.headers().get(REQUEST_ID).is_some_and(|v| !acceptable(v)) {
        req.headers_mut().remove(REQUEST_ID);
    }
    next.run(req).await
}

/// The span every log line of a request carries: method, path and request id. Headers (the
/// bearer token) and bodies (images) are never recorded.
pub fn request_span(req: &Request) -> tracing::Span {
    let id = req.headers().get(REQUEST_ID).and_then(|v| v.to_str().ok()).unwrap_or("-");
    tracing::info_span!("request", method = %req.method(), path = %req.uri().path(), request_id = %id)
}

/// A panicking handler answers 500 with the usual JSON error instead of dropping the connection.
pub fn panic_response(_panic: Box<dyn std::any::Any + Send + 'static>) -> Response {
    ApiError::Internal("the request handler panicked".into()).into_response()
}

/// Counts requests by route template, method and status, and times them.
pub async fn record_metrics(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let started = Instant::now();
    let route = req.extensions().get::<MatchedPath>().map_or("unmatched", |p| p.as_str()).to_string();
    let method = req.method().clone();
    let response = next.run(req).await;
    state.metrics.observe_request(&route, method.as_str(), response.status().as_u16(), started.elapsed());
    response
}

/// Bounds the POST requests handled at once (their bodies are held in memory while they wait
/// for the executor): beyond it, 503 before the body is read.
pub async fn limit_in_flight(State(state): State<AppState>, req: Request, next: Next) -> Response {
    if req.method() != Method::POST {
        return next.run(req).await;
    }
    let Ok(_permit) = state.in_flight.clone().try_acquire_owned() else {
        return ApiError::Unavailable {
            message: "server busy: too many requests in flight".into(),
            retry_after_secs: 1,
        }
        .into_response();
    };
    next.run(req).await
}
