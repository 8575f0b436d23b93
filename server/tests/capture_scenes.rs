//! Capture scenes over the fake graph runner: scenes of 3..=N views, the choice of three sources
//! per target, pinning, the volume cache (metrics, graph runs, its byte bound), named scenes
//! (PUT, namespaces, the routing proxy's header) and `POST /v1/captures` with the fixtures of
//! every dataset format. (Bit-identity with `/v1/render` through the real graphs is in
//! tests/tests/parity.rs.)

mod common;

use std::sync::atomic::Ordering;
use std::time::Duration;

use axum::body::Body;
use axum::http::Request;
use axum::Router;
use common::*;
use scnerf_server::bundle::GraphKind;
use scnerf_server::cache::CacheConfig;
use scnerf_server::http::{router, ServiceOptions};
use scnerf_server::request::Limits;
use scnerf_server::testing::{bundle, camera_json, png, state_with_options, FakeRunner};
use serde_json::{json, Value};

/// Views of the ring below: at these angles (radians) around the origin.
const ANGLES: [f64; 8] = [-0.6, -0.4, -0.2, 0.0, 0.2, 0.4, 0.6, 0.8];

struct App {
    router: Router,
    /// Graph runs so far, per graph (`GraphKind::index`).
    calls: std::sync::Arc<[std::sync::atomic::AtomicUsize; GraphKind::ALL.len()]>,
}

impl App {
    fn new(limits: Limits, options: ServiceOptions) -> App {
        let b = bundle("scnerf", "near_far");
        let runner = FakeRunner::new(&b);
        let calls = runner.calls.clone();
        App { router: router(state_with_options(b, runner, limits, options, 8)), calls }
    }

    fn plain() -> App {
        App::new(Limits::default(), ServiceOptions::default())
    }

    fn volumes_built(&self) -> usize {
        self.calls[GraphKind::Volume.index()].load(Ordering::SeqCst)
    }

    async fn metric(&self, name: &str) -> f64 {
        let got = send(self.router.clone(), get("/metrics", &[])).await;
        let text = String::from_utf8_lossy(&got.2).into_owned();
        text.lines()
            .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.trim().parse().ok())
            .unwrap_or_else(|| panic!("no {name} in\n{text}"))
    }
}

/// A scene request of views at `angles` (16x16 sources) and its multipart parts' images.
fn ring_scene(angles: &[f64]) -> (Value, Vec<Vec<u8>>) {
    let sources: Vec<Value> = angles.iter().map(|&a| json!({"camera": camera_json(16, 16, a)})).collect();
    let images = (0..angles.len()).map(|i| png(16, 16, [(20 * i) as u8, 90, 160, 255])).collect();
    (json!({"sources": sources, "near": 2.0, "far": 6.0}), images)
}

fn scene_parts<'a>(json: &'a [u8], images: &'a [Vec<u8>], names: &'a [String]) -> Vec<(&'a str, &'a [u8])> {
    let mut parts: Vec<(&str, &[u8])> = vec![("request", json)];
    parts.extend(names.iter().map(String::as_str).zip(images.iter().map(Vec::as_slice)));
    parts
}

async fn upload(app: &App, method: &str, path: &str, angles: &[f64], headers: &[(&str, &str)]) -> common::Got {
    let (request, images) = ring_scene(angles);
    let json = serde_json::to_vec(&request).unwrap();
    let names: Vec<String> = (0..images.len()).map(|i| format!("source_{i}")).collect();
    let mut req = multipart_to(path, &scene_parts(&json, &images, &names), headers);
    *req.method_mut() = method.parse().unwrap();
    send(app.router.clone(), req).await
}

async fn create(app: &App, angles: &[f64]) -> String {
    let got = upload(app, "POST", "/v1/scenes", angles, &[]).await;
    assert_eq!(got.0, 201, "{}", String::from_utf8_lossy(&got.2));
    json_of(&got)["scene_id"].as_str().unwrap().to_string()
}

/// Renders a 4x4 view from angle `at`; `pinned` views if given. Returns the response.
async fn render(app: &App, id: &str, at: f64, pinned: Option<Value>) -> common::Got {
    let mut body = json!({"target": camera_json(4, 4, at), "outputs": ["rgb"]});
    if let Some(p) = pinned {
        body["sources"] = p;
    }
    send(app.router.clone(), json_to(&format!("/v1/scenes/{id}/render"), &body, &[("accept", "application/json")]))
        .await
}

fn sources_of(got: &common::Got) -> (String, Value) {
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    (got.1["x-scnerf-sources"].to_str().unwrap().to_string(), json_of(got)["sources"].clone())
}

#[tokio::test]
async fn a_capture_renders_from_its_three_nearest_views_nearest_first() {
    let app = App::plain();
    let id = create(&app, &ANGLES).await;
    assert_eq!(app.volumes_built(), 0, "a capture builds volumes per triple, when rendered");
    // Between 0.2 (view 4) and 0.4 (view 5), nearer 0.2; then 0.0 (view 3) before 0.6.
    let (header, body) = sources_of(&render(&app, &id, 0.27, None).await);
    assert_eq!((header.as_str(), body), ("4,5,3", json!([4, 5, 3])));
    let (header, _) = sources_of(&render(&app, &id, -0.55, None).await);
    assert_eq!(header, "0,1,2");
}

#[tokio::test]
async fn a_camera_path_near_the_same_views_builds_one_volume() {
    let app = App::plain();
    let id = create(&app, &ANGLES).await;
    for at in [0.25, 0.26, 0.27, 0.28] {
        assert_eq!(sources_of(&render(&app, &id, at, None).await).0, "4,5,3");
    }
    assert_eq!(app.volumes_built(), 1);
    assert_eq!(app.metric("scnerf_volume_cache_misses_total").await, 1.0);
    assert_eq!(app.metric("scnerf_volume_cache_hits_total").await, 3.0);
    assert_eq!(app.metric("scnerf_volume_cache_entries").await, 1.0);
    // Past the midpoint the reference changes: another volume.
    assert_eq!(sources_of(&render(&app, &id, 0.33, None).await).0, "5,4,6");
    assert_eq!(app.volumes_built(), 2);
    let volume_bytes = app.metric("scnerf_volume_cache_bytes").await;
    assert!(volume_bytes > 0.0 && volume_bytes < app.metric("scnerf_scene_cache_bytes").await);
}

#[tokio::test]
async fn a_three_view_scene_renders_from_its_views_in_upload_order() {
    let app = App::plain();
    let id = create(&app, &ANGLES[..3]).await;
    assert_eq!(app.volumes_built(), 1, "built at creation, as before capture scenes");
    for at in [-0.6, 0.0, 0.7] {
        assert_eq!(sources_of(&render(&app, &id, at, None).await).0, "0,1,2");
    }
    assert_eq!(app.volumes_built(), 1);
    assert_eq!(app.metric("scnerf_volume_cache_hits_total").await, 3.0);
    // Pinned in another order: another reference, another volume.
    assert_eq!(sources_of(&render(&app, &id, 0.0, Some(json!([2, 0, 1]))).await).0, "2,0,1");
    assert_eq!(app.volumes_built(), 2);
}

#[tokio::test]
async fn one_shot_renders_name_their_sources() {
    let app = App::plain();
    let got = send(
        app.router.clone(),
        multipart_with("/v1/render", &scnerf_server::testing::request_json(32), 32, &[("accept", "application/json")]),
    )
    .await;
    let (header, body) = sources_of(&got);
    assert_eq!((header.as_str(), body), ("0,1,2", json!([0, 1, 2])));
}

#[tokio::test]
async fn pinned_sources_are_used_and_bad_ones_named() {
    let app = App::plain();
    let id = create(&app, &ANGLES).await;
    assert_eq!(sources_of(&render(&app, &id, 0.0, Some(json!([7, 0, 4]))).await).0, "7,0,4");
    for (pinned, field) in [
        (json!([0, 1]), "sources"),
        (json!([0, 1, 2, 3]), "sources"),
        (json!([0, 8, 2]), "sources[1]"),
        (json!([3, 1, 3]), "sources[2]"),
    ] {
        assert_error(&render(&app, &id, 0.0, Some(pinned)).await, 422, "invalid_request", Some(field));
    }
    assert_error(&render(&app, &id, 0.0, Some(json!([0, -1, 2]))).await, 400, "malformed_request", Some("sources[1]"));
    assert_error(&render(&app, &id, 0.0, Some(json!("0,1,2"))).await, 400, "malformed_request", Some("sources"));
}

#[tokio::test]
async fn too_few_views_facing_the_target_is_a_422() {
    let app = App::plain();
    let id = create(&app, &ANGLES[..5]).await;
    // At (0, 0, 8) looking along +z, away from the origin that every view of the ring looks at.
    let away = json!({"width": 4, "height": 4, "intrinsics": {"fx": 4.0, "fy": 4.0, "cx": 2.0, "cy": 2.0},
                      "pose": {"matrix": [[-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 8.0], [0.0, 0.0, 0.0, 1.0]],
                               "kind": "camera_to_world", "axes": "opengl"}});
    let body = json!({"target": away, "outputs": ["rgb"]});
    let got = send(app.router.clone(), json_to(&format!("/v1/scenes/{id}/render"), &body, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("target.pose.matrix"));
    // Pinned, the same target renders.
    let pinned = json!({"target": body["target"], "sources": [0, 1, 2]});
    assert_eq!(send(app.router.clone(), json_to(&format!("/v1/scenes/{id}/render"), &pinned, &[])).await.0, 200);
}

#[tokio::test]
async fn scenes_hold_three_to_max_scene_views() {
    let app = App::new(Limits { max_scene_views: 5, ..Limits::default() }, ServiceOptions::default());
    // Too few: 422 naming `sources`.
    assert_error(&upload(&app, "POST", "/v1/scenes", &ANGLES[..2], &[]).await, 422, "invalid_request", Some("sources"));
    // Too many: the part beyond the limit is refused as it arrives, naming it.
    assert_error(
        &upload(&app, "POST", "/v1/scenes", &ANGLES[..6], &[]).await,
        422,
        "invalid_request",
        Some("source_5"),
    );
    // The same in JSON (base64 images) and protobuf: `sources`.
    let (mut request, images) = ring_scene(&ANGLES[..6]);
    for (i, img) in images.iter().enumerate() {
        request["sources"][i]["image"] = json!(b64(img));
    }
    let got = send(app.router.clone(), json_to("/v1/scenes", &request, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("sources"));
    assert_eq!(upload(&app, "POST", "/v1/scenes", &ANGLES[..5], &[]).await.0, 201);
    let model = json_of(&send(app.router.clone(), get("/v1/model", &[])).await);
    assert_eq!(model["max_scene_views"], 5);
}

/// Many triples of one capture with a cache room for the capture and two volumes: the bytes
/// held stay within the bound after every render, and the capture stays.
#[tokio::test]
async fn the_cache_bound_holds_with_many_triples() {
    let probe = App::plain();
    let id = create(&probe, &ANGLES).await;
    let _ = render(&probe, &id, 0.0, None).await;
    let scene = probe.metric("scnerf_scene_cache_bytes").await - probe.metric("scnerf_volume_cache_bytes").await;
    let volume = probe.metric("scnerf_volume_cache_bytes").await;
    let max = (scene + 2.0 * volume) as usize;
    let app = App::new(
        Limits::default(),
        ServiceOptions {
            cache: CacheConfig { max_bytes: max, ttl: Duration::from_secs(60), per_owner_bytes: None },
            ..Default::default()
        },
    );
    let id = create(&app, &ANGLES).await;
    for i in 0..6u32 {
        let got = render(&app, &id, 0.0, Some(json!([i, i + 1, i + 2]))).await;
        assert_eq!(got.0, 200);
        assert!(app.metric("scnerf_scene_cache_bytes").await <= max as f64, "after triple {i}");
    }
    assert_eq!(app.metric("scnerf_volume_cache_entries").await, 2.0);
    assert_eq!(app.metric("scnerf_volume_cache_evictions_total").await, 4.0);
    assert_eq!(app.metric("scnerf_scene_cache_entries").await, 1.0);
    assert_eq!(render(&app, &id, 0.0, None).await.0, 200, "the capture is still there");
}

#[tokio::test]
async fn named_scenes_are_created_replaced_and_private_to_their_token() {
    let app = App { router: two_token_app(), calls: Default::default() };
    let alice = bearer(ALICE);
    let bob = bearer(BOB);
    let put = |token: &str, angles: &'static [f64]| {
        let headers = [("authorization", token.to_string())];
        let app = &app;
        async move {
            let h: Vec<(&str, &str)> = headers.iter().map(|(k, v)| (*k, v.as_str())).collect();
            upload(app, "PUT", "/v1/scenes/lego-1", angles, &h).await
        }
    };
    let got = put(&alice, &ANGLES[..3]).await;
    assert_eq!(got.0, 201, "{}", String::from_utf8_lossy(&got.2));
    assert_eq!(json_of(&got)["scene_id"], "lego-1");
    assert_eq!(got.1["location"], "/v1/scenes/lego-1");
    assert_eq!(put(&alice, &ANGLES).await.0, 200, "replaced");
    assert_eq!(put(&bob, &ANGLES[..4]).await.0, 201, "the same id under another token is another scene");
    let render_as = |token: &str| {
        let body = json!({"target": camera_json(4, 4, 0.27), "outputs": ["rgb"]});
        let auth = token.to_string();
        let router = app.router.clone();
        async move {
            let headers = [("authorization", auth.as_str()), ("accept", "application/json")];
            send(router, json_to("/v1/scenes/lego-1/render", &body, &headers)).await
        }
    };
    assert_eq!(sources_of(&render_as(&alice).await).0, "4,5,3", "Alice's scene is now the 8-view one");
    assert_eq!(sources_of(&render_as(&bob).await).0, "3,2,1", "Bob's has 4 views");
    let del = Request::delete("/v1/scenes/lego-1").header("authorization", &bob).body(Body::empty()).unwrap();
    assert_eq!(send(app.router.clone(), del).await.0, 204);
    assert_error(&render_as(&bob).await, 404, "scene_not_found", Some("scene_id"));
    assert_eq!(render_as(&alice).await.0, 200);
}

#[tokio::test]
async fn a_routing_proxy_names_posted_scenes() {
    let app = App::plain();
    let named = [("x-scnerf-scene-id", "0f1e2d3c4b5a69788796a5b4c3d2e1f0")];
    let got = upload(&app, "POST", "/v1/scenes", &ANGLES[..3], &named).await;
    assert_eq!(got.0, 201);
    assert_eq!(json_of(&got)["scene_id"], "0f1e2d3c4b5a69788796a5b4c3d2e1f0");
    assert_eq!(render(&app, "0f1e2d3c4b5a69788796a5b4c3d2e1f0", 0.0, None).await.0, 200);
    let bad = [("x-scnerf-scene-id", "../x")];
    assert_error(
        &upload(&app, "POST", "/v1/scenes", &ANGLES[..3], &bad).await,
        400,
        "malformed_request",
        Some("x-scnerf-scene-id"),
    );
}

// --- POST /v1/captures

async fn post_capture(app: &App, files: &[(String, Vec<u8>)], query: &str) -> common::Got {
    let parts: Vec<(&str, Option<&str>, &str, &[u8])> = files
        .iter()
        .map(|(name, data)| ("file", Some(name.as_str()), "application/octet-stream", data.as_slice()))
        .collect();
    let (ctype, body) = scnerf_e2e::multipart(&parts);
    send(app.router.clone(), raw_to("POST", &format!("/v1/captures{query}"), &ctype, body, &[])).await
}

#[tokio::test]
async fn captures_of_every_format_become_scenes() {
    let app = App::plain();
    for (folder, format, views) in [
        ("blender", "blender", 5),
        ("nerfstudio", "nerfstudio", 4),
        ("llff", "llff", 4),
        ("colmap", "colmap", 4),
        ("colmap_binary", "colmap", 4),
        ("dtu", "dtu", 4),
    ] {
        let got = post_capture(&app, &files_of(&datasets().join(folder)), "").await;
        assert_eq!(got.0, 201, "{folder}: {}", String::from_utf8_lossy(&got.2));
        let body = json_of(&got);
        assert_eq!(body["format"], format, "{folder}");
        assert_eq!(body["cameras"].as_array().unwrap().len(), views, "{folder}");
        assert_eq!(body["names"].as_array().unwrap().len(), views, "{folder}");
        let expected: Value = serde_json::from_slice(
            &std::fs::read(
                datasets().join(if folder == "colmap_binary" { "colmap" } else { folder }).join("expected.json"),
            )
            .unwrap(),
        )
        .unwrap();
        assert!((body["near"].as_f64().unwrap() - expected["near"].as_f64().unwrap()).abs() < 1e-9, "{folder}");
        let first_image = expected["views"][0]["image"].as_str().unwrap().trim_start_matches("./");
        assert_eq!(body["names"][0], first_image, "{folder}");
        let camera = &body["cameras"][0];
        assert_eq!(
            (camera["pose"]["kind"].as_str(), camera["pose"]["axes"].as_str()),
            (Some("world_to_camera"), Some("opencv"))
        );
        let w2c = &expected["views"][0]["w2c"];
        for r in 0..4 {
            for c in 0..4 {
                let (a, b) = (camera["pose"]["matrix"][r][c].as_f64().unwrap(), w2c[r][c].as_f64().unwrap());
                assert!((a - b).abs() < 1e-9, "{folder}: w2c[{r}][{c}] {a} vs {b}");
            }
        }
        let id = body["scene_id"].as_str().unwrap();
        assert_eq!(got.1["location"], format!("/v1/scenes/{id}").as_str());
        // The fixtures' cameras point anywhere (COLMAP's: only 2 face view 0's way): pinned.
        let target = json!({"target": camera, "outputs": ["rgb"], "sources": [0, 1, 2]});
        let rendered = send(app.router.clone(), json_to(&format!("/v1/scenes/{id}/render"), &target, &[])).await;
        assert_eq!(rendered.0, 200, "{folder}: {}", String::from_utf8_lossy(&rendered.2));
        assert!(rendered.1.contains_key("x-scnerf-sources"));
    }
}

#[tokio::test]
async fn captures_are_thinned_to_max_scene_views() {
    let app = App::new(Limits { max_scene_views: 4, ..Limits::default() }, ServiceOptions::default());
    let got = post_capture(&app, &files_of(&datasets().join("blender")), "").await;
    assert_eq!(got.0, 201, "{}", String::from_utf8_lossy(&got.2));
    let body = json_of(&got);
    assert_eq!(body["cameras"].as_array().unwrap().len(), 4);
    let warnings = body["warnings"].to_string();
    assert!(warnings.contains("the capture has 5 views; the scene keeps 4 of them"), "{warnings}");
}

#[tokio::test]
async fn bad_captures_get_4xx_naming_the_file() {
    let app = App::plain();
    let llff = files_of(&datasets().join("llff"));
    // Images without their poses: nothing tells the format.
    let images: Vec<_> = llff.iter().filter(|(n, _)| n.starts_with("images/")).cloned().collect();
    let got = post_capture(&app, &images, "").await;
    assert_error(&got, 422, "invalid_request", Some("file"));
    assert!(json_of(&got)["error"]["message"].as_str().unwrap().contains("cannot tell the dataset format"));
    // One image short of the poses file.
    let short: Vec<_> = llff.iter().filter(|(n, _)| n != "images/IMG_0003.jpg").cloned().collect();
    assert_error(&post_capture(&app, &short, "").await, 422, "invalid_request", Some("poses_bounds.npy"));
    // Fewer than three images.
    let two: Vec<_> = files_of(&datasets().join("nerfstudio"))
        .into_iter()
        .filter(|(n, _)| !n.ends_with("frame_00001.png") && !n.ends_with("frame_00002.png"))
        .collect();
    let got = post_capture(&app, &two, "").await;
    assert_eq!(got.0, 422, "{}", String::from_utf8_lossy(&got.2));
    assert!(json_of(&got)["error"]["message"].as_str().unwrap().contains("a capture needs at least 3"));
    // Distortion the lens model cannot invert over the image, and the same used as pinhole.
    let mut distorted = files_of(&datasets().join("nerfstudio"));
    let transforms = distorted.iter_mut().find(|(n, _)| n == "transforms.json").unwrap();
    let mut data: Value = serde_json::from_slice(&transforms.1).unwrap();
    data["k1"] = json!(-40.0);
    transforms.1 = serde_json::to_vec(&data).unwrap();
    let got = post_capture(&app, &distorted, "").await;
    assert_error(&got, 422, "invalid_request", Some("transforms.json"));
    assert!(json_of(&got)["error"]["message"].as_str().unwrap().contains("cannot be inverted"), "{got:?}");
    assert_eq!(post_capture(&app, &distorted, "?ignore_distortion=true").await.0, 201);
    for bad in ["?ignore_distortion=maybe", "?undistort_to=sideways"] {
        assert_error(&post_capture(&app, &distorted, bad).await, 400, "malformed_request", Some("query"));
    }
    // An image whose size differs from the others: the scene refuses it, naming the file.
    let mut mixed = files_of(&datasets().join("blender"));
    mixed.iter_mut().find(|(n, _)| n == "train/r_1.png").unwrap().1 = png(16, 12, [0, 0, 0, 255]);
    let got = post_capture(&app, &mixed, "").await;
    assert_error(&got, 422, "invalid_request", Some("train/r_1.png"));
    // Multipart mistakes: 400 naming the part.
    let (ctype, body) = scnerf_e2e::multipart(&[("request", None, "application/json", b"{}")]);
    let got = send(app.router.clone(), raw_to("POST", "/v1/captures", &ctype, body, &[])).await;
    assert_error(&got, 400, "malformed_request", Some("request"));
    let twice = vec![("a.json".to_string(), b"{}".to_vec()), ("./a.json".to_string(), b"{}".to_vec())];
    assert_error(&post_capture(&app, &twice, "").await, 400, "malformed_request", Some("./a.json"));
    assert_error(&post_capture(&app, &[], "").await, 422, "invalid_request", Some("file"));
    let got = send(app.router.clone(), json_to("/v1/captures", &json!({}), &[])).await;
    assert_error(&got, 415, "unsupported_media_type", Some("content-type"));
}

#[tokio::test]
async fn captures_have_their_own_body_limit() {
    let app = App::new(Limits { max_capture_bytes: 64 << 10, ..Limits::default() }, ServiceOptions::default());
    let mut files = files_of(&datasets().join("blender"));
    files.push(("big.bin".into(), vec![7; 100 << 10]));
    assert_error(&post_capture(&app, &files, "").await, 413, "payload_too_large", Some("body"));
    // The other routes keep theirs (64 MiB by default): the same files fit a capture under it.
    let small = App::new(Limits { max_body_bytes: 64 << 10, ..Limits::default() }, ServiceOptions::default());
    assert_eq!(post_capture(&small, &files_of(&datasets().join("blender")), "").await.0, 201);
}

/// An LLFF capture as distributed: `images/` (8x6) and `images_2/` (4x3) beside it.
fn llff_with_two_sets() -> Vec<(String, Vec<u8>)> {
    let mut files = files_of(&datasets().join("llff"));
    files.extend((0..4).map(|i| (format!("images_2/IMG_000{i}.png"), png(4, 3, [40 * i as u8, 90, 160, 255]))));
    files
}

/// The limits clients read before uploading, and the image set `POST /v1/captures` reads: the
/// largest within `max_source_pixels`, or the one `downscale` names; the others are named as not
/// read, and a capture none of whose sets fits is refused naming them.
#[tokio::test]
async fn captures_read_the_largest_image_set_within_the_limit() {
    let limits = Limits { max_source_pixels: 47, max_scene_views: 6, max_capture_bytes: 5 << 20, ..Limits::default() };
    let app = App::new(limits.clone(), ServiceOptions::default());
    let got = json_of(&send(app.router.clone(), get("/v1/limits", &[])).await);
    assert_eq!(
        got,
        json!({"max_source_pixels": 47, "max_target_pixels": limits.max_target_pixels, "max_scene_views": 6,
               "max_body_bytes": limits.max_body_bytes, "max_capture_bytes": 5 << 20,
               "max_json_bytes": limits.max_json_bytes})
    );
    let files = llff_with_two_sets();
    let fitting = json_of(&post_capture(&app, &files, "").await);
    assert_eq!(fitting["image_set"], "images_2", "{fitting}");
    assert_eq!(
        (fitting["cameras"][0]["width"].as_u64(), fitting["names"][0].as_str()),
        (Some(4), Some("images_2/IMG_0000.png"))
    );
    assert!(
        fitting["warnings"].to_string().contains("read the image set images_2 (4x3); not read: images (8x6)"),
        "{fitting}"
    );

    let plain = App::plain();
    let full = json_of(&post_capture(&plain, &files, "").await);
    assert_eq!((full["image_set"].as_str(), full["cameras"][0]["width"].as_u64()), (Some("images"), Some(8)));
    let asked = json_of(&post_capture(&plain, &files, "?downscale=2").await);
    assert_eq!((asked["image_set"].as_str(), asked["cameras"][0]["width"].as_u64()), (Some("images_2"), Some(4)));
    // the focal length scales with the set (LLFF: hwf describes the full-size images)
    let (f_full, f_half) = (
        full["cameras"][0]["intrinsics"]["fx"].as_f64().unwrap(),
        asked["cameras"][0]["intrinsics"]["fx"].as_f64().unwrap(),
    );
    assert_eq!(f_half, f_full / 2.0);
    let got = post_capture(&plain, &files, "?downscale=8").await;
    assert_error(&got, 422, "invalid_request", Some("downscale"));
    assert!(json_of(&got)["error"]["message"].as_str().unwrap().contains("no images_8 folder"), "{got:?}");
    // The API document's minimum (1) holds: there is no images_0.
    let got = post_capture(&plain, &files, "?downscale=0").await;
    assert_error(&got, 400, "malformed_request", Some("query"));
    assert!(json_of(&got)["error"]["message"].as_str().unwrap().contains("downscale"), "{got:?}");
    // only the set the client chose was sent: that one is read
    let half_only: Vec<_> = files.iter().filter(|(n, _)| !n.starts_with("images/")).cloned().collect();
    assert_eq!(json_of(&post_capture(&plain, &half_only, "").await)["image_set"], "images_2");

    // no set fits: the smallest is resized to fit, as the `scnerf` client does, said in a warning
    let tiny = App::new(Limits { max_source_pixels: 11, ..Limits::default() }, ServiceOptions::default());
    let got = json_of(&post_capture(&tiny, &files, "").await);
    assert_eq!((got["image_set"].as_str(), got["cameras"][0]["width"].as_u64()), (Some("images_2"), Some(3)));
    assert_eq!(got["cameras"][0]["height"].as_u64(), Some(2));
    let note = "4 images of 4x3 exceed the server's limit of 11 pixels per source view: resizing them to 3x2";
    assert!(got["warnings"].to_string().contains(note), "{got}");
}
