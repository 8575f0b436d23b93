//! Cross-cutting layers: request ids, tracing spans, panics, metrics and the in-flight limit.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use axum::extract::{ConnectInfo, MatchedPath, Request, State};
use axum::http::{HeaderValue, Method};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::body::{body_limit, drain, keep_rest, refuse_declared_length};
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

/// Bounds the requests with a body (POST, PUT) handled at once, in all and per client (their
/// bodies are held in memory while they wait for the executor), and holds each upload to the
/// minimum rate. A body declared larger than the route's limit is refused at once: 413 before
/// anything is read. A request refused before its body was read to the end has the rest read
/// (up to the limit, at the upload rate) before the answer goes out, so that a client still
/// sending receives the answer (see `body::keep_rest`).
pub async fn limit_in_flight(State(state): State<AppState>, req: Request, next: Next) -> Response {
    if req.method() != Method::POST && req.method() != Method::PUT {
        return next.run(req).await;
    }
    let limit = body_limit(state.pipeline.limits(), req.uri().path());
    if let Err(e) = refuse_declared_length(req.body(), limit) {
        return e.into_response();
    }
    let client = req.extensions().get::<ConnectInfo<SocketAddr>>().map(|c| c.0.ip());
    let _slot = match state.in_flight.acquire(client) {
        Ok(slot) => slot,
        Err(e) => return e.into_response(),
    };
    let policy = state.uploads;
    let (parts, body) = req.into_parts();
    let (body, mut rest) = keep_rest(policy.apply(body));
    let response = next.run(Request::from_parts(parts, body)).await;
    if !response.status().is_success() {
        if let Ok(rest) = rest.try_recv() {
            drain(rest, limit).await;
        }
    }
    response
}

/// Slots for requests being handled: `total` in all, `per_client` (0: any) per peer address.
pub struct Slots {
    total: Arc<Semaphore>,
    per_client: usize,
    clients: Arc<Mutex<HashMap<IpAddr, usize>>>,
}

/// A taken slot, given back when dropped.
pub struct Slot {
    _total: OwnedSemaphorePermit,
    _client: Option<ClientSlot>,
}

struct ClientSlot {
    ip: IpAddr,
    clients: Arc<Mutex<HashMap<IpAddr, usize>>>,
}

impl Drop for ClientSlot {
    fn drop(&mut self) {
        let mut clients = self.clients.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(held) = clients.get_mut(&self.ip) {
            *held -= 1;
            if *held == 0 {
                clients.remove(&self.ip);
            }
        }
    }
}

impl Slots {
    pub fn new(total: usize, per_client: usize) -> Slots {
        Slots { total: Arc::new(Semaphore::new(total.max(1))), per_client, clients: Arc::default() }
    }

    /// `client`: the peer address (`None` in-process, where there is no peer to tell apart).
    /// The client's own cap is checked first, so that the client holding many slots is the one
    /// told (429), not the others (503).
    pub fn acquire(&self, client: Option<IpAddr>) -> Result<Slot, ApiError> {
        let client = match client.filter(|_| self.per_client > 0) {
            Some(ip) => Some(self.client_slot(ip)?),
            None => None,
        };
        let total = self.total.clone().try_acquire_owned().map_err(|_| ApiError::Unavailable {
            message: "server busy: too many requests in flight".into(),
            retry_after_secs: 1,
        })?;
        Ok(Slot { _total: total, _client: client })
    }

    fn client_slot(&self, ip: IpAddr) -> Result<ClientSlot, ApiError> {
        let mut clients = self.clients.lock().unwrap_or_else(|p| p.into_inner());
        let held = clients.entry(ip).or_default();
        if *held >= self.per_client {
            return Err(ApiError::TooManyRequests {
                message: format!("this client already has {} requests in flight", self.per_client),
                retry_after_secs: 1,
            });
        }
        *held += 1;
        Ok(ClientSlot { ip, clients: self.clients.clone() })
    }
}
