//! Graceful shutdown of the real binary: SIGTERM while a render is in flight. The server stops
//! accepting connections, finishes the request (the client gets its 200), and exits 0; past the
//! grace period the request is answered 503 and the exit status is 1.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use scnerf_e2e::{http_request, repo_root, server_binary, Case, HttpResponse, ServerProcess};

fn fixtures() -> PathBuf {
    repo_root().join("tests/fixtures/parity")
}

/// The first parity case as a multipart render request, its target camera enlarged `scale` times
/// (96x64 at scale 1: about a second of CPU on 2 cores).
fn render_body(scale: u32) -> (String, Vec<u8>) {
    let case = Case::load(&fixtures().join("cases/opencv_64x96")).expect("parity fixtures are committed");
    let mut request = case.request.clone();
    request["outputs"] = serde_json::json!(["rgb"]);
    let target = &mut request["target"];
    for side in ["width", "height"] {
        target[side] = (target[side].as_u64().unwrap() * u64::from(scale)).into();
    }
    // Pixel centres stay on the same rays: c' = (c + 0.5) * scale - 0.5.
    let intrinsics = &mut target["intrinsics"];
    for focal in ["fx", "fy"] {
        intrinsics[focal] = (intrinsics[focal].as_f64().unwrap() * f64::from(scale)).into();
    }
    for centre in ["cx", "cy"] {
        intrinsics[centre] = ((intrinsics[centre].as_f64().unwrap() + 0.5) * f64::from(scale) - 0.5).into();
    }
    case.multipart(&request)
}

fn start(grace_secs: &str) -> ServerProcess {
    let bundle = fixtures().join("bundle");
    let bundle = bundle.to_str().unwrap();
    // Full sampling: a render long enough to be in flight when the grace period ends.
    let mut server = ServerProcess::start(
        &server_binary(),
        &["--bundle", bundle, "--skip-warmup", "--shutdown-grace-secs", grace_secs, "--sampling", "full"],
    );
    server.wait_ready(Duration::from_secs(120));
    server
}

/// Sends the render on another thread; returns once the server has admitted it.
fn render_in_flight(server: &ServerProcess, scale: u32) -> std::thread::JoinHandle<std::io::Result<HttpResponse>> {
    let addr = server.addr;
    let client = std::thread::spawn(move || {
        let (ctype, body) = render_body(scale);
        http_request(addr, "POST", "/v1/render", &[("content-type", &ctype)], &body, Duration::from_secs(600))
    });
    let start = Instant::now();
    loop {
        let metrics = http_request(addr, "GET", "/metrics", &[], b"", Duration::from_secs(10)).unwrap();
        if String::from_utf8_lossy(&metrics.body).lines().any(|l| l == "scnerf_inference_queue_requests 1") {
            return client;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "the render was never admitted");
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn sigterm_finishes_the_request_in_flight_and_exits_0() {
    let mut server = start("300");
    let client = render_in_flight(&server, 1);
    let signalled = Instant::now();
    server.terminate();

    // No new connections once the signal is handled (the render is still running).
    let deadline = Instant::now() + Duration::from_secs(10);
    while http_request(server.addr, "GET", "/healthz", &[], b"", Duration::from_secs(2)).is_ok() {
        assert!(Instant::now() < deadline, "still accepting connections after SIGTERM");
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(server.child.try_wait().unwrap().is_none(), "exited before finishing the request in flight");

    let response = client.join().unwrap().expect("the request in flight is answered");
    assert_eq!(response.status, 200, "{}", String::from_utf8_lossy(&response.body));
    let png = image::load_from_memory(&response.body).expect("a PNG");
    assert_eq!((png.width(), png.height()), (96, 64));
    let status = server.wait_exit(Duration::from_secs(60));
    assert_eq!(status.code(), Some(0), "{status}");
    eprintln!("request answered and server exited {:?} after SIGTERM", signalled.elapsed());
}

#[test]
fn past_the_grace_period_requests_in_flight_get_503_and_the_exit_status_is_1() {
    let mut server = start("1");
    // 384x256: 16 times the pixels, well past the 1 s grace period on any machine.
    let client = render_in_flight(&server, 4);
    let signalled = Instant::now();
    server.terminate();
    let status = server.wait_exit(Duration::from_secs(30));
    let took = signalled.elapsed();
    assert_eq!(status.code(), Some(1), "{status}");
    // The client is told, not cut off.
    let response = client.join().unwrap().expect("the request in flight is answered");
    assert_eq!(response.status, 503, "{}", String::from_utf8_lossy(&response.body));
    assert_eq!(response.header("retry-after"), Some("1"));
    eprintln!("answered 503 and exited 1 {took:?} after SIGTERM with a 1 s grace period");
}
