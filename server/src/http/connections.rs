//! The connection policy `serve` applies: how many connections the server holds (in all, per
//! client address, a reserve for the probes) and the file descriptors they need, how a connection
//! the server cannot take is refused, how one answered before its body was read is let go
//! (`linger`), and the count of requests in flight that shutdown waits on.
//!
//! At the cap, a new connection is answered 503 and closed at once, except for a small reserve
//! (`PROBE_CONNECTIONS`) that serves the probes and metrics (`/healthz`, `/readyz`,
//! `/metrics`) one request per connection: whoever holds every connection, an orchestrator's
//! probes still get their answer. A client address at its own cap is answered 429 and closed.

use std::collections::HashMap;
use std::net::IpAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, Bytes, HttpBody};
use axum::response::IntoResponse;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use crate::error::ApiError;

/// File descriptors the process needs besides its connections: the listener, the runtime's
/// epoll, stdio, bundle files while loading, ONNX Runtime and blocking threads.
const RESERVED_FDS: u64 = 64;

/// Connections kept for the probes and metrics when every other one is taken.
pub const PROBE_CONNECTIONS: usize = 8;

/// The paths a connection of the probes' reserve serves.
pub(super) const PROBE_PATHS: [&str; 3] = ["/healthz", "/readyz", "/metrics"];

/// How long a probe connection may take to send its request head.
pub(super) const PROBE_HEADER_TIMEOUT: Duration = Duration::from_secs(5);

/// How long the answer to a refused connection may take to write.
const REFUSE_WRITE_TIME: Duration = Duration::from_secs(1);

/// How long a connection answered before its request body was read goes on reading (and
/// dropping) what the client still sends, after the answer and a FIN: closing a socket with
/// unread data sends a reset, which makes a client that writes its whole body before it reads
/// lose the answer. Bounded, so that the connection's slot comes back soon.
const LINGER: Duration = Duration::from_secs(2);

/// A connection the server cannot take: what the client already sent is read (so that closing
/// does not reset the answer away), `error`'s response (`error.rs`'s mapping, `connection:
/// close` added) written within `REFUSE_WRITE_TIME`, and the socket closed. Nothing waits for the
/// client's request.
pub(super) fn refuse(mut stream: TcpStream, error: ApiError) {
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

pub(super) fn connection_limit() -> ApiError {
    ApiError::Unavailable { message: "server busy: every connection is taken".into(), retry_after_secs: 1 }
}

/// The open connections the server holds: in all, per client address, and the probes' reserve.
pub(super) struct Caps {
    slots: Arc<Semaphore>,
    probe_slots: Arc<Semaphore>,
    clients: PerAddress,
}

/// What a connection holds while it is open: its slot, and its count in its address's.
pub(super) type Held = (OwnedSemaphorePermit, Option<AddressGuard>);

impl Caps {
    pub(super) fn new(max_connections: usize, max_connections_per_client: usize) -> Caps {
        Caps {
            slots: Arc::new(Semaphore::new(max_connections.max(1))),
            probe_slots: Arc::new(Semaphore::new(PROBE_CONNECTIONS)),
            clients: PerAddress::new(max_connections_per_client),
        }
    }

    /// What a connection from `ip` holds while it is open, and whether it is one of the probes'
    /// reserve; or the refusal to answer it with.
    pub(super) fn admit(&self, ip: IpAddr) -> Result<(Held, bool), ApiError> {
        let Some(client) = self.clients.enter(ip) else {
            return Err(too_many_connections(self.clients.cap()));
        };
        match (self.slots.clone().try_acquire_owned(), self.probe_slots.clone().try_acquire_owned()) {
            (Ok(permit), _) => Ok(((permit, client), false)),
            (Err(_), Ok(permit)) => Ok(((permit, client), true)),
            (Err(_), Err(_)) => {
                // Debug level: at the cap this comes once per connection, an attacker's pace.
                tracing::debug!("connection limit reached");
                Err(connection_limit())
            }
        }
    }
}

/// Counts per client address of something each may hold at most `cap` of (0: no cap): open
/// connections (`serve`), requests in flight in the middleware's slots.
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

/// The FIN after the answer, then what the client still sends read and dropped for up to
/// `LINGER` (see there).
pub(super) async fn linger(mut stream: TcpStream) {
    let _ = stream.shutdown().await;
    let mut scratch = vec![0u8; 64 << 10];
    let drop_what_comes = async { while matches!(stream.read(&mut scratch).await, Ok(n) if n > 0) {} };
    let _ = tokio::time::timeout(LINGER, drop_what_comes).await;
}

/// Requests in progress on one connection and on the server; a request counts from its head
/// until its response body is written (or dropped).
#[derive(Clone)]
pub(super) struct InFlight {
    connection: Arc<AtomicUsize>,
    server: Arc<AtomicUsize>,
}

impl InFlight {
    /// A new connection's count, on the server's `server`.
    pub(super) fn new(server: Arc<AtomicUsize>) -> InFlight {
        InFlight { connection: Arc::default(), server }
    }

    pub(super) fn on_connection(&self) -> usize {
        self.connection.load(Ordering::SeqCst)
    }

    pub(super) fn enter(&self) -> InFlightGuard {
        self.connection.fetch_add(1, Ordering::SeqCst);
        self.server.fetch_add(1, Ordering::SeqCst);
        InFlightGuard(self.clone())
    }
}

pub(super) struct InFlightGuard(InFlight);

impl Drop for InFlightGuard {
    fn drop(&mut self) {
        self.0.connection.fetch_sub(1, Ordering::SeqCst);
        self.0.server.fetch_sub(1, Ordering::SeqCst);
    }
}

/// `body`, its request counted until hyper has written it.
pub(super) fn counted_until_written(body: Body, guard: InFlightGuard) -> Body {
    Body::new(Tracked { body, _guard: guard })
}

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
