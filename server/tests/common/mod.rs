//! Helpers shared by the router-level test files (driven with `tower::ServiceExt::oneshot`).
#![allow(dead_code)] // each test file uses a different subset

use axum::body::{Body, Bytes};
use axum::http::{HeaderMap, Request, StatusCode};
use axum::Router;
use base64::Engine;
use http_body_util::BodyExt;
use scnerf_server::testing::{png, request_json};
use serde_json::{json, Value};
use tower::ServiceExt;

pub use scnerf_e2e::BOUNDARY;

pub type Got = (StatusCode, HeaderMap, Bytes);

pub async fn send(app: Router, req: Request<Body>) -> Got {
    let resp = app.oneshot(req).await.expect("infallible");
    let status = resp.status();
    let headers = resp.headers().clone();
    let body = resp.into_body().collect().await.unwrap().to_bytes();
    (status, headers, body)
}

/// Asserts docs/design.md's error body with the given status, code and field.
pub fn assert_error(got: &Got, status: u16, code: &str, field: Option<&str>) {
    let (s, headers, body) = got;
    let text = String::from_utf8_lossy(body);
    assert_eq!(s.as_u16(), status, "body: {text}");
    assert_eq!(headers["content-type"], "application/json", "{text}");
    let v: Value = serde_json::from_slice(body).unwrap_or_else(|_| panic!("not JSON: {text}"));
    assert_eq!(v["error"]["code"], code, "{text}");
    assert!(v["error"]["message"].as_str().is_some_and(|m| !m.is_empty()), "{text}");
    match field {
        Some(f) => assert_eq!(v["error"]["field"], f, "{text}"),
        None => assert!(v["error"]["field"].is_null(), "{text}"),
    }
}

pub fn json_of(got: &Got) -> Value {
    serde_json::from_slice(&got.2).unwrap_or_else(|_| panic!("not JSON: {}", String::from_utf8_lossy(&got.2)))
}

/// A multipart body of (name, bytes) parts: the `request` part as JSON, the others as files.
pub fn multipart_body(parts: &[(&str, &[u8])]) -> Vec<u8> {
    let parts: Vec<(&str, Option<&str>, &str, &[u8])> = parts
        .iter()
        .map(|&(name, data)| match name {
            "request" => (name, None, "application/json", data),
            _ => (name, Some(name), "application/octet-stream", data),
        })
        .collect();
    scnerf_e2e::multipart(&parts).1
}

pub fn multipart_to(path: &str, parts: &[(&str, &[u8])], headers: &[(&str, &str)]) -> Request<Body> {
    let mut b = Request::post(path).header("content-type", format!("multipart/form-data; boundary={BOUNDARY}"));
    for (k, v) in headers {
        b = b.header(*k, *v);
    }
    b.body(Body::from(multipart_body(parts))).unwrap()
}

pub fn images(size: u32) -> Vec<Vec<u8>> {
    (0..3).map(|i| png(size, size, [40 * i as u8, 100, 200, 255])).collect()
}

/// A multipart request to `path` with the given request JSON and three images of `size`.
pub fn multipart_with(path: &str, request: &Value, size: u32, headers: &[(&str, &str)]) -> Request<Body> {
    let json = serde_json::to_vec(request).unwrap();
    let imgs = images(size);
    let parts: [(&str, &[u8]); 4] =
        [("request", &json), ("source_0", &imgs[0]), ("source_1", &imgs[1]), ("source_2", &imgs[2])];
    multipart_to(path, &parts, headers)
}

pub fn json_to(path: &str, body: &Value, headers: &[(&str, &str)]) -> Request<Body> {
    raw_to("POST", path, "application/json", serde_json::to_vec(body).unwrap(), headers)
}

pub fn raw_to(method: &str, path: &str, ctype: &str, body: Vec<u8>, headers: &[(&str, &str)]) -> Request<Body> {
    let mut b = Request::builder().method(method).uri(path).header("content-type", ctype);
    for (k, v) in headers {
        b = b.header(*k, *v);
    }
    b.body(Body::from(body)).unwrap()
}

pub fn get(path: &str, headers: &[(&str, &str)]) -> Request<Body> {
    let mut b = Request::get(path);
    for (k, v) in headers {
        b = b.header(*k, *v);
    }
    b.body(Body::empty()).unwrap()
}

pub fn b64(data: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(data)
}

/// docs/design.md's JSON body: the request with base64 images.
pub fn json_with_images(size: u32) -> Value {
    let mut v = request_json(size);
    for (i, img) in images(size).iter().enumerate() {
        v["sources"][i]["image"] = json!(b64(img));
    }
    v
}

/// The scene part of `request_json` (no target, no outputs).
pub fn scene_json(size: u32) -> Value {
    scnerf_e2e::split_request(&request_json(size)).0
}

/// The view part of `request_json`.
pub fn target_json(size: u32) -> Value {
    scnerf_e2e::split_request(&request_json(size)).1
}

pub const ALICE: &str = "alice-token-9f8e7d6c5b4a";
pub const BOB: &str = "bob-token-0a1b2c3d4e5f";

/// The router over a fake runner with bearer auth for the two tokens above.
pub fn two_token_app() -> Router {
    use scnerf_server::auth::Auth;
    use scnerf_server::http::{router, ServiceOptions};
    use scnerf_server::request::Limits;
    use scnerf_server::testing::{bundle, state_with_options, FakeRunner};
    let b = bundle("scnerf", "near_far");
    let runner = FakeRunner::new(&b);
    let options = ServiceOptions { auth: Auth::from_tokens(&[ALICE, BOB]), ..Default::default() };
    router(state_with_options(b, runner, Limits::default(), options, 8))
}

pub fn bearer(token: &str) -> String {
    format!("Bearer {token}")
}

/// A camera of docs/design.md's JSON form (`{fx, fy, cx, cy}` intrinsics) as a protobuf message.
pub fn proto_camera(c: &Value) -> scnerf_proto::v1::Camera {
    use scnerf_proto::v1 as pb;
    let f = |v: &Value| v.as_f64().unwrap();
    let i = &c["intrinsics"];
    let pose = &c["pose"];
    let kind = match pose["kind"].as_str() {
        Some("camera_to_world") => pb::PoseKind::CameraToWorld,
        _ => pb::PoseKind::WorldToCamera,
    };
    let axes = if pose["axes"] == "opengl" { pb::Axes::Opengl } else { pb::Axes::Opencv };
    pb::Camera {
        width: c["width"].as_u64().unwrap() as u32,
        height: c["height"].as_u64().unwrap() as u32,
        intrinsics_kind: Some(pb::camera::IntrinsicsKind::Intrinsics(pb::Intrinsics {
            fx: f(&i["fx"]),
            fy: f(&i["fy"]),
            cx: f(&i["cx"]),
            cy: f(&i["cy"]),
        })),
        pose: Some(pb::Pose {
            matrix: pose["matrix"]
                .as_array()
                .unwrap()
                .iter()
                .flat_map(|r| r.as_array().unwrap().iter().map(f))
                .collect(),
            kind: kind as i32,
            axes: axes as i32,
        }),
    }
}

/// A render request in docs/design.md's JSON form with `images`, as a protobuf message (the fields
/// the JSON leaves out stay empty).
pub fn proto_request(r: &Value, images: &[Vec<u8>]) -> scnerf_proto::v1::RenderRequest {
    use scnerf_proto::v1 as pb;
    let numbers = |v: &Value| v.as_array().map(|a| a.iter().filter_map(Value::as_f64).collect()).unwrap_or_default();
    let strings = |v: &Value| {
        v.as_array().map(|a| a.iter().filter_map(|s| s.as_str().map(str::to_string)).collect()).unwrap_or_default()
    };
    pb::RenderRequest {
        sources: (0..images.len())
            .map(|i| pb::Source { camera: Some(proto_camera(&r["sources"][i]["camera"])), image: images[i].clone() })
            .collect(),
        target: Some(proto_camera(&r["target"])),
        near: r["near"].as_f64().unwrap(),
        far: r["far"].as_f64().unwrap(),
        background: numbers(&r["background"]),
        outputs: strings(&r["outputs"]),
        sampling: r["sampling"].as_str().unwrap_or_default().to_string(),
        model: r["model"].as_str().unwrap_or_default().to_string(),
    }
}

/// The dataset fixtures of every capture format.
pub fn datasets() -> std::path::PathBuf {
    scnerf_e2e::repo_root().join("tests/fixtures/datasets")
}

/// Every file under `dir` as (path relative to `dir`, bytes).
pub fn files_of(dir: &std::path::Path) -> Vec<(String, Vec<u8>)> {
    fn walk(root: &std::path::Path, dir: &std::path::Path, out: &mut Vec<(String, Vec<u8>)>) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                walk(root, &path, out);
            } else {
                out.push((
                    path.strip_prefix(root).unwrap().to_str().unwrap().to_string(),
                    std::fs::read(&path).unwrap(),
                ));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}
