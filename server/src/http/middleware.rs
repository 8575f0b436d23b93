//! Cross-cutting layers: request ids, tracing spans, the log line of each response, panics,
//! metrics and the in-flight limit.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use axum::body::HttpBody;
use axum::extract::{ConnectInfo, MatchedPath, Request, State};
use axum::http::{header, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use tower_http::classify::ServerErrorsFailureClass;
use tracing::Level;

use super::body::{body_limit, refuse_declared_length, BodyUse};
use super::service::READINESS_PATH;
use super::state::AppState;
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

/// The log line of every response, in its request's span, at [`response_level`].
pub async fn log_response(req: Request, next: Next) -> Response {
    let path = req.uri().path().to_owned();
    let started = Instant::now();
    let response = next.run(req).await;
    let status = response.status().as_u16();
    let latency_ms = started.elapsed().as_millis() as u64;
    match response_level(&path, response.status()) {
        Level::ERROR => tracing::error!(status, latency_ms, "response"),
        Level::WARN => tracing::warn!(status, latency_ms, "response"),
        Level::INFO => tracing::info!(status, latency_ms, "response"),
        _ => tracing::debug!(status, latency_ms, "response"),
    }
    response
}

/// How loud a response is in the logs. Only failures of the server are errors. Refusals are the
/// API working as documented, and clients and orchestrators cause them in bulk (a readiness probe
/// polling a warming server, a client asking for a scene this replica no longer holds, a flood of
/// bad requests): at ERROR they would bury the real failures, so they stay at DEBUG, counted by
/// status in `/metrics`. A 503 or 504 of the API means the server is out of capacity or time: a
/// warning for the operator, not a failure.
pub fn response_level(path: &str, status: StatusCode) -> Level {
    match status {
        StatusCode::SERVICE_UNAVAILABLE if path == READINESS_PATH => Level::DEBUG,
        StatusCode::SERVICE_UNAVAILABLE | StatusCode::GATEWAY_TIMEOUT => Level::WARN,
        s if s.is_server_error() => Level::ERROR,
        _ => Level::DEBUG,
    }
}

/// The trace layer's failures other than a status: a response body that broke while streaming.
/// Responses with a 5xx status are [`log_response`]'s, at their [`response_level`].
pub fn log_stream_failure(failure: ServerErrorsFailureClass, latency: Duration, _span: &tracing::Span) {
    if let ServerErrorsFailureClass::Error(error) = failure {
        tracing::error!(error = %error, latency_ms = latency.as_millis() as u64, "response failed");
    }
}

/// A panicking handler answers 500 with the usual JSON error instead of dropping the connection;
/// the panic's message is logged (a bug of ours: it must be found), not sent.
pub fn panic_response(panic: Box<dyn std::any::Any + Send + 'static>) -> Response {
    let message = panic
        .downcast_ref::<String>()
        .map(String::as_str)
        .or_else(|| panic.downcast_ref::<&str>().copied())
        .unwrap_or("(not a string)");
    tracing::error!(panic = message, "the request handler panicked");
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

/// Bounds the requests with a body (POST, PUT) handled at once, in all and per client, holds
/// each upload to the minimum rate, and holds its bytes against the memory budget as they
/// arrive (`body::BodyUse`: 503 when the budget is full). A body declared larger than the
/// route's limit is refused at once: 413 before anything is read.
///
/// A request answered before its body was read to the end (refused, past its deadline, or a
/// client that sends more than it said) is answered at once with `connection: close`, and the
/// rest of its body is not read: the slot and the memory are freed with the answer. The
/// connection then closes the way `serve` closes one with unread data (see `connections::linger`).
pub async fn limit_in_flight(State(state): State<AppState>, req: Request, next: Next) -> Response {
    if req.method() != Method::POST && req.method() != Method::PUT {
        return next.run(req).await;
    }
    let unread = !req.body().is_end_stream();
    let refuse = |e: ApiError| close_unless(!unread, e.into_response());
    let limit = body_limit(state.pipeline().limits(), req.uri().path());
    if let Err(e) = refuse_declared_length(req.body(), limit) {
        return refuse(e);
    }
    let client = req.extensions().get::<ConnectInfo<SocketAddr>>().map(|c| c.0.ip());
    let _slot = match state.in_flight.acquire(client) {
        Ok(slot) => slot,
        Err(e) => return refuse(e),
    };
    let lease = match state.pipeline().executor().lease(0) {
        Ok(lease) => lease,
        Err(e) => return refuse(e.into()),
    };
    let (parts, body) = req.into_parts();
    let (body, used) = BodyUse::track(state.uploads.apply(body), lease);
    let response = next.run(Request::from_parts(parts, body)).await;
    close_unless(used.ended(), response)
}

/// `response` with `connection: close` unless `read`: the request's body was read to its end.
fn close_unless(read: bool, mut response: Response) -> Response {
    if !read {
        response.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    fn level(path: &str, status: u16) -> Level {
        response_level(path, StatusCode::from_u16(status).unwrap())
    }

    #[test]
    fn a_warming_server_answering_its_readiness_probe_is_not_an_error() {
        assert_eq!(level("/readyz", 503), Level::DEBUG);
        assert_eq!(level("/readyz", 200), Level::DEBUG);
        assert_eq!(level("/healthz", 200), Level::DEBUG);
    }

    #[test]
    fn client_errors_are_debug() {
        for status in [400, 401, 404, 405, 408, 413, 415, 422, 429, 431] {
            assert_eq!(level("/v1/scenes/abc/render", status), Level::DEBUG, "{status}");
        }
        assert_eq!(level("/no/such/route", 404), Level::DEBUG);
    }

    #[test]
    fn an_api_out_of_capacity_or_time_is_a_warning() {
        assert_eq!(level("/v1/render", 503), Level::WARN);
        assert_eq!(level("/v1/scenes", 503), Level::WARN);
        assert_eq!(level("/v1/scenes/abc/render", 504), Level::WARN);
    }

    #[test]
    fn failures_of_the_server_are_errors() {
        assert_eq!(level("/v1/render", 500), Level::ERROR);
        assert_eq!(level("/v1/scenes/abc/render", 502), Level::ERROR);
        assert_eq!(level("/readyz", 500), Level::ERROR);
        assert_eq!(level("/metrics", 500), Level::ERROR);
    }
}
