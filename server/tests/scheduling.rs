//! Scheduling on the shared inference executor, over a slow fake runner: earliest deadline
//! first, admission by estimated finish time under overload, per-request deadlines (config and
//! header) and dropping the remaining work of requests whose deadline passed or whose client
//! disconnected.

mod common;

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::Request;
use common::*;
use scnerf_server::bundle::GraphKind;
use scnerf_server::http::{router, AppState, ServiceOptions};
use scnerf_server::request::Limits;
use scnerf_server::testing::{bundle, camera_json, request_json, state_with_options, FakeRunner};
use serde_json::Value;
use std::io::Write;

/// Every graph run takes `delay`; renderer chunks are 100 rays (testing::state_with_options).
fn slow_state(delay: Duration, timeout: Duration) -> (AppState, Arc<[AtomicUsize; GraphKind::ALL.len()]>) {
    let b = bundle("scnerf", "near_far");
    let mut runner = FakeRunner::new(&b);
    runner.delay = delay;
    let calls = runner.calls.clone();
    let options = ServiceOptions { request_timeout: timeout, ..Default::default() };
    (state_with_options(b, runner, Limits::default(), options, 8), calls)
}

fn renderer_runs(calls: &[AtomicUsize; GraphKind::ALL.len()]) -> usize {
    calls[GraphKind::Renderer.index()].load(Ordering::SeqCst)
}

/// A request whose target is `w` x `h` (w·h/100 renderer chunks).
fn request_with_target(w: u32, h: u32) -> Value {
    let mut req = request_json(32);
    req["target"] = camera_json(w, h, 0.1);
    req
}

async fn wait_for(what: &str, cond: impl Fn() -> bool) {
    let start = Instant::now();
    while !cond() {
        assert!(start.elapsed() < Duration::from_secs(20), "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// Earliest deadline first: a small view due sooner overtakes a big view that arrived before it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_view_due_sooner_overtakes_a_big_one() {
    let (state, calls) = slow_state(Duration::from_millis(20), Duration::from_secs(60));
    let app = router(state);
    // 100 x 80 = 80 chunks of 20 ms: 1.6 s of renderer work, due in 60 s.
    let big = tokio::spawn(send(app.clone(), multipart_with("/v1/render", &request_with_target(100, 80), 32, &[])));
    wait_for("the big view's renderer runs", || renderer_runs(&calls) >= 5).await;
    let start = Instant::now();
    let soon = [("x-scnerf-deadline-ms", "5000")];
    let small = send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &soon)).await;
    let small_took = start.elapsed();
    assert_eq!(small.0, 200, "{}", String::from_utf8_lossy(&small.2));
    assert!(!big.is_finished(), "the small view should finish while the big one is still rendering");
    // Its three graph runs go before the big view's remaining chunks: ~4 x 20 ms, not 75 x 20 ms.
    assert!(small_took < Duration::from_millis(900), "small view took {small_took:?}");
    let big = big.await.unwrap();
    assert_eq!(big.0, 200);
    assert_eq!(renderer_runs(&calls), 80 + 1);
}

/// The warm-up's tiny runs are mostly fixed cost: per ray, its 16-ray renderer run costs six times
/// what a 100-ray chunk does. Extrapolated, they would refuse the first real request on an idle
/// server; the warm-up leaves the graphs unmeasured instead.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_warm_up_does_not_refuse_the_first_request() {
    let (state, _calls) = slow_state(Duration::from_millis(20), Duration::from_secs(60));
    scnerf_server::server::warm_up(state.pipeline()).await.unwrap();
    // 50 chunks of 20 ms: 1 s of work, estimated 6 s at the warm-up's rate, due in 3 s.
    let due = [("x-scnerf-deadline-ms", "3000")];
    let got = send(router(state), multipart_with("/v1/render", &request_with_target(100, 50), 32, &due)).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
}

/// Sixteen concurrent renders of 10 graph runs of 20 ms (200 ms each) due in 1 s. Served round
/// robin they all finished together, after ~3.2 s: sixteen 504s. Earliest deadline first, with
/// admission by estimated finish time: the first few finish in time and the others are refused
/// at once with 429 + Retry-After (the work ahead of them makes them late) instead of failing late.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overload_finishes_what_can_finish_and_refuses_the_rest_at_once() {
    let b = bundle("scnerf", "near_far");
    let mut runner = FakeRunner::new(&b);
    runner.delay = Duration::from_millis(20);
    let app = router(state_with_options(b, runner, Limits::default(), ServiceOptions::default(), 16));
    let render = |headers: &[(&str, &str)]| multipart_with("/v1/render", &request_with_target(40, 20), 32, headers);
    // One render first, so that the executor has measured its graphs.
    assert_eq!(send(app.clone(), render(&[])).await.0, 200);
    let due = [("x-scnerf-deadline-ms", "1000")];
    let start = Instant::now();
    let tasks: Vec<_> = (0..16)
        .map(|_| {
            let request = send(app.clone(), render(&due));
            tokio::spawn(async move { (request.await, start.elapsed()) })
        })
        .collect();
    let mut outcomes = Vec::new();
    for t in tasks {
        let (got, took) = t.await.unwrap();
        if got.0 == 429 {
            assert_error(&got, 429, "too_many_requests", None);
            assert!(got.1.contains_key("retry-after"));
            assert!(took < Duration::from_millis(500), "a refusal should come at once, came after {took:?}");
        }
        outcomes.push((got.0.as_u16(), took));
    }
    let count = |status: u16| outcomes.iter().filter(|(s, _)| *s == status).count();
    assert!(count(200) >= 3, "too few finished in time: {outcomes:?}");
    assert!(count(504) <= 2, "admitted requests should finish in time: {outcomes:?}");
    assert!(count(429) >= 1, "the overload should be refused: {outcomes:?}");
    assert_eq!(count(200) + count(429) + count(504), 16, "{outcomes:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deadline_header_gives_504_and_the_rest_of_the_work_is_dropped() {
    let (state, calls) = slow_state(Duration::from_millis(20), Duration::from_secs(60));
    let app = router(state.clone());
    let start = Instant::now();
    let req = multipart_with("/v1/render", &request_with_target(100, 80), 32, &[("x-scnerf-deadline-ms", "300")]);
    let got = send(app, req).await;
    assert_error(&got, 504, "deadline_exceeded", None);
    assert!(json_of(&got)["error"]["message"].as_str().unwrap().contains("300 ms"));
    assert!(start.elapsed() < Duration::from_secs(2), "504 after {:?}", start.elapsed());
    let at_timeout = renderer_runs(&calls);
    tokio::time::sleep(Duration::from_millis(400)).await;
    let later = renderer_runs(&calls);
    assert!(later <= at_timeout + 1, "chunks kept running after the deadline: {at_timeout} -> {later}");
    assert!(later < 40, "{later} of 80 chunks ran");
    assert_eq!(state.pipeline().executor().stats().admitted, 0);
    assert_eq!(state.pipeline().executor().stats().queued_jobs, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_configured_deadline_bounds_the_header() {
    let (state, _) = slow_state(Duration::from_millis(50), Duration::from_millis(200));
    let req = multipart_with("/v1/render", &request_with_target(100, 80), 32, &[("x-scnerf-deadline-ms", "100000")]);
    let start = Instant::now();
    assert_error(&send(router(state), req).await, 504, "deadline_exceeded", None);
    assert!(start.elapsed() < Duration::from_secs(2));
}

#[tokio::test]
async fn bad_deadline_headers_are_400() {
    let (state, _) = slow_state(Duration::ZERO, Duration::from_secs(10));
    let app = router(state);
    for bad in ["soon", "0", "-5", "1.5", "99999999999999999999999", "+5000", "05000", "00", "5000 ms", "5_000"] {
        let req = multipart_with("/v1/render", &request_json(32), 32, &[("x-scnerf-deadline-ms", bad)]);
        assert_error(&send(app.clone(), req).await, 400, "malformed_request", Some("x-scnerf-deadline-ms"));
    }
    let req = multipart_with("/v1/render", &request_json(32), 32, &[("x-scnerf-deadline-ms", "5000")]);
    assert_eq!(send(app, req).await.0, 200);
}

/// Over a real socket: the client closes its connection mid-render; hyper drops the handler,
/// and with it the request's ticket, so its remaining chunks never run.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_disconnected_client_s_remaining_chunks_are_dropped() {
    let (state, calls) = slow_state(Duration::from_millis(20), Duration::from_secs(60));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let app = router(state.clone());
    let server = tokio::spawn(async move { axum::serve(listener, app).await });

    let json = serde_json::to_vec(&request_with_target(100, 80)).unwrap();
    let imgs = images(32);
    let body =
        multipart_body(&[("request", &json), ("source_0", &imgs[0]), ("source_1", &imgs[1]), ("source_2", &imgs[2])]);
    let head = format!(
        "POST /v1/render HTTP/1.1\r\nHost: {addr}\r\nContent-Type: multipart/form-data; boundary={BOUNDARY}\r\nContent-Length: {}\r\n\r\n",
        body.len()
    );
    // A blocking socket is fine here: the request fits in the loopback socket buffers.
    let mut stream = std::net::TcpStream::connect(addr).unwrap();
    stream.write_all(head.as_bytes()).unwrap();
    stream.write_all(&body).unwrap();
    wait_for("the renderer to start", || renderer_runs(&calls) >= 3).await;
    drop(stream);

    wait_for("the request to be released", || state.pipeline().executor().stats().admitted == 0).await;
    let at_release = renderer_runs(&calls);
    tokio::time::sleep(Duration::from_millis(400)).await;
    let later = renderer_runs(&calls);
    assert!(later <= at_release + 1, "chunks kept running after the disconnect: {at_release} -> {later}");
    assert!(later < 40, "{later} of 80 chunks ran for a client that left");
    assert_eq!(state.pipeline().executor().stats().queued_jobs, 0);

    // The server still serves.
    let got = send(router(state), multipart_with("/v1/render", &request_json(32), 32, &[])).await;
    assert_eq!(got.0, 200);
    server.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_executor_answers_503_with_retry_after_and_recovers() {
    let b = bundle("scnerf", "near_far");
    let mut runner = FakeRunner::new(&b);
    runner.delay = Duration::from_millis(30);
    let app = router(state_with_options(b, runner, Limits::default(), ServiceOptions::default(), 2));
    let tasks: Vec<_> = (0..8)
        .map(|_| tokio::spawn(send(app.clone(), multipart_with("/v1/render", &request_with_target(40, 20), 32, &[]))))
        .collect();
    let mut statuses = Vec::new();
    for t in tasks {
        let got = t.await.unwrap();
        if got.0 == 503 {
            assert_error(&got, 503, "unavailable", None);
            assert!(got.1.contains_key("retry-after"));
        }
        statuses.push(got.0.as_u16());
    }
    assert!(statuses.contains(&503) && statuses.contains(&200), "{statuses:?}");
    let req = Request::get("/readyz").body(Body::empty()).unwrap();
    assert_eq!(send(app.clone(), req).await.0, 200);
    assert_eq!(send(app, multipart_with("/v1/render", &request_json(32), 32, &[])).await.0, 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn posts_beyond_the_in_flight_limit_get_503_before_their_body_is_read() {
    let b = bundle("scnerf", "near_far");
    let mut runner = FakeRunner::new(&b);
    runner.delay = Duration::from_millis(20);
    let calls = runner.calls.clone();
    let options = ServiceOptions { max_concurrent_requests: 1, ..Default::default() };
    let app = router(state_with_options(b, runner, Limits::default(), options, 8));
    let busy = tokio::spawn(send(app.clone(), multipart_with("/v1/render", &request_with_target(40, 20), 32, &[])));
    wait_for("the first request to start", || calls[GraphKind::Encoder.index()].load(Ordering::SeqCst) >= 1).await;
    let got = send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[])).await;
    assert_error(&got, 503, "unavailable", None);
    assert_eq!(got.1["retry-after"], "1");
    // GETs are not limited.
    assert_eq!(send(app.clone(), get("/healthz", &[])).await.0, 200);
    assert_eq!(busy.await.unwrap().0, 200);
    assert_eq!(send(app, multipart_with("/v1/render", &request_json(32), 32, &[])).await.0, 200);
}
