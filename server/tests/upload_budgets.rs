//! Scene and capture uploads against the memory budget, over the fake runner: their decoding is
//! admitted from the images' sizes before anything is decoded (503 + Retry-After while the budget
//! is in use, 422 naming the sizes for what can never fit, 422 for a scene larger than the
//! cache), a capture's files other than images are capped, and hostile capture files get a 4xx
//! naming the file, in time linear in the capture's files.

mod common;

use std::time::Duration;

use axum::Router;
use common::*;
use scnerf_server::backend::{BackendHandle, ExecutorOptions, MemoryBudget};
use scnerf_server::cache::CacheConfig;
use scnerf_server::http::{router, ServiceOptions};
use scnerf_server::request::Limits;
use scnerf_server::testing::{bundle, camera_json, png_header, state_with_executor, FakeRunner};
use serde_json::{json, Value};

/// A router whose requests may hold `budget_mib` MiB of estimates, and its executor (to hold
/// part of the budget as another request would).
fn app(budget_mib: u64, limits: Limits, cache: CacheConfig) -> (Router, BackendHandle) {
    let b = bundle("scnerf", "near_far");
    let executor = ExecutorOptions {
        memory: MemoryBudget { total: budget_mib << 20, reserved: 0 },
        ..ExecutorOptions::with_capacity(8)
    };
    let options = ServiceOptions { request_timeout: Duration::from_secs(60), cache, ..Default::default() };
    let state = state_with_executor(b.clone(), FakeRunner::new(&b), limits, options, executor);
    (router(state.clone()), state.pipeline().executor().clone())
}

async fn post_capture(app: &Router, files: &[(String, Vec<u8>)], headers: &[(&str, &str)]) -> Got {
    post_capture_to(app, "/v1/captures", files, headers).await
}

async fn post_capture_to(app: &Router, path: &str, files: &[(String, Vec<u8>)], headers: &[(&str, &str)]) -> Got {
    let parts: Vec<(&str, Option<&str>, &str, &[u8])> = files
        .iter()
        .map(|(name, data)| ("file", Some(name.as_str()), "application/octet-stream", data.as_slice()))
        .collect();
    let (ctype, body) = scnerf_e2e::multipart(&parts);
    send(app.clone(), raw_to("POST", path, &ctype, body, headers)).await
}

/// A Blender capture of `views` flat-looking `size` x `size` PNGs that only claim their size
/// (decoding them fails: a refusal before decoding is the only way to get anything else).
fn big_capture(views: usize, size: u32) -> Vec<(String, Vec<u8>)> {
    let fixture: Value =
        serde_json::from_slice(&std::fs::read(datasets().join("blender/transforms_train.json")).unwrap()).unwrap();
    let matrix = fixture["frames"][0]["transform_matrix"].clone();
    let frames: Vec<Value> =
        (0..views).map(|i| json!({"file_path": format!("./train/r_{i}"), "transform_matrix": matrix})).collect();
    let transforms = json!({"camera_angle_x": 0.69, "frames": frames});
    let mut files = vec![("transforms_train.json".to_string(), serde_json::to_vec(&transforms).unwrap())];
    files.extend((0..views).map(|i| (format!("train/r_{i}.png"), png_header(size, size))));
    files
}

fn message(got: &Got) -> String {
    json_of(got)["error"]["message"].as_str().unwrap_or_default().to_string()
}

#[tokio::test]
async fn a_capture_is_admitted_by_its_decoded_size_before_anything_is_decoded() {
    // 64 views of 1024x1024: 768 MiB decoded.
    let files = big_capture(64, 1024);
    let (small, _) = app(512, Limits::default(), CacheConfig::default());
    let got = post_capture(&small, &files, &[]).await;
    assert_error(&got, 422, "invalid_request", Some("sources"));
    assert!(message(&got).contains("64 source views of 1024x1024 need an estimated"), "{}", message(&got));

    let (roomy, executor) = app(2048, Limits::default(), CacheConfig { max_bytes: 1 << 30, ..Default::default() });
    let other = executor.lease(1500 << 20).unwrap(); // what other requests hold now
    let got = post_capture(&roomy, &files, &[]).await;
    assert_error(&got, 503, "unavailable", None);
    assert!(got.1.contains_key("retry-after"), "{:?}", got.1);
    drop(other);
    // With the budget free it is decoded, and the images, which only claim their size, fail.
    let got = post_capture(&roomy, &files, &[]).await;
    assert_error(&got, 400, "malformed_request", Some("train/r_0.png"));
}

/// 32 photos of 4096x4096 (sent as headers alone) are fitted to 1024x1024, which takes decoding
/// and resizing each: the scene is refused for the cache share from the headers' sizes first.
#[tokio::test]
async fn a_capture_too_large_for_the_cache_is_refused_from_its_headers_before_any_decode() {
    let files = big_capture(32, 4096);
    let (cached, _) = app(4096, Limits::default(), CacheConfig { max_bytes: 64 << 20, ..Default::default() });
    let got = post_capture(&cached, &files, &[]).await;
    assert_error(&got, 422, "invalid_request", Some("sources"));
    assert!(message(&got).contains("a client may hold at most"), "{}", message(&got));
    // Too large for the memory budget: refused the same way, naming the fitted sizes.
    let (small, _) = app(256, Limits::default(), CacheConfig::default());
    let got = post_capture(&small, &files, &[]).await;
    assert_error(&got, 422, "invalid_request", Some("sources"));
    assert!(message(&got).contains("32 source views of 1024x1024 need an estimated"), "{}", message(&got));
    // A depth range that validation refuses: refused before decoding too, naming the field.
    let (roomy, _) = app(4096, Limits::default(), CacheConfig::default());
    let got = post_capture_to(&roomy, "/v1/captures?near=1e-12&far=6", &files, &[]).await;
    assert_error(&got, 422, "invalid_request", Some("near"));
}

#[tokio::test]
async fn a_scene_upload_is_admitted_the_same_way_and_refused_first_when_the_cache_cannot_hold_it() {
    let sources: Vec<Value> = (0..64).map(|i| json!({"camera": camera_json(1024, 1024, 0.01 * i as f64)})).collect();
    let request = serde_json::to_vec(&json!({"sources": sources, "near": 2.0, "far": 6.0})).unwrap();
    let image = png_header(1024, 1024);
    let names: Vec<String> = (0..64).map(|i| format!("source_{i}")).collect();
    let mut parts: Vec<(&str, &[u8])> = vec![("request", &request)];
    parts.extend(names.iter().map(|n| (n.as_str(), image.as_slice())));

    let (small, _) = app(512, Limits::default(), CacheConfig::default());
    let got = send(small, multipart_to("/v1/scenes", &parts, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("sources"));
    assert!(message(&got).contains("64 source views of 1024x1024"), "{}", message(&got));

    let (roomy, executor) = app(2048, Limits::default(), CacheConfig { max_bytes: 1 << 30, ..Default::default() });
    let other = executor.lease(1500 << 20).unwrap();
    assert_error(&send(roomy.clone(), multipart_to("/v1/scenes", &parts, &[])).await, 503, "unavailable", None);
    drop(other);

    // A cache of 512 MiB cannot hold 768 MiB of views: 422 before decoding (decoding these
    // images would fail with 400).
    let (cached, _) = app(2048, Limits::default(), CacheConfig { max_bytes: 512 << 20, ..Default::default() });
    let got = send(cached, multipart_to("/v1/scenes", &parts, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("sources"));
    assert!(message(&got).contains("a client may hold at most"), "{}", message(&got));
}

#[tokio::test]
async fn a_captures_files_other_than_images_are_capped_apart_from_them() {
    let limits = Limits { max_capture_metadata_bytes: 2048, ..Limits::default() };
    let (app, _) = app(4096, limits, CacheConfig::default());
    // The images of the fixture are 266 bytes each: transforms_train.json (2929) goes over.
    let mut files = files_of(&datasets().join("blender"));
    files.retain(|(name, _)| name != "expected.json");
    let got = post_capture(&app, &files, &[]).await;
    assert_error(&got, 413, "payload_too_large", Some("transforms_train.json"));
    assert!(message(&got).contains("--max-capture-metadata-bytes"), "{}", message(&got));
    // The same bytes as images are fine.
    let mut images = files_of(&datasets().join("blender"));
    images.push(("train/extra.png".into(), vec![0; 4096]));
    let (roomy, _) = app_default();
    assert_eq!(post_capture(&roomy, &images, &[]).await.0, 201);
}

fn app_default() -> (Router, BackendHandle) {
    app(4096, Limits::default(), CacheConfig::default())
}

#[tokio::test]
async fn hostile_capture_files_get_a_4xx_naming_the_file() {
    let (app, _) = app_default();
    // Duplicate keys in a transforms file: the docs say they are refused, and now they are.
    let mut files = files_of(&datasets().join("nerfstudio"));
    let transforms = files.iter_mut().find(|(n, _)| n == "transforms.json").unwrap();
    let text = String::from_utf8(transforms.1.clone()).unwrap().replacen("\"fl_x\"", "\"fl_x\": 1.0, \"fl_x\"", 1);
    transforms.1 = text.into_bytes();
    let got = post_capture(&app, &files, &[]).await;
    assert_error(&got, 422, "invalid_request", Some("transforms.json"));
    assert!(message(&got).contains("key \"fl_x\" appears twice"), "{}", message(&got));

    // An LLFF poses file whose header declares (1085102592571150096, 17): a 500 ("capacity
    // overflow") before.
    let mut files = files_of(&datasets().join("llff"));
    let header = "{'descr': '<f8', 'fortran_order': False, 'shape': (1085102592571150096, 17), }";
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend_from_slice(&(header.len() as u16).to_le_bytes());
    npy.extend_from_slice(header.as_bytes());
    npy.extend_from_slice(&[0; 128]);
    files.iter_mut().find(|(n, _)| n == "poses_bounds.npy").unwrap().1 = npy;
    assert_error(&post_capture(&app, &files, &[]).await, 422, "invalid_request", Some("poses_bounds.npy"));

    // A filename that is not UTF-8: said so, rather than "needs a filename".
    let mut body = format!("--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"").into_bytes();
    body.extend_from_slice(b"\xff\xfe.png\"\r\nContent-Type: image/png\r\n\r\nxx\r\n");
    body.extend_from_slice(format!("--{BOUNDARY}--\r\n").as_bytes());
    let ctype = format!("multipart/form-data; boundary={BOUNDARY}");
    let got = send(app.clone(), raw_to("POST", "/v1/captures", &ctype, body, &[])).await;
    assert_error(&got, 400, "malformed_request", Some("file"));
    assert!(message(&got).contains("not UTF-8"), "{}", message(&got));
}

/// DTU's detection asked whether each entry of `Rectified/` is a folder by scanning every file:
/// 8,000 files cost 7.5 CPU-seconds (release build). Now the capture is read well within a
/// 5-second deadline, even in a debug build.
#[tokio::test]
async fn dtu_detection_is_linear_in_the_captures_files() {
    let (app, _) = app_default();
    let mut files = files_of(&datasets().join("dtu"));
    files.extend((0..8000).map(|i| (format!("Rectified/junk_{i:05}.txt"), vec![b'x'])));
    let got = post_capture(&app, &files, &[("x-scnerf-deadline-ms", "5000")]).await;
    assert_eq!(got.0, 201, "{}", String::from_utf8_lossy(&got.2));
}
