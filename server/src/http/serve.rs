//! Accepting and serving connections. hyper is driven directly (not through `axum::serve`) for
//! the limits `axum::serve` does not expose: a cap on open connections, a header-read timeout
//! (hyper runs it from the moment a connection waits for a request head, so it also closes idle
//! keep-alive connections), a cap on the size of a request head, and a shutdown that waits for
//! requests, not for connections.

use std::convert::Infallible;
use std::net::SocketAddr;
use std::pin::{pin, Pin};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, Bytes, HttpBody};
use axum::extract::ConnectInfo;
use axum::http::{Request, Response};
use axum::response::IntoResponse;
use axum::Router;
use hyper::body::Incoming;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{watch, OwnedSemaphorePermit, Semaphore};
use tokio::task::JoinSet;
use tower::ServiceExt;

use crate::error::ApiError;

#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// Open connections at most; further clients wait in the listen backlog.
    pub max_connections: usize,
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

/// File descriptors the process needs besides its connections: the listener, the runtime's
/// epoll, stdio, bundle files while loading, ONNX Runtime and blocking threads.
const RESERVED_FDS: u64 = 64;

/// Serves `app` on `listener` until `shutdown` resolves, then stops accepting, closes connections
/// that have no request in progress, and waits up to the grace period for the others.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    options: &ServeOptions,
    shutdown: impl std::future::Future<Output = ()>,
) -> Stopped {
    let mut http = http1::Builder::new();
    http.timer(TokioTimer::new())
        .header_read_timeout(options.header_read_timeout)
        .max_header_size(options.max_header_bytes);
    let http = Arc::new(http);
    let (phase_tx, phase) = watch::channel(Phase::Serving);
    let slots = Arc::new(Semaphore::new(options.max_connections.max(1)));
    let requests = Arc::new(AtomicUsize::new(0));
    let mut connections = JoinSet::new();
    let mut shutdown = pin!(shutdown);
    loop {
        while connections.try_join_next().is_some() {}
        let Some(permit) = connection_slot(&slots, shutdown.as_mut()).await else { break };
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
        let connection = Connection { app: app.clone(), peer, phase: phase.clone(), requests: requests.clone() };
        connections.spawn(connection.serve(http.clone(), stream, permit));
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

/// A permit for one more connection; `None` once `shutdown` resolves first.
async fn connection_slot(
    slots: &Arc<Semaphore>,
    shutdown: Pin<&mut impl std::future::Future<Output = ()>>,
) -> Option<OwnedSemaphorePermit> {
    if let Ok(permit) = slots.clone().try_acquire_owned() {
        return Some(permit);
    }
    // Debug level: at the cap this comes once per connection accepted, an attacker's pace.
    tracing::debug!("connection limit reached; accepting again when one closes");
    tokio::select! {
        _ = shutdown => None,
        permit = slots.clone().acquire_owned() => permit.ok(),
    }
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
}

impl Connection {
    async fn serve(self, http: Arc<http1::Builder>, stream: TcpStream, _permit: OwnedSemaphorePermit) {
        let in_flight = InFlight { connection: Arc::default(), server: self.requests.clone() };
        let mut phase = self.phase.clone();
        let service = {
            let in_flight = in_flight.clone();
            hyper::service::service_fn(move |req: Request<Incoming>| {
                let (app, phase, guard) = (self.app.clone(), self.phase.clone(), in_flight.enter());
                handle(app, req, self.peer, phase, guard)
            })
        };
        let mut conn = pin!(http.serve_connection(TokioIo::new(stream), service));
        tokio::select! {
            _ = conn.as_mut() => return,
            _ = phase.wait_for(|p| *p != Phase::Serving) => {}
        }
        conn.as_mut().graceful_shutdown();
        // Idle, or its request head still incomplete: nothing to finish, close it now.
        if in_flight.connection.load(Ordering::SeqCst) > 0 {
            let _ = conn.await;
        }
    }
}

async fn handle(
    app: Router,
    mut req: Request<Incoming>,
    peer: SocketAddr,
    mut phase: watch::Receiver<Phase>,
    guard: InFlightGuard,
) -> Result<Response<Body>, Infallible> {
    req.extensions_mut().insert(ConnectInfo(peer));
    let response = tokio::select! {
        response = app.oneshot(req.map(Body::new)) => response.unwrap_or_else(|never| match never {}),
        Ok(_) = phase.wait_for(|p| *p == Phase::GraceOver) => {
            ApiError::Unavailable { message: "the server is shutting down".into(), retry_after_secs: 1 }.into_response()
        }
    };
    Ok(response.map(|body| Body::new(Tracked { body, _guard: guard })))
}

/// Requests in progress on one connection and on the server; a request counts from its head
/// until its response body is written (or dropped).
#[derive(Clone)]
struct InFlight {
    connection: Arc<AtomicUsize>,
    server: Arc<AtomicUsize>,
}

impl InFlight {
    fn enter(&self) -> InFlightGuard {
        self.connection.fetch_add(1, Ordering::SeqCst);
        self.server.fetch_add(1, Ordering::SeqCst);
        InFlightGuard(self.clone())
    }
}

struct InFlightGuard(InFlight);

impl Drop for InFlightGuard {
    fn drop(&mut self) {
        self.0.connection.fetch_sub(1, Ordering::SeqCst);
        self.0.server.fetch_sub(1, Ordering::SeqCst);
    }
}

/// A response body that keeps its request counted until hyper has written it.
struct Tracked {
    body: Body,
    _guard: InFlightGuard,
}

impl HttpBody for Tracked {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.body.size_hint()
    }
}

/// The connection cap must stay below the open-file limit: beyond it accept() fails with EMFILE
/// and nothing, not even /healthz, gets through. Raises the soft limit (up to the hard one)
/// when it is too low; refuses to start when even the hard limit is.
pub fn ensure_file_limit(max_connections: usize) -> Result<(), String> {
    let needed = max_connections as u64 + RESERVED_FDS;
    let mut limit = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
    // SAFETY: getrlimit writes into the struct we pass.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
        return Err(format!("cannot read the open-file limit: {}", std::io::Error::last_os_error()));
    }
    if limit.rlim_cur >= needed {
        return Ok(());
    }
    if limit.rlim_max < needed {
        return Err(format!(
            "--max-connections {max_connections} needs {needed} open files, but the limit is {} \
             (hard limit {}): lower --max-connections or raise the limit (ulimit -n)",
            limit.rlim_cur, limit.rlim_max
        ));
    }
    let raised = libc::rlimit { rlim_cur: needed, rlim_max: limit.rlim_max };
    // SAFETY: setrlimit reads the struct we pass.
    if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } != 0 {
        return Err(format!("cannot raise the open-file limit to {needed}: {}", std::io::Error::last_os_error()));
    }
    tracing::info!(from = limit.rlim_cur, to = needed, "raised the open-file limit for --max-connections");
    Ok(())
}
