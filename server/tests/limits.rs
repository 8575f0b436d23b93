//! Request limits: decompression bombs are refused from the image header without allocating the
//! image (checked with a counting allocator), JSON depth and size, body size, target size.

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use axum::Router;
use common::*;
use scnerf_server::http::router;
use scnerf_server::image_io::decode_source;
use scnerf_server::request::Limits;
use scnerf_server::testing::{bundle, png_header, request_json, state_with, FakeRunner};
use serde_json::json;

/// Records the largest single allocation, and the bytes allocated and not yet freed (live) with
/// their peak.
struct PeakAlloc;

static LARGEST: AtomicUsize = AtomicUsize::new(0);
static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK_LIVE: AtomicUsize = AtomicUsize::new(0);

fn grew(by: usize) {
    let live = LIVE.fetch_add(by, Ordering::Relaxed) + by;
    PEAK_LIVE.fetch_max(live, Ordering::Relaxed);
}

unsafe impl GlobalAlloc for PeakAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        LARGEST.fetch_max(layout.size(), Ordering::Relaxed);
        grew(layout.size());
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        LARGEST.fetch_max(new_size, Ordering::Relaxed);
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        grew(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: PeakAlloc = PeakAlloc;

fn app(limits: Limits) -> Router {
    let b = bundle("scnerf", "near_far");
    let runner = FakeRunner::new(&b);
    router(state_with(b, runner, limits, Duration::from_secs(10)))
}

/// One test only touches the allocator counter (tests of a binary run in parallel, and the
/// counter is process-wide), so all bomb checks live here.
#[tokio::test]
async fn decompression_bombs_are_refused_from_the_header_without_allocating() {
    let bomb = png_header(100_000, 100_000); // 30 GB of RGB if decoded
    LARGEST.store(0, Ordering::Relaxed);
    let err = decode_source(&bomb, "source_1", [0.0; 3], 1024 * 1024).unwrap_err();
    let largest = LARGEST.load(Ordering::Relaxed);
    assert_eq!(err.field(), Some("source_1"));
    assert!(largest < 1 << 20, "refusing the bomb allocated {largest} bytes at once");

    // Through HTTP: the camera claims 32x32, the image header says 100000x100000.
    let json = serde_json::to_vec(&request_json(32)).unwrap();
    let imgs = images(32);
    let parts: [(&str, &[u8]); 4] =
        [("request", &json), ("source_0", &imgs[0]), ("source_1", &bomb), ("source_2", &imgs[2])];
    let got = send(app(Limits::default()), multipart_to("/v1/render", &parts, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("source_1"));
    let largest = LARGEST.load(Ordering::Relaxed);
    assert!(largest < 16 << 20, "the request allocated {largest} bytes at once");
}

/// 8 MiB of empty `sources` entries (`0a 00`, 4M of them) used to become 4M decoded structs
/// (~600 MB, 3.5 GB for a 63 MiB body) before the view count was checked. Now the entries are
/// counted on the wire first: the refusal costs about the body's own size. (Live bytes are
/// process-wide: other tests of this binary allocate a few MB meanwhile; the margin covers them.)
#[tokio::test]
async fn protobuf_repeated_fields_cannot_amplify_memory() {
    let app = app(Limits::default());
    let body = [0x0a, 0x00].repeat(4 << 20);
    for path in ["/v1/render", "/v1/scenes"] {
        let before = LIVE.load(Ordering::Relaxed);
        PEAK_LIVE.store(before, Ordering::Relaxed);
        let got = send(app.clone(), raw_to("POST", path, "application/x-protobuf", body.clone(), &[])).await;
        let grown = PEAK_LIVE.load(Ordering::Relaxed).saturating_sub(before);
        eprintln!("{path}: refusing {} bytes of empty sources took {grown} bytes at peak", body.len());
        assert!(grown < 5 * body.len(), "{path}: refusing {} bytes of protobuf took {grown} bytes", body.len());
        assert_error(&got, 422, "invalid_request", Some("sources"));
    }
}

#[tokio::test]
async fn deeply_nested_json_is_refused_before_parsing() {
    let app = app(Limits::default());
    let mut req = request_json(32);
    req["seed"] = json!([[0]]);
    let deep = format!("{{\"sources\": {}{}", "[".repeat(50_000), "]".repeat(50_000));
    let parts: [(&str, &[u8]); 1] = [("request", deep.as_bytes())];
    let got = send(app.clone(), multipart_to("/v1/render", &parts, &[])).await;
    assert_error(&got, 400, "malformed_request", Some("request"));
    assert!(String::from_utf8_lossy(&got.2).contains("nested deeper"));
    let got = send(app.clone(), raw_to("POST", "/v1/render", "application/json", deep.clone().into_bytes(), &[])).await;
    assert_error(&got, 400, "malformed_request", Some("body"));
    // Within the limit but still not a request: an ordinary, named parse error.
    let got = send(app, multipart_with("/v1/render", &req, 32, &[])).await;
    assert_error(&got, 400, "malformed_request", Some("seed"));
}

#[tokio::test]
async fn json_depth_limit_is_configurable() {
    // A valid request nests 7 deep (sources[i].camera.pose.matrix rows).
    let got = send(
        app(Limits { max_json_depth: 6, ..Limits::default() }),
        multipart_with("/v1/render", &request_json(32), 32, &[]),
    )
    .await;
    assert_error(&got, 400, "malformed_request", Some("request"));
    let got = send(
        app(Limits { max_json_depth: 7, ..Limits::default() }),
        multipart_with("/v1/render", &request_json(32), 32, &[]),
    )
    .await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
}

#[tokio::test]
async fn json_documents_over_the_size_limit_are_413() {
    let app = app(Limits { max_json_bytes: 4096, ..Limits::default() });
    let mut req = request_json(32);
    req["seed"] = json!("x".repeat(5000));
    let got = send(app.clone(), multipart_with("/v1/render", &req, 32, &[])).await;
    assert_error(&got, 413, "payload_too_large", Some("request"));
    let mut view = target_json(32);
    view["pad"] = json!("x".repeat(5000));
    let got = send(app.clone(), json_to("/v1/scenes/0123456789abcdef0123456789abcdef/render", &view, &[])).await;
    assert_error(&got, 413, "payload_too_large", Some("body"));
    // Images are not JSON: a multipart body with images above 4 KiB is fine.
    let got = send(app, multipart_with("/v1/render", &request_json(32), 32, &[])).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
}
