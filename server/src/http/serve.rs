//! Accepting and serving connections. hyper is driven directly (not through `axum::serve`) for
//! the limits `axum::serve` does not expose: a cap on open connections, in all and per client
//! address, a header-read timeout (hyper runs it from the moment a connection waits for a
//! request head, so it also closes idle keep-alive connections), a cap on the size of a request
//! head, a shutdown that waits for requests, not for connections, and the close of a connection
//! whose request body was left unread (`linger`).
//!
//! At the cap, a new connection is answered 503 and closed at once, except for a small reserve
//! (`PROBE_CONNECTIONS`) that serves the probes and metrics (`/healthz`, `/readyz`,
//! `/metrics`) one request per connection: whoever holds every connection, an orchestrator's
//! probes still get their answer. A client address at its own cap is answered 429 and closed.

use std::collections::HashMap;
use std::convert::Infallible;
use std::net::{IpAddr, SocketAddr};
use std::pin::{pin, Pin};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, Bytes, HttpBody};
use axum::extract::ConnectInfo;
use axum::http::header::CONNECTION;
use axum::http::{HeaderValue, Request, Response};
use axum::response::IntoResponse;
use axum::Router;
use hyper::body::Incoming;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{watch, OwnedSemaphorePermit, Semaphore};
use tokio::task::JoinSet;
use tower::ServiceExt;

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

/// File descriptors the process needs besides its connections: the listener, the runtime's
/// epoll, stdio, bundle files while loading, ONNX Runtime and blocking threads.
const RESERVED_FDS: u64 = 64;

/// Connections kept for the probes and metrics when every other one is taken.
pub const PROBE_CONNECTIONS: usize = 8;

/// The paths a connection of the probes' reserve serves.
const PROBE_PATHS: [&str; 3] = ["/healthz", "/readyz", "/metrics"];

/// How long a probe connection may take to send its request head.
const PROBE_HEADER_TIMEOUT: Duration = Duration::from_secs(5);

/// How long the answer to a refused connection may take to write.
const REFUSE_WRITE_TIME: Duration = Duration::from_secs(1);

/// How long a connection answered before its request body was read goes on reading (and
/// dropping) what the client still sends, after the answer and a FIN: closing a socket with
/// unread data sends a reset, which makes a client that writes its whole body before it reads
/// lose the answer. Bounded, so that the connection's slot comes back soon.
const LINGER: Duration = Duration::from_secs(2);

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
    let (slots, probe_slots) =
        (Arc::new(Semaphore::new(options.max_connections.max(1))), Arc::new(Semaphore::new(PROBE_CONNECTIONS)));
    let clients = PerAddress::new(options.max_connections_per_client);
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
        let Some(client) = clients.enter(peer.ip()) else {
            refuse(stream, too_many_connections(options.max_connections_per_client));
            continue;
        };
        let (permit, http, probes_only) =
            match (slots.clone().try_acquire_owned(), probe_slots.clone().try_acquire_owned()) {
                (Ok(permit), _) => (permit, http.clone(), false),
                (Err(_), Ok(permit)) => (permit, probe_http.clone(), true),
                (Err(_), Err(_)) => {
                    // Debug level: at the cap this comes once per connection, an attacker's pace.
                    tracing::debug!("connection limit reached");
                    refuse(stream, connection_limit());
                    continue;
                }
            };
        let connection =
            Connection { app: app.clone(), peer, phase: phase.clone(), requests: requests.clone(), probes_only };
        connections.spawn(connection.serve(http, stream, (permit, client)));
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

/// A connection the server cannot take: what the client already sent is read (so that closing
/// does not reset the answer away), `error`'s response (`error.rs`'s mapping, `connection:
/// close` added) written within `REFUSE_WRITE_TIME`, and the socket closed. Nothing waits for the
/// client's request.
fn refuse(mut stream: TcpStream, error: ApiError) {
    tokio::spawn(async move {
        let mut scratch = [0u8; 4096];
        let _ = stream.try_read(&mut scratch);
        let (parts, body) = error.into_response().into_parts();
        let Ok(body) = axum::body::to_bytes(body, 1 << 16).await else { return };
        let mut head = format!("HTTP/1.1 {}\r\nconnection: close\r\ncontent-length: {}\r\n", parts.status, body.len());
        for (name, value) in &parts.headers {
            if let Ok(value) = value.to_str() {
                head.push_str(&format!("{name}: {value}\r\n"));
            }
        }
        head.push_str("\r\n");
        let _ = tokio::time::timeout(REFUSE_WRITE_TIME, stream.write_all(&[head.as_bytes(), &body].concat())).await;
    });
}

fn too_many_connections(cap: usize) -> ApiError {
    ApiError::TooManyRequests {
        message: format!("this client already has {cap} connections open (--max-connections-per-client)"),
        retry_after_secs: 1,
    }
}

fn connection_limit() -> ApiError {
    ApiError::Unavailable { message: "server busy: every connection is taken".into(), retry_after_secs: 1 }
}

/// Counts per client address of something each may hold at most `cap` of (0: no cap): open
/// connections here, requests in flight in the middleware's slots.
#[derive(Clone)]
pub struct PerAddress {
    cap: usize,
    held: Arc<std::sync::Mutex<HashMap<IpAddr, usize>>>,
}

/// One held by an address; given back when dropped.
pub struct AddressGuard {
    ip: IpAddr,
    held: Arc<std::sync::Mutex<HashMap<IpAddr, usize>>>,
}

impl PerAddress {
    pub fn new(cap: usize) -> PerAddress {
        PerAddress { cap, held: Arc::default() }
    }

    pub fn cap(&self) -> usize {
        self.cap
    }

    /// One more for `ip`; `None` when it holds its cap already. With no cap, `Some` always (and
    /// nothing is counted).
    pub fn enter(&self, ip: IpAddr) -> Option<Option<AddressGuard>> {
        if self.cap == 0 {
            return Some(None);
        }
        let mut held = self.held.lock().unwrap_or_else(|p| p.into_inner());
        let count = held.entry(ip).or_default();
        if *count >= self.cap {
            return None;
        }
        *count += 1;
        Some(Some(AddressGuard { ip, held: self.held.clone() }))
    }
}

impl Drop for AddressGuard {
    fn drop(&mut self) {
        let mut held = self.held.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(count) = held.get_mut(&self.ip) {
            *count -= 1;
            if *count == 0 {
                held.remove(&self.ip);
            }
        }
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
    /// A connection of the probes' reserve: it serves `PROBE_PATHS` only.
    probes_only: bool,
}

/// What a connection holds while it is open: its slot, and its count in its address's.
type Held = (OwnedSemaphorePermit, Option<AddressGuard>);

impl Connection {
    async fn serve(self, http: Arc<http1::Builder>, stream: TcpStream, _held: Held) {
        let in_flight = InFlight { connection: Arc::default(), server: self.requests.clone() };
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
                if in_flight.connection.load(Ordering::SeqCst) > 0 {
                    let _ = std::future::poll_fn(|cx| conn.poll_without_shutdown(cx)).await;
                }
            }
        }
    }
}

/// The FIN after the answer, then what the client still sends read and dropped for up to
/// `LINGER` (see there).
async fn linger(mut stream: TcpStream) {
    let _ = stream.shutdown().await;
    let mut scratch = vec![0u8; 64 << 10];
    let drop_what_comes = async { while matches!(stream.read(&mut scratch).await, Ok(n) if n > 0) {} };
    let _ = tokio::time::timeout(LINGER, drop_what_comes).await;
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
    let needed = (max_connections + PROBE_CONNECTIONS) as u64 + RESERVED_FDS;
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
