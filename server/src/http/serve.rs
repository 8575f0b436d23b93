//! Accepting and serving connections. hyper is driven directly (not through `axum::serve`) for
//! the limits `axum::serve` does not expose: the connection policy of `connections` (caps on open
//! connections, in all and per client address, with a reserve for the probes; the close of a
//! connection whose request body was left unread), a header-read timeout (hyper runs it from the
//! moment a connection waits for a request head, so it also closes idle keep-alive connections),
//! a cap on the size of a request head, and a shutdown that waits for requests, not for
//! connections.

use std::convert::Infallible;
use std::net::SocketAddr;
use std::pin::{pin, Pin};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::ConnectInfo;
use axum::http::header::CONNECTION;
use axum::http::{HeaderValue, Request, Response};
use axum::response::IntoResponse;
use axum::Router;
use hyper::body::Incoming;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;
use tokio::task::JoinSet;
use tower::ServiceExt;

use super::connections::{
    connection_limit, counted_until_written, linger, refuse, Caps, Held, InFlight, InFlightGuard, PROBE_HEADER_TIMEOUT,
    PROBE_PATHS,
};
use crate::error::ApiError;

#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// Open connections at most (besides the probes' reserve); further ones get 503.
    pub max_connections: usize,
    /// Open connections from one client address at most (0: no cap); further ones get 429.
    pub max_connections_per_client: usize,
    /// A connection must deliver a complete request head within this time of opening, or of
    /// its previous response (idle keep-alive).
    pub header_read_timeout: Duration,
    /// Largest request head (request line and headers); beyond it hyper answers 431.
    pub max_header_bytes: usize,
    /// After the shutdown signal, requests in flight get this long to finish.
    pub shutdown_grace: Duration,
}

/// How serving ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stopped {
    /// Requests still running when the grace period ran out; they were answered 503.
    pub cut: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    Serving,
    /// Shutting down: no new connections; requests in flight finish.
    Draining,
    /// The grace period ran out: requests still running are answered 503.
    GraceOver,
}

/// How long the 503s sent when the grace period runs out get to reach their clients.
const CUT_WRITE_TIME: Duration = Duration::from_secs(2);

/// Serves `app` on `listener` until `shutdown` resolves, then stops accepting, closes connections
/// that have no request in progress, and waits up to the grace period for the others.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    options: &ServeOptions,
    shutdown: impl std::future::Future<Output = ()>,
) -> Stopped {
    let builder = |header_read_timeout: Duration, keep_alive: bool| {
        let mut http = http1::Builder::new();
        http.timer(TokioTimer::new())
            .header_read_timeout(header_read_timeout)
            .max_header_size(options.max_header_bytes)
            .keep_alive(keep_alive);
        Arc::new(http)
    };
    let http = builder(options.header_read_timeout, true);
    let probe_http = builder(options.header_read_timeout.min(PROBE_HEADER_TIMEOUT), false);
    let (phase_tx, phase) = watch::channel(Phase::Serving);
    let caps = Caps::new(options.max_connections, options.max_connections_per_client);
    let requests = Arc::new(AtomicUsize::new(0));
    let mut connections = JoinSet::new();
    let mut shutdown = pin!(shutdown);
    loop {
        while connections.try_join_next().is_some() {}
        let (stream, peer) = tokio::select! {
            _ = shutdown.as_mut() => break,
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    accept_failed(e).await;
                    continue;
                }
            },
        };
        let (held, probes_only) = match caps.admit(peer.ip()) {
            Ok(admitted) => admitted,
            Err(refusal) => {
                refuse(stream, refusal);
                continue;
            }
        };
        let http = if probes_only { probe_http.clone() } else { http.clone() };
        let connection =
            Connection { app: app.clone(), peer, phase: phase.clone(), requests: requests.clone(), probes_only };
        connections.spawn(connection.serve(http, stream, held));
    }
    drop(listener);
    tracing::info!(
        connections = connections.len(),
        requests = requests.load(Ordering::SeqCst),
        "no longer accepting; closing idle connections, finishing requests in flight"
    );
    phase_tx.send_replace(Phase::Draining);
    if tokio::time::timeout(options.shutdown_grace, join_all(&mut connections)).await.is_ok() {
        return Stopped { cut: 0 };
    }
    let cut = requests.load(Ordering::SeqCst);
    tracing::warn!(requests = cut, "grace period over: answering the requests still in flight with 503");
    phase_tx.send_replace(Phase::GraceOver);
    let _ = tokio::time::timeout(CUT_WRITE_TIME, join_all(&mut connections)).await;
    Stopped { cut }
}

/// Errors of one connection (reset before it was accepted) are routine; anything else (out of
/// file descriptors, memory) is logged and retried after a pause rather than in a busy loop.
async fn accept_failed(e: std::io::Error) {
    use std::io::ErrorKind::{ConnectionAborted, ConnectionRefused, ConnectionReset};
    if !matches!(e.kind(), ConnectionAborted | ConnectionRefused | ConnectionReset) {
        tracing::warn!(error = %e, "accept failed");
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

async fn join_all(set: &mut JoinSet<()>) {
    while set.join_next().await.is_some() {}
}

/// One accepted connection and what its requests need.
struct Connection {
    app: Router,
    peer: SocketAddr,
    phase: watch::Receiver<Phase>,
    /// Requests in progress on the whole server.
    requests: Arc<AtomicUsize>,
    /// A connection of the probes' reserve: it serves `PROBE_PATHS` only.
    probes_only: bool,
}

impl Connection {
    async fn serve(self, http: Arc<http1::Builder>, stream: TcpStream, _held: Held) {
        let in_flight = InFlight::new(self.requests.clone());
        let unread_body = Arc::new(AtomicBool::new(false));
        let mut phase = self.phase.clone();
        let service = {
            let (in_flight, unread_body) = (in_flight.clone(), unread_body.clone());
            hyper::service::service_fn(move |req: Request<Incoming>| {
                let (app, phase, guard) = (self.app.clone(), self.phase.clone(), in_flight.enter());
                let request =
                    Served { peer: self.peer, probes_only: self.probes_only, unread_body: unread_body.clone() };
                Box::pin(handle(app, req, request, phase, guard))
            })
        };
        let mut conn = http.serve_connection(TokioIo::new(stream), service);
        let finished = tokio::select! {
            done = std::future::poll_fn(|cx| conn.poll_without_shutdown(cx)) => Some(done.is_ok()),
            _ = phase.wait_for(|p| *p != Phase::Serving) => None,
        };
        match finished {
            Some(true) if unread_body.load(Ordering::SeqCst) => linger(conn.into_parts().io.into_inner()).await,
            Some(_) => {}
            None => {
                Pin::new(&mut conn).graceful_shutdown();
                // Idle, or its request head still incomplete: nothing to finish, close it now.
                if in_flight.on_connection() > 0 {
                    let _ = std::future::poll_fn(|cx| conn.poll_without_shutdown(cx)).await;
                }
            }
        }
    }
}

/// What `handle` needs to know about the connection of a request.
struct Served {
    peer: SocketAddr,
    probes_only: bool,
    /// Set when an answer leaves the request's body unread (`connection: close`).
    unread_body: Arc<AtomicBool>,
}

async fn handle(
    app: Router,
    mut req: Request<Incoming>,
    served: Served,
    mut phase: watch::Receiver<Phase>,
    guard: InFlightGuard,
) -> Result<Response<Body>, Infallible> {
    req.extensions_mut().insert(ConnectInfo(served.peer));
    let response = if served.probes_only && !PROBE_PATHS.contains(&req.uri().path()) {
        let mut refused = connection_limit().into_response();
        refused.headers_mut().insert(CONNECTION, HeaderValue::from_static("close"));
        refused
    } else {
        tokio::select! {
            response = app.oneshot(req.map(Body::new)) => response.unwrap_or_else(|never| match never {}),
            Ok(_) = phase.wait_for(|p| *p == Phase::GraceOver) => {
                ApiError::Unavailable { message: "the server is shutting down".into(), retry_after_secs: 1 }.into_response()
            }
        }
    };
    if response.headers().get(CONNECTION).is_some_and(|v| v.as_bytes().eq_ignore_ascii_case(b"close")) {
        served.unread_body.store(true, Ordering::SeqCst);
    }
    Ok(response.map(|body| counted_until_written(body, guard)))
}
