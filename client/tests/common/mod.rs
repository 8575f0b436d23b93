//! A small in-process stand-in for scnerf-server's capture-scene API (axum on a loopback port):
//! `PUT /v1/scenes/{id}` (multipart: `request` JSON + `source_i` images; 201 new, 200
//! replaced), `POST /v1/scenes/{id}/render` (JSON) and `GET /v1/limits` (`max_scene_views`,
//! `max_source_pixels` as set in [`FakeState::max_source_pixels`]),
//! answering like the real server, plus scripted failures:
//! the next renders can answer 503 with Retry-After, or 404 `scene_not_found` with the hint
//! `reupload` (the scene is forgotten, as after expiry), or a plain 404 without the hint (as a
//! proxy in front of no scene API would), or 422 for a target wider than 4096; a scene of more than
//! `MAX_VIEWS` views is refused from its `request` part, before the images are read.

#![allow(dead_code)] // each test binary uses part of it

pub mod captures;

use std::collections::HashSet;
use std::io::Cursor;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use axum::extract::{Multipart, Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, put};
use axum::{Json, Router};
use base64::Engine;
use scnerf_capture::camera::{Axes, PoseKind};
use scnerf_capture::wire::{WireCamera, WireIntrinsics};
use serde::Deserialize;
use serde_json::{json, Value};

/// Most views per scene.
pub const MAX_VIEWS: usize = 8;

#[derive(Default)]
pub struct FakeState {
    /// Number of views of every upload, in order.
    pub uploads: Mutex<Vec<usize>>,
    /// The scene id of every upload, in order.
    pub ids: Mutex<Vec<String>>,
    /// Renders answered 200.
    pub renders: AtomicUsize,
    /// The next this many renders answer 503 (Retry-After: 1).
    pub busy: AtomicUsize,
    /// The next this many renders answer 404 `not_found` without a hint.
    pub unrouted: AtomicUsize,
    /// The next this many renders forget their scene and answer 404 scene_not_found.
    pub forget: AtomicUsize,
    /// What `GET /v1/limits` answers as `max_source_pixels` (0: 1024 x 1024).
    pub max_source_pixels: AtomicUsize,
    /// The size of the first image of every upload.
    pub first_image_sizes: Mutex<Vec<(u32, u32)>>,
    /// The `sampling` of every render request (None: not sent).
    pub samplings: Mutex<Vec<Option<String>>>,
    /// The `model` of every upload and of every render request, in order (None: not sent).
    pub upload_models: Mutex<Vec<Option<String>>>,
    pub render_models: Mutex<Vec<Option<String>>>,
    scenes: Mutex<HashSet<String>>,
}

pub struct FakeServer {
    pub url: String,
    pub state: Arc<FakeState>,
    _runtime: tokio::runtime::Runtime,
}

impl FakeServer {
    pub fn start() -> FakeServer {
        let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        let state = Arc::new(FakeState::default());
        let listener = runtime.block_on(tokio::net::TcpListener::bind("127.0.0.1:0")).unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let app = Router::new()
            .route("/v1/scenes/{id}", put(create))
            .route("/v1/scenes/{id}/render", post(render))
            .route("/v1/limits", get(limits))
            .with_state(state.clone());
        runtime.spawn(async move { axum::serve(listener, app).await.unwrap() });
        FakeServer { url, state, _runtime: runtime }
    }

    pub fn uploads(&self) -> Vec<usize> {
        self.state.uploads.lock().unwrap().clone()
    }

    pub fn ids(&self) -> Vec<String> {
        self.state.ids.lock().unwrap().clone()
    }

    pub fn renders(&self) -> usize {
        self.state.renders.load(Ordering::SeqCst)
    }
}

async fn limits(State(state): State<Arc<FakeState>>) -> Json<Value> {
    let pixels = match state.max_source_pixels.load(Ordering::SeqCst) {
        0 => 1 << 20,
        n => n,
    };
    Json(json!({"max_source_pixels": pixels, "max_target_pixels": 1 << 22, "max_scene_views": MAX_VIEWS,
                "max_body_bytes": 64 << 20, "max_capture_bytes": 256 << 20, "max_json_bytes": 1 << 20}))
}

fn error(status: StatusCode, code: &str, message: &str, field: Option<&str>) -> Response {
    (status, Json(json!({"error": {"code": code, "message": message, "field": field}}))).into_response()
}

/// The real server's answer for a scene it does not hold.
fn scene_not_found() -> Response {
    let body = json!({"error": {"code": "scene_not_found", "message": "no such scene (expired?)",
                                "field": "scene_id", "hint": "reupload"}});
    (StatusCode::NOT_FOUND, Json(body)).into_response()
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneRequest {
    sources: Vec<Source>,
    near: f64,
    far: f64,
    background: [f64; 3],
    model: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Source {
    camera: WireCamera,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RenderRequest {
    target: WireCamera,
    outputs: Vec<String>,
    sampling: Option<String>,
    model: Option<String>,
}

/// What the client always sends: `{fx, fy, cx, cy}` with positive focal lengths, canonical poses.
fn check(c: &WireCamera) {
    let Some(WireIntrinsics::Focal(i)) = &c.intrinsics else { panic!("the client sends {{fx, fy, cx, cy}}") };
    assert!(c.k.is_none() && i.fx > 0.0 && i.fy > 0.0 && i.cx.is_finite() && i.cy.is_finite());
    assert_eq!((c.pose.kind, c.pose.axes), (PoseKind::WorldToCamera, Axes::Opencv));
    assert_eq!(c.pose.matrix[3], [0.0, 0.0, 0.0, 1.0]);
}

async fn create(State(state): State<Arc<FakeState>>, Path(id): Path<String>, mut multipart: Multipart) -> Response {
    let mut request: Option<SceneRequest> = None;
    let mut images = Vec::new();
    while let Some(field) = multipart.next_field().await.unwrap() {
        let name = field.name().unwrap_or_default().to_string();
        let bytes = field.bytes().await.unwrap();
        if name == "request" {
            match serde_json::from_slice::<SceneRequest>(&bytes) {
                // refused before the images are read, as the real server does
                Ok(r) if r.sources.len() > MAX_VIEWS => {
                    let message = format!("a scene takes at most {MAX_VIEWS} views, got {}", r.sources.len());
                    return error(StatusCode::UNPROCESSABLE_ENTITY, "invalid_request", &message, Some("sources"));
                }
                Ok(r) => request = Some(r),
                Err(e) => return error(StatusCode::BAD_REQUEST, "malformed", &e.to_string(), Some("request")),
            }
        } else {
            assert_eq!(name, format!("source_{}", images.len()), "parts in order");
            images.push(bytes);
        }
    }
    let request = request.expect("a request part");
    assert_eq!(request.sources.len(), images.len(), "one image part per source");
    assert!(request.sources.len() >= 3 && request.near < request.far);
    assert!(request.background.iter().all(|c| (0.0..=1.0).contains(c)));
    for (s, img) in request.sources.iter().zip(&images) {
        let dims = image::load_from_memory(img).map(|i| (i.width(), i.height())).unwrap();
        assert_eq!(dims, (s.camera.width, s.camera.height), "camera size is the image's");
        check(&s.camera);
    }
    let first = &request.sources[0].camera;
    state.first_image_sizes.lock().unwrap().push((first.width, first.height));
    state.uploads.lock().unwrap().push(images.len());
    state.upload_models.lock().unwrap().push(request.model.clone());
    state.ids.lock().unwrap().push(id.clone());
    let status = if state.scenes.lock().unwrap().insert(id.clone()) { StatusCode::CREATED } else { StatusCode::OK };
    (status, Json(json!({"scene_id": id, "expires_at": "2026-12-01T00:00:00.000Z"}))).into_response()
}

/// Takes one from a counter of scripted failures.
fn take(counter: &AtomicUsize) -> bool {
    counter.fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1)).is_ok()
}

async fn render(State(state): State<Arc<FakeState>>, Path(id): Path<String>, body: String) -> Response {
    if take(&state.busy) {
        let mut r = error(StatusCode::SERVICE_UNAVAILABLE, "overloaded", "the inference queue is full", None);
        r.headers_mut().insert("retry-after", HeaderValue::from_static("1"));
        return r;
    }
    if take(&state.unrouted) {
        return error(StatusCode::NOT_FOUND, "not_found", "no route", Some("path"));
    }
    if take(&state.forget) {
        state.scenes.lock().unwrap().remove(&id);
    }
    if !state.scenes.lock().unwrap().contains(&id) {
        return scene_not_found();
    }
    let request: RenderRequest = match serde_json::from_str(&body) {
        Ok(r) => r,
        Err(e) => return error(StatusCode::BAD_REQUEST, "malformed", &e.to_string(), Some("body")),
    };
    let (w, h) = (request.target.width, request.target.height);
    if w > 4096 {
        return error(StatusCode::UNPROCESSABLE_ENTITY, "invalid", "target too large", Some("target.width"));
    }
    check(&request.target);
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 255 / w) as u8, (y * 255 / h) as u8, 128]));
    let mut png = Vec::new();
    img.write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png).unwrap();
    let b64 = |b: &[u8]| base64::engine::general_purpose::STANDARD.encode(b);
    let mut body = json!({
        "model_id": "fake", "width": w, "height": h,
        "rgb": {"format": "png", "data": b64(&png)},
        "timings_ms": {"renderer": 12.5, "total": 13.0},
        "sources": [0, 1, 2],
    });
    if request.outputs.iter().any(|o| o == "depth") {
        let depth: Vec<u8> = (0..w * h).flat_map(|i| (2.0f32 + i as f32 * 0.01).to_le_bytes()).collect();
        body["depth"] =
            json!({"width": w, "height": h, "dtype": "float32", "byte_order": "little", "data": b64(&depth)});
    }
    // Like the real server: the sampling asked for is said back, with its samples per ray.
    if let Some(sampling) = &request.sampling {
        body["sampling"] = json!(sampling);
        body["samples_per_ray"] = json!(if sampling == "full" { 128.0 } else { 7.5 });
    }
    state.samplings.lock().unwrap().push(request.sampling.clone());
    state.render_models.lock().unwrap().push(request.model.clone());
    state.renders.fetch_add(1, Ordering::SeqCst);
    let mut headers = HeaderMap::new();
    headers.insert("x-scnerf-sources", HeaderValue::from_static("0,1,2"));
    (headers, Json::<Value>(body)).into_response()
}
