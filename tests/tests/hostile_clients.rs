//! Hostile clients against the real binary over real sockets: trickling and stalled uploads,
//! declared lengths over the limit, abandoned uploads, partial headers, idle keep-alive
//! connections, oversized headers, the connection caps (in all, per address, the probes'
//! reserve), refused and expired requests answered without their bodies, bodies held against
//! the memory budget, and a shutdown with idle connections. loadtest/attacks.sh runs the probe's
//! attacks at their own sizes.
//! Settings go through the environment (`SCNERF_*`), so each test also runs against a build
//! that predates them (`SCNERF_SERVER_BIN`), where it fails.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::mpsc::{channel, Sender};
use std::time::{Duration, Instant};

use scnerf_e2e::{http_request, memory_kib, repo_root, server_binary, ServerProcess};

fn start(env: &[(&str, &str)]) -> ServerProcess {
    let bundle = repo_root().join("tests/fixtures/parity/bundle");
    let args = ["--bundle", bundle.to_str().unwrap(), "--skip-warmup"];
    let mut server = ServerProcess::start_with_env(&server_binary(), &args, env);
    server.wait_ready(Duration::from_secs(120));
    server
}

/// A connection from `ip` (any 127.x.y.z is this machine): how a test plays several clients.
fn connect_from(ip: &str, server: SocketAddr) -> TcpStream {
    let runtime = tokio::runtime::Builder::new_current_thread().enable_io().build().unwrap();
    let stream = runtime.block_on(async {
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.bind(format!("{ip}:0").parse().unwrap()).unwrap();
        socket.connect(server).await.unwrap()
    });
    let stream = stream.into_std().unwrap();
    stream.set_nonblocking(false).unwrap();
    stream
}

fn post_head(path: &str, content_type: &str, length: u64) -> String {
    format!("POST {path} HTTP/1.1\r\nHost: test\r\nContent-Type: {content_type}\r\nContent-Length: {length}\r\n\r\n")
}

/// The status of the response on `stream`, if one arrives within `timeout`.
fn status_within(stream: &mut TcpStream, timeout: Duration) -> Option<u16> {
    stream.set_read_timeout(Some(timeout)).unwrap();
    let mut buf = [0u8; 4096];
    let n = stream.read(&mut buf).ok()?;
    let head = String::from_utf8_lossy(&buf[..n]);
    head.split_whitespace().nth(1)?.parse().ok()
}

/// Whether the server closes `stream` within `timeout` (reading what it sends first).
fn closed_within(stream: &mut TcpStream, timeout: Duration) -> bool {
    let start = Instant::now();
    let mut buf = [0u8; 4096];
    while start.elapsed() < timeout {
        stream.set_read_timeout(Some(timeout.saturating_sub(start.elapsed()).max(Duration::from_millis(1)))).unwrap();
        match stream.read(&mut buf) {
            Ok(0) => return true,
            Ok(_) => continue,
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => return true,
            Err(_) => return false,
        }
    }
    false
}

/// Sends the head of a 10 kB upload, then 2 bytes every 200 ms, until an answer comes (its
/// status and when) or 10 s pass (`None`); the outcome goes to `done`.
fn trickle(from: &'static str, server: SocketAddr, done: Sender<Option<(u16, Duration)>>) {
    std::thread::spawn(move || {
        let outcome = (|| {
            let mut stream = connect_from(from, server);
            let start = Instant::now();
            stream.write_all(post_head("/v1/render", "application/json", 10_000).as_bytes()).ok()?;
            while start.elapsed() < Duration::from_secs(10) {
                if let Some(status) = status_within(&mut stream, Duration::from_millis(200)) {
                    return Some((status, start.elapsed()));
                }
                stream.write_all(b"  ").ok()?;
            }
            None
        })();
        let _ = done.send(outcome);
    });
}

#[test]
fn trickling_uploads_get_408_and_one_client_cannot_hold_every_post_slot() {
    let server = start(&[
        ("SCNERF_MAX_CONCURRENT_REQUESTS", "4"),
        ("SCNERF_MAX_REQUESTS_PER_CLIENT", "2"),
        ("SCNERF_BODY_TIMEOUT_SECS", "1"),
        ("SCNERF_MIN_BODY_BYTES_PER_SEC", "1000"),
    ]);
    let (done, outcomes) = channel();
    for _ in 0..4 {
        trickle("127.0.0.2", server.addr, done.clone());
    }
    // The client's cap is 2: two of its uploads are refused at once, which means the other two
    // hold their slots from then on.
    let refused: Vec<_> = (0..2).map(|_| outcomes.recv_timeout(Duration::from_secs(10)).unwrap()).collect();
    assert!(refused.iter().all(|r| matches!(r, Some((429, _)))), "{refused:?}");
    // Another client still gets a slot: its POST reaches the handler (400: `{}` is no view).
    let path = "/v1/scenes/0123456789abcdef0123456789abcdef/render";
    let other = http_request(
        server.addr,
        "POST",
        path,
        &[("content-type", "application/json")],
        b"{}",
        Duration::from_secs(10),
    )
    .unwrap();
    assert_eq!(other.status, 400, "{}", String::from_utf8_lossy(&other.body));
    let held: Vec<_> = (0..2).map(|_| outcomes.recv_timeout(Duration::from_secs(20)).unwrap()).collect();
    assert!(held.iter().all(|r| matches!(r, Some((408, _)))), "{held:?}");
    // 1 s at any rate, then 1000 bytes/s: the few bytes sent buy almost nothing more.
    assert!(held.iter().flatten().all(|(_, t)| *t < Duration::from_secs(4)), "{held:?}");
}

#[test]
fn a_declared_length_over_the_limit_is_413_before_any_byte_is_read() {
    let server = start(&[]);
    let mut stream = TcpStream::connect(server.addr).unwrap();
    stream.write_all(post_head("/v1/render", "application/x-protobuf", 1_000_000_000_000).as_bytes()).unwrap();
    assert_eq!(status_within(&mut stream, Duration::from_secs(5)), Some(413));
}

#[test]
fn abandoned_uploads_give_their_memory_back() {
    let server = start(&[("SCNERF_MAX_REQUESTS_PER_CLIENT", "0")]);
    let pid = server.child.id();
    let rss_mib = || memory_kib(pid).expect("/proc").1 / 1024;
    let baseline = rss_mib();
    let (uploads, sent_mib) = (8, 48);
    let clients: Vec<_> = (0..uploads)
        .map(|_| {
            let addr = server.addr;
            std::thread::spawn(move || {
                let mut stream = TcpStream::connect(addr).unwrap();
                stream.write_all(post_head("/v1/render", "application/json", 60 << 20).as_bytes()).unwrap();
                stream.write_all(&vec![b' '; sent_mib << 20]).unwrap();
                stream // stalls here, then is dropped: the client went away mid-upload
            })
        })
        .collect();
    let streams: Vec<_> = clients.into_iter().map(|c| c.join().unwrap()).collect();
    let held = baseline + (uploads * sent_mib / 2) as u64;
    let holding = poll_until(rss_mib, |rss| *rss > held, Duration::from_secs(30));
    drop(streams);
    let after = poll_until(rss_mib, |rss| *rss <= baseline + 64, Duration::from_secs(5));
    eprintln!("RSS MiB: {baseline} before, {holding} holding {uploads} x {sent_mib} MiB, {after} after they left");
    assert!(holding > held, "the uploads were not held: {holding} MiB");
    assert!(after <= baseline + 64, "RSS stayed at {after} MiB after the uploads were abandoned ({baseline} before)");
}

#[test]
fn partial_headers_and_idle_keep_alive_connections_are_closed() {
    let server = start(&[("SCNERF_HEADER_READ_TIMEOUT_SECS", "1")]);
    let mut partial = TcpStream::connect(server.addr).unwrap();
    partial.write_all(b"GET /healthz HTTP/1.1\r\nHost: test\r\n").unwrap();
    let mut idle = TcpStream::connect(server.addr).unwrap();
    idle.write_all(b"GET /healthz HTTP/1.1\r\nHost: test\r\n\r\n").unwrap();
    assert_eq!(status_within(&mut idle, Duration::from_secs(5)), Some(200));
    assert!(closed_within(&mut partial, Duration::from_secs(5)), "a partial request head kept its connection");
    assert!(closed_within(&mut idle, Duration::from_secs(5)), "an idle keep-alive connection stayed open");
}

#[test]
fn an_oversized_request_head_is_431() {
    let server = start(&[("SCNERF_MAX_HEADER_BYTES", "16384")]);
    let mut stream = TcpStream::connect(server.addr).unwrap();
    let big = "a".repeat(200 << 10);
    stream.write_all(format!("GET /healthz HTTP/1.1\r\nHost: test\r\nx-padding: {big}\r\n\r\n").as_bytes()).unwrap();
    assert_eq!(status_within(&mut stream, Duration::from_secs(5)), Some(431));
}

#[test]
fn the_connection_cap_must_fit_the_file_limit_and_slots_come_back() {
    let mut child = std::process::Command::new(server_binary())
        .args(["--addr", "127.0.0.1:0", "--skip-warmup"])
        .env("SCNERF_MAX_CONNECTIONS", "4000000000")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let began = Instant::now();
    while child.try_wait().unwrap().is_none() && began.elapsed() < Duration::from_secs(20) {
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = child.kill();
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && (stderr.contains("open-file limit") || stderr.contains("open files")), "{stderr}");

    // At the cap, idle connections time out and give their slots to new clients.
    let server = start(&[("SCNERF_MAX_CONNECTIONS", "8"), ("SCNERF_HEADER_READ_TIMEOUT_SECS", "1")]);
    let _idle: Vec<_> = (0..8).map(|_| TcpStream::connect(server.addr).unwrap()).collect();
    let health = http_request(server.addr, "GET", "/healthz", &[], b"", Duration::from_secs(10)).unwrap();
    assert_eq!(health.status, 200);
}

#[test]
fn sigterm_does_not_wait_for_connections_without_a_request() {
    let mut server = start(&[("SCNERF_SHUTDOWN_GRACE_SECS", "30")]);
    let mut idle = TcpStream::connect(server.addr).unwrap();
    idle.write_all(b"GET /healthz HTTP/1.1\r\nHost: test\r\n\r\n").unwrap();
    assert_eq!(status_within(&mut idle, Duration::from_secs(5)), Some(200));
    let mut partial = TcpStream::connect(server.addr).unwrap();
    partial.write_all(b"POST /v1/render HTTP/1.1\r\nHost: te").unwrap();
    // Connections are accepted in order: once a later one is answered, the partial one is held.
    let later = http_request(server.addr, "GET", "/healthz", &[], b"", Duration::from_secs(10)).unwrap();
    assert_eq!(later.status, 200);
    let signalled = Instant::now();
    server.terminate();
    let status = server.wait_exit(Duration::from_secs(25));
    assert_eq!(status.code(), Some(0), "{status}");
    assert!(signalled.elapsed() < Duration::from_secs(5), "exit took {:?}", signalled.elapsed());
}

/// The head and header lines of the response on `stream` (lower-case names), if one arrives
/// within `timeout`.
fn response_within(stream: &mut TcpStream, timeout: Duration) -> Option<(u16, String)> {
    stream.set_read_timeout(Some(timeout)).unwrap();
    let mut buf = vec![0u8; 16 << 10];
    let n = stream.read(&mut buf).ok().filter(|n| *n > 0)?;
    let head = String::from_utf8_lossy(&buf[..n]).to_ascii_lowercase();
    Some((head.split_whitespace().nth(1)?.parse().ok()?, head))
}

/// A connection from `ip` that sends the head of a POST of `length` bytes, then `sent` of them,
/// then nothing.
fn stalled_post(ip: &str, server: SocketAddr, path: &str, headers: &str, length: u64, sent: usize) -> TcpStream {
    let mut stream = connect_from(ip, server);
    let head = format!(
        "POST {path} HTTP/1.1\r\nHost: test\r\nContent-Type: multipart/form-data; boundary=x\r\n{headers}Content-Length: {length}\r\n\r\n"
    );
    stream.write_all(head.as_bytes()).unwrap();
    stream.write_all(&vec![b' '; sent]).unwrap();
    stream
}

#[test]
fn one_address_cannot_take_every_connection_and_probes_are_answered_at_the_cap() {
    // Idle connections are not closed while the test runs, however slowly the machine runs it.
    let server = start(&[
        ("SCNERF_MAX_CONNECTIONS", "16"),
        ("SCNERF_MAX_CONNECTIONS_PER_CLIENT", "8"),
        ("SCNERF_HEADER_READ_TIMEOUT_SECS", "600"),
    ]);
    // One address holds as many connections as it may: the ninth is told 429 at once.
    let mut held: Vec<TcpStream> = (0..8).map(|_| connect_from("127.0.0.2", server.addr)).collect();
    let mut ninth = connect_from("127.0.0.2", server.addr);
    let (status, head) = response_within(&mut ninth, Duration::from_secs(1)).expect("an answer at once");
    assert_eq!(status, 429, "{head}");
    assert!(head.contains("retry-after: 1") && head.contains("connection: close"), "{head}");
    // Another address fills every other connection. Connections are taken in the order they
    // arrive, so the 16 ordinary ones are held before any probe comes.
    held.extend((0..8).map(|_| connect_from("127.0.0.3", server.addr)));
    // At the cap, the probes still get theirs, from the reserve, and only the probes. A probe
    // closes its connection, so that its reserve slot is back soon after its answer.
    let probe = |ip: &str, path: &str| {
        let mut s = connect_from(ip, server.addr);
        s.write_all(format!("GET {path} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n").as_bytes()).unwrap();
        let started = Instant::now();
        let status = response_within(&mut s, Duration::from_secs(5)).map(|(code, _)| code);
        (status, started.elapsed())
    };
    for path in ["/healthz", "/readyz", "/metrics"] {
        let (status, took) = probe("127.0.0.4", path);
        assert_eq!(status, Some(200), "{path}");
        assert!(took < Duration::from_secs(1), "{path} took {took:?}");
    }
    assert_eq!(probe("127.0.0.4", "/v1/model").0, Some(503));
    drop(held);
}

#[test]
fn a_refused_request_is_answered_at_once_without_its_body_being_read() {
    let server = start(&[("SCNERF_MAX_REQUESTS_PER_CLIENT", "1")]);
    // The client's one slot: an upload that stalls.
    let _holding = stalled_post("127.0.0.2", server.addr, "/v1/scenes", "", 4 << 20, 1 << 20);
    // Its body is being read, held against the memory budget, once it holds the slot.
    poll_until(|| metric(server.addr, "scnerf_memory_leased_bytes"), |b| *b > 0.0, Duration::from_secs(30));
    // Its next upload is refused with 4 MiB declared and 1 MiB sent: the answer comes at once,
    // with connection: close, although the rest of the body never comes.
    let mut refused = stalled_post("127.0.0.2", server.addr, "/v1/scenes", "", 4 << 20, 1 << 20);
    let (status, head) = response_within(&mut refused, Duration::from_secs(1)).expect("an answer within 1 s");
    assert_eq!(status, 429, "{head}");
    assert!(head.contains("connection: close"), "{head}");
    assert!(closed_within(&mut refused, Duration::from_secs(5)), "the refused connection stayed open");
}

#[test]
fn an_expired_request_is_answered_at_its_deadline_and_a_stalled_body_at_the_stall_limit() {
    let server = start(&[("SCNERF_BODY_STALL_SECS", "2")]);
    // 1 MiB of a 4 MiB body, then nothing: the 1 s deadline passes while the body is read.
    let started = Instant::now();
    let mut expired =
        stalled_post("127.0.0.2", server.addr, "/v1/render", "x-scnerf-deadline-ms: 1000\r\n", 4 << 20, 1 << 20);
    let (status, head) = response_within(&mut expired, Duration::from_secs(5)).expect("an answer");
    assert_eq!(status, 504, "{head}");
    assert!(head.contains("connection: close"), "{head}");
    assert!(started.elapsed() < Duration::from_secs(2), "the 504 came after {:?}", started.elapsed());
    // 2 MiB at once and then nothing buys no time: 408 at the stall limit, well before the
    // 30 s grace and the 64 s the bytes would have bought.
    let started = Instant::now();
    let mut stalled = stalled_post("127.0.0.3", server.addr, "/v1/render", "", 4 << 20, 2 << 20);
    let (status, head) = response_within(&mut stalled, Duration::from_secs(10)).expect("an answer");
    assert_eq!(status, 408, "{head}");
    assert!(started.elapsed() < Duration::from_secs(4), "the 408 came after {:?}", started.elapsed());
}

/// `read()` again every 20 ms until `done` holds of what it read, or `timeout` passes: its last value.
fn poll_until<T>(mut read: impl FnMut() -> T, done: impl Fn(&T) -> bool, timeout: Duration) -> T {
    let start = Instant::now();
    loop {
        let value = read();
        if done(&value) || start.elapsed() > timeout {
            return value;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// `/metrics` gauge `name`.
fn metric(server: SocketAddr, name: &str) -> f64 {
    let got = http_request(server, "GET", "/metrics", &[], b"", Duration::from_secs(120)).unwrap();
    let text = String::from_utf8_lossy(&got.body).into_owned();
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.trim().parse().ok())
        .unwrap_or_else(|| panic!("no {name} in /metrics"))
}

#[test]
fn bodies_in_flight_are_held_against_the_memory_budget() {
    let server = start(&[
        ("SCNERF_MEMORY_BUDGET_MB", "300"),
        ("SCNERF_SCENE_CACHE_MB", "0"),
        ("SCNERF_MAX_REQUESTS_PER_CLIENT", "0"),
        // Reading the uploads is slow in a debug build: they must not stall out meanwhile.
        ("SCNERF_BODY_STALL_SECS", "300"),
        ("SCNERF_BODY_TIMEOUT_SECS", "300"),
    ]);
    let for_requests =
        metric(server.addr, "scnerf_memory_budget_bytes") - metric(server.addr, "scnerf_memory_reserved_bytes");
    // Two uploads that stall halfway hold all but 16 MiB of what requests may have.
    let upload = (for_requests as usize - (16 << 20)) / 2;
    let addr = server.addr;
    let uploads: Vec<_> = (0..2)
        .map(|_| std::thread::spawn(move || stalled_post("127.0.0.2", addr, "/v1/captures", "", 250 << 20, upload)))
        .collect();
    let stalled: Vec<TcpStream> = uploads.into_iter().map(|u| u.join().unwrap()).collect();
    let leased_bytes = || metric(server.addr, "scnerf_memory_leased_bytes");
    let leased = poll_until(leased_bytes, |b| *b >= (2 * upload) as f64, Duration::from_secs(60));
    assert!(leased >= (2 * upload) as f64, "{leased} bytes leased for {} sent", 2 * upload);
    // A third is refused as its bytes come (503, at once), and so is a render.
    let mut third = stalled_post("127.0.0.3", server.addr, "/v1/captures", "", 250 << 20, 32 << 20);
    let (status, head) = response_within(&mut third, Duration::from_secs(2)).expect("an answer");
    assert_eq!(status, 503, "{head}");
    assert!(head.contains("retry-after") && head.contains("connection: close"), "{head}");
    let case = scnerf_e2e::Case::load(&repo_root().join("tests/fixtures/parity/cases/opencv_64x96")).unwrap();
    let (ctype, body) = case.multipart(&case.request);
    let render = |timeout| {
        http_request(server.addr, "POST", "/v1/render", &[("content-type", ctype.as_str())], &body, timeout).unwrap()
    };
    let busy = render(Duration::from_secs(60));
    assert_eq!(busy.status, 503, "{}", String::from_utf8_lossy(&busy.body));
    assert!(String::from_utf8_lossy(&busy.body).contains("MiB"));
    // The uploads' clients leave: their bytes, and their hold on the budget, go with them.
    drop(stalled);
    poll_until(leased_bytes, |b| *b == 0.0, Duration::from_secs(5));
    assert_eq!(render(Duration::from_secs(120)).status, 200);
}
