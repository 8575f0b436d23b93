//! The scene cache endpoints over the fake graph runner: create, render, delete, errors, eviction
//! by bytes and by TTL. (Bit-identity with one-shot renders through real ONNX Runtime graphs is
//! in tests/tests/parity.rs.)

mod common;

use std::time::Duration;

use axum::body::Body;
use axum::http::Request;
use axum::Router;
use common::*;
use scnerf_server::cache::{CacheConfig, ManualClock};
use scnerf_server::http::{router, ServiceOptions};
use scnerf_server::request::Limits;
use scnerf_server::testing::{bundle, fake_state, request_json, state_with_options, FakeRunner};
use serde_json::{json, Value};

fn app_with_cache(cache: CacheConfig) -> Router {
    app_with(ServiceOptions { cache, ..Default::default() })
}

fn app_with(options: ServiceOptions) -> Router {
    let b = bundle("scnerf", "near_far");
    let runner = FakeRunner::new(&b);
    router(state_with_options(b, runner, Limits::default(), options, 8))
}

/// Bytes of one cached fake scene of 32x32 sources: images 3·3·32·32, features 3·32·8·8 and
/// volume 8·8·12·12 floats (fake bundle: 8 planes, pad 2).
const SCENE_BYTES: usize = 4 * (9216 + 6144 + 9216);

async fn create(app: &Router, size: u32) -> String {
    let got = send(app.clone(), multipart_with("/v1/scenes", &scene_json(size), size, &[])).await;
    assert_eq!(got.0, 201, "{}", String::from_utf8_lossy(&got.2));
    let v = json_of(&got);
    let id = v["scene_id"].as_str().unwrap().to_string();
    assert_eq!(got.1["location"], format!("/v1/scenes/{id}").as_str());
    id
}

fn render_req(id: &str, body: &Value, accept: Option<&str>) -> Request<Body> {
    let headers: Vec<(&str, &str)> = accept.map(|a| ("accept", a)).into_iter().collect();
    json_to(&format!("/v1/scenes/{id}/render"), body, &headers)
}

#[tokio::test]
async fn create_render_delete() {
    let app = router(fake_state());
    let got = send(app.clone(), multipart_with("/v1/scenes", &scene_json(32), 32, &[])).await;
    assert_eq!(got.0, 201, "{}", String::from_utf8_lossy(&got.2));
    assert_eq!(got.1["content-type"], "application/json");
    assert!(got.1["server-timing"].to_str().unwrap().contains("volume;dur="));
    let v = json_of(&got);
    let id = v["scene_id"].as_str().unwrap();
    assert_eq!(id.len(), 32);
    let expires = v["expires_at"].as_str().unwrap();
    assert!(expires.ends_with('Z') && expires.contains('T'), "{expires}");

    let got = send(app.clone(), render_req(id, &target_json(32), None)).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    assert_eq!(got.1["content-type"], "image/png");
    assert!(got.1.contains_key("x-scene-expires-at"));
    let timing = got.1["server-timing"].to_str().unwrap();
    assert!(timing.contains("renderer;dur=") && !timing.contains("volume"), "cached: renderer only: {timing}");
    let img = image::load_from_memory(&got.2).unwrap();
    assert_eq!((img.width(), img.height()), (8, 6));

    let del = Request::delete(format!("/v1/scenes/{id}")).body(Body::empty()).unwrap();
    assert_eq!(send(app.clone(), del).await.0, 204);
    assert_error(
        &send(app.clone(), render_req(id, &target_json(32), None)).await,
        404,
        "scene_not_found",
        Some("scene_id"),
    );
    let del = Request::delete(format!("/v1/scenes/{id}")).body(Body::empty()).unwrap();
    assert_error(&send(app, del).await, 404, "scene_not_found", Some("scene_id"));
}

/// Every body form of /v1/render works for /v1/scenes, and all of them give the pixels of the
/// one-shot render of the same request, in every response format.
#[tokio::test]
async fn cached_views_equal_one_shot_views_in_every_format() {
    let app = router(fake_state());
    let mut full = request_json(32);
    full["outputs"] = json!(["rgb", "depth", "opacity"]);
    let one_shot = send(app.clone(), multipart_with("/v1/render", &full, 32, &[("accept", "application/json")])).await;
    assert_eq!(one_shot.0, 200);
    let one_shot = json_of(&one_shot);

    let mut scene = json_with_images(32);
    scene.as_object_mut().unwrap().remove("target");
    scene.as_object_mut().unwrap().remove("outputs");
    let got = send(app.clone(), json_to("/v1/scenes", &scene, &[])).await;
    assert_eq!(got.0, 201, "{}", String::from_utf8_lossy(&got.2));
    let id = json_of(&got)["scene_id"].as_str().unwrap().to_string();
    let view = json!({"target": full["target"], "outputs": full["outputs"]});
    let cached = json_of(&send(app.clone(), render_req(&id, &view, Some("application/json"))).await);
    for key in ["width", "height", "model_id", "rgb", "depth", "opacity"] {
        assert_eq!(cached[key], one_shot[key], "{key}");
    }
    // Default Accept with rgb only: the PNG bytes of the one-shot render.
    let png_one_shot = send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[])).await.2;
    let png_cached = send(app.clone(), render_req(&id, &target_json(32), None)).await.2;
    assert_eq!(png_cached, png_one_shot);
}

#[tokio::test]
async fn protobuf_scene_and_protobuf_view() {
    use prost::Message;
    use scnerf_proto::v1 as pb;
    let app = router(fake_state());
    let id = create(&app, 32).await;
    let view = pb::SceneRenderRequest {
        target: Some(pb::Camera {
            width: 4,
            height: 4,
            intrinsics_kind: Some(pb::camera::IntrinsicsKind::Intrinsics(pb::Intrinsics {
                fx: 4.0,
                fy: 4.0,
                cx: 2.0,
                cy: 2.0,
            })),
            pose: Some(pb::Pose {
                matrix: vec![1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 4., 0., 0., 0., 1.],
                kind: pb::PoseKind::WorldToCamera as i32,
                axes: pb::Axes::Opencv as i32,
            }),
        }),
        outputs: vec!["depth".into()],
        sources: vec![2, 0, 1],
        ..Default::default()
    };
    let req = raw_to(
        "POST",
        &format!("/v1/scenes/{id}/render"),
        "application/x-protobuf",
        view.encode_to_vec(),
        &[("accept", "application/x-protobuf")],
    );
    let got = send(app, req).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    assert_eq!(got.1["x-scnerf-sources"], "2,0,1");
    let resp = pb::RenderResponse::decode(got.2).unwrap();
    assert_eq!((resp.width, resp.height), (4, 4));
    assert_eq!(resp.sources, vec![2, 0, 1], "pinned: another reference");
    assert_eq!(resp.depth.unwrap().data.len(), 4 * 4 * 4);
    assert!(resp.rgb_png.is_empty());
}

#[tokio::test]
async fn scene_request_errors_name_the_field() {
    let app = router(fake_state());
    // A target belongs to the render call, not to the scene.
    let mut with_target = scene_json(32);
    with_target["target"] = request_json(32)["target"].clone();
    let got = send(app.clone(), multipart_with("/v1/scenes", &with_target, 32, &[])).await;
    assert_error(&got, 400, "malformed_request", Some("target"));
    let mut two_views = json_with_images(32);
    two_views.as_object_mut().unwrap().retain(|k, _| k != "target" && k != "outputs");
    two_views["sources"].as_array_mut().unwrap().pop();
    let got = send(app.clone(), json_to("/v1/scenes", &two_views, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("sources"));
    let mut bad_far = scene_json(32);
    bad_far["far"] = json!(1.0);
    let got = send(app.clone(), multipart_with("/v1/scenes", &bad_far, 32, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("far"));

    let id = create(&app, 32).await;
    let path = format!("/v1/scenes/{id}/render");
    let got = send(app.clone(), json_to(&path, &json!({"outputs": ["rgb"]}), &[])).await;
    assert_error(&got, 400, "malformed_request", Some("target"));
    let got = send(app.clone(), json_to(&path, &json!({"target": request_json(32)["target"], "near": 1}), &[])).await;
    assert_error(&got, 400, "malformed_request", Some("near"));
    let huge = serde_json::to_string(&target_json(32)).unwrap().replacen("\"matrix\":[[", "\"matrix\":[[1e400,", 1);
    let got = send(app.clone(), raw_to("POST", &path, "application/json", huge.into_bytes(), &[])).await;
    assert_error(&got, 400, "malformed_request", Some("target.pose.matrix[0][0]"));
    let got = send(app.clone(), multipart_to(&path, &[("request", b"{}")], &[])).await;
    assert_error(&got, 415, "unsupported_media_type", Some("content-type"));
    let got = send(app.clone(), render_req(&id, &target_json(32), Some("text/html"))).await;
    assert_error(&got, 406, "not_acceptable", Some("accept"));
}

#[tokio::test]
async fn bad_and_unknown_scene_ids() {
    let app = router(fake_state());
    let unknown = "0123456789abcdef0123456789abcdef";
    for id in [unknown, "xyz", "My-Scene_1.v2"] {
        let got = send(app.clone(), render_req(id, &target_json(32), None)).await;
        assert_error(&got, 404, "scene_not_found", Some("scene_id"));
        assert_eq!(json_of(&got)["error"]["hint"], "reupload", "a machine-readable hint to upload again");
    }
    let too_long = "a".repeat(65);
    for bad in ["a%20b", "%2e%2e", "caf%C3%A9", too_long.as_str()] {
        let got = send(app.clone(), render_req(bad, &target_json(32), None)).await;
        assert_error(&got, 400, "malformed_request", Some("scene_id"));
    }
    let got = send(app.clone(), get(&format!("/v1/scenes/{unknown}"), &[])).await;
    assert_error(&got, 405, "method_not_allowed", Some("method"));
}

#[tokio::test]
async fn least_recently_used_scene_is_evicted_by_bytes() {
    // Room for two scenes, not three.
    let app = app_with_cache(CacheConfig {
        max_bytes: 2 * SCENE_BYTES + SCENE_BYTES / 2,
        ttl: Duration::from_secs(60),
        per_owner_bytes: None,
    });
    let a = create(&app, 32).await;
    let b = create(&app, 32).await;
    assert_eq!(send(app.clone(), render_req(&a, &target_json(32), None)).await.0, 200); // a: recent
    let c = create(&app, 32).await;
    assert_error(
        &send(app.clone(), render_req(&b, &target_json(32), None)).await,
        404,
        "scene_not_found",
        Some("scene_id"),
    );
    for id in [&a, &c] {
        assert_eq!(send(app.clone(), render_req(id, &target_json(32), None)).await.0, 200);
    }
}

#[tokio::test]
async fn a_scene_larger_than_the_cache_is_refused() {
    let app =
        app_with_cache(CacheConfig { max_bytes: SCENE_BYTES - 1, ttl: Duration::from_secs(60), per_owner_bytes: None });
    let got = send(app, multipart_with("/v1/scenes", &scene_json(32), 32, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("sources"));
}

#[tokio::test]
async fn idle_scenes_expire_and_renders_extend_their_life() {
    let (clock, time) = ManualClock::new();
    let cache = CacheConfig { max_bytes: 1 << 30, ttl: Duration::from_secs(600), per_owner_bytes: None };
    let app = app_with(ServiceOptions { cache, clock: time, ..Default::default() });
    let kept = create(&app, 32).await;
    let idle = create(&app, 32).await;
    for _ in 0..3 {
        clock.advance(Duration::from_secs(300));
        assert_eq!(send(app.clone(), render_req(&kept, &target_json(32), None)).await.0, 200);
    }
    // 900 s after creation: `idle` is gone, `kept` was used 300 s ago.
    assert_error(
        &send(app.clone(), render_req(&idle, &target_json(32), None)).await,
        404,
        "scene_not_found",
        Some("scene_id"),
    );
    clock.advance(Duration::from_secs(599));
    assert_eq!(send(app.clone(), render_req(&kept, &target_json(32), None)).await.0, 200);
    clock.advance(Duration::from_secs(600));
    assert_error(&send(app, render_req(&kept, &target_json(32), None)).await, 404, "scene_not_found", Some("scene_id"));
}

async fn create_as(app: &Router, token: &str) -> String {
    let got =
        send(app.clone(), multipart_with("/v1/scenes", &scene_json(32), 32, &[("authorization", &bearer(token))]))
            .await;
    assert_eq!(got.0, 201, "{}", String::from_utf8_lossy(&got.2));
    json_of(&got)["scene_id"].as_str().unwrap().to_string()
}

async fn render_as(app: &Router, id: &str, token: &str) -> u16 {
    let req = json_to(&format!("/v1/scenes/{id}/render"), &target_json(32), &[("authorization", &bearer(token))]);
    send(app.clone(), req).await.0.as_u16()
}

/// The probe's sequence over HTTP: with two tokens and room for six scenes (an equal share of
/// three each), token B caches three scenes and renders them; token A then uploads five. B's
/// scenes all still render: A made room from its own.
#[tokio::test]
async fn one_token_cannot_empty_another_token_s_scenes() {
    let b = bundle("scnerf", "near_far");
    let runner = FakeRunner::new(&b);
    let cache = CacheConfig { max_bytes: 6 * SCENE_BYTES + SCENE_BYTES / 2, ..Default::default() };
    let auth = scnerf_server::auth::Auth::from_tokens(&[ALICE, BOB]);
    let app = router(state_with_options(
        b,
        runner,
        Limits::default(),
        ServiceOptions { cache, auth, ..Default::default() },
        8,
    ));
    let mut bobs = Vec::new();
    for _ in 0..3 {
        let id = create_as(&app, BOB).await;
        assert_eq!(render_as(&app, &id, BOB).await, 200);
        bobs.push(id);
    }
    let mut alices = Vec::new();
    for _ in 0..5 {
        alices.push(create_as(&app, ALICE).await);
    }
    for id in &bobs {
        assert_eq!(render_as(&app, id, BOB).await, 200, "Bob's scenes stay");
    }
    let mut kept = Vec::new();
    for id in &alices {
        kept.push(render_as(&app, id, ALICE).await);
    }
    assert_eq!(kept, [404, 404, 200, 200, 200], "Alice keeps her share: her three latest");
}
