//! Handler tests: the real router driven with `tower::ServiceExt::oneshot`, over a fake graph
//! runner (no ONNX Runtime needed). Every error path of the API has a test here; numerical
//! parity with real graphs is in tests/tests/parity.rs.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::body::Body;
use axum::http::Request;
use axum::Router;
use base64::Engine;
use nalgebra::{Matrix3, Matrix4, Vector3, Vector4};
use prost::Message;
use scnerf_proto::v1 as pb;
use scnerf_server::bundle::GraphKind;
use scnerf_server::http::router;
use scnerf_server::request::Limits;
use scnerf_server::testing::{
    self, bundle, camera_json, fake_state, png, request_json, state_with, FakeRunner, RendererCameras,
};
use serde_json::{json, Value};

mod common;
use common::*;

fn app() -> Router {
    router(fake_state())
}

/// What the fake renderers were fed, run by run.
type Fed = Arc<Mutex<Vec<RendererCameras>>>;

/// The app over a fake runner of `variant` and `norm`, and the cameras its renderers are fed.
fn recording_app(variant: &str, norm: &str) -> (Router, Fed) {
    let b = bundle(variant, norm);
    let runner = FakeRunner::new(&b);
    let fed = runner.renderer_cameras.clone();
    (router(state_with(b, runner, Limits::default(), Duration::from_secs(60))), fed)
}

/// A request's camera in the canonical form, from the conventions' definitions (docs/api.md):
/// K from `intrinsics` (`{fx, fy, cx, cy}` or rows) or `K`; world-to-camera = the pose matrix, or
/// its inverse when it is camera-to-world, with the camera's y and z flipped when its axes are
/// OpenGL's (y up, z back) rather than OpenCV's.
fn canonical(camera: &Value) -> (Matrix3<f64>, Matrix4<f64>) {
    let f = |v: &Value| v.as_f64().unwrap_or_else(|| panic!("a number: {v}"));
    let k = match camera.get("K").or_else(|| camera.get("intrinsics").filter(|i| i.is_array())) {
        Some(rows) => Matrix3::from_fn(|r, c| f(&rows[r][c])),
        None => {
            let i = &camera["intrinsics"];
            Matrix3::new(f(&i["fx"]), 0.0, f(&i["cx"]), 0.0, f(&i["fy"]), f(&i["cy"]), 0.0, 0.0, 1.0)
        }
    };
    let pose = &camera["pose"];
    let m = Matrix4::from_fn(|r, c| f(&pose["matrix"][r][c]));
    let w2c = if pose["kind"] == "camera_to_world" { m.try_inverse().unwrap() } else { m };
    let flip = if pose["axes"] == "opengl" { Vector4::new(1.0, -1.0, -1.0, 1.0) } else { Vector4::repeat(1.0) };
    (k, Matrix4::from_diagonal(&flip) * w2c)
}

fn assert_close(got: f32, want: f64, what: &str) {
    assert!((f64::from(got) - want).abs() <= 1e-5 * want.abs().max(1.0), "{what}: {got} vs {want}");
}

/// Every renderer run was fed the request's sources in canonical form, in the request's order
/// (`intrinsics`, `extrinsics`), and the rays of its target: from its centre, through each pixel
/// centre in row order. `passes`: the runs expected (a target of at most 100 pixels is one run per
/// pass with the test state's chunks).
fn assert_fed_the_cameras(fed: &Fed, request: &Value, passes: usize) {
    let runs = fed.lock().unwrap();
    assert_eq!(runs.len(), passes, "renderer runs");
    let sources: Vec<_> = request["sources"].as_array().unwrap().iter().map(|s| canonical(&s["camera"])).collect();
    let target = &request["target"];
    let (k, w2c) = canonical(target);
    let c2w = w2c.try_inverse().unwrap();
    let (width, height) = (target["width"].as_u64().unwrap() as usize, target["height"].as_u64().unwrap() as usize);
    for run in runs.iter() {
        assert_eq!(run.intrinsics.shape(), [sources.len(), 3, 3]);
        assert_eq!(run.extrinsics.shape(), [sources.len(), 4, 4]);
        for (v, (sk, sw2c)) in sources.iter().enumerate() {
            for (r, c) in (0..3).flat_map(|r| (0..3).map(move |c| (r, c))) {
                assert_close(run.intrinsics[[v, r, c]], sk[(r, c)], &format!("{:?} source {v} K[{r},{c}]", run.graph));
            }
            for (r, c) in (0..4).flat_map(|r| (0..4).map(move |c| (r, c))) {
                assert_close(
                    run.extrinsics[[v, r, c]],
                    sw2c[(r, c)],
                    &format!("{:?} source {v} w2c[{r},{c}]", run.graph),
                );
            }
        }
        assert_eq!(run.ray_origins.nrows(), width * height, "one run per pass");
        for (i, (origin, direction)) in run.ray_origins.rows().into_iter().zip(run.ray_directions.rows()).enumerate() {
            let (u, v) = ((i % width) as f64, (i / width) as f64);
            let camera_ray = Vector3::new((u - k[(0, 2)]) / k[(0, 0)], (v - k[(1, 2)]) / k[(1, 1)], 1.0);
            let want = c2w.fixed_view::<3, 3>(0, 0) * camera_ray;
            for a in 0..3 {
                assert_close(origin[a], c2w[(a, 3)], &format!("ray {i} origin[{a}]"));
                assert_close(direction[a], want[a], &format!("ray {i} direction[{a}]"));
            }
        }
    }
}

async fn render_multipart_error(request: Value, status: u16, code: &str, field: Option<&str>) {
    let got = send(app(), multipart_with("/v1/render", &request, 32, &[])).await;
    assert_error(&got, status, code, field);
}

// ---------------------------------------------------------------------------------------------
// Success paths

#[tokio::test]
async fn multipart_renders_png_by_default() {
    let (app, fed) = recording_app("scnerf", "near_far");
    let (status, headers, body) = send(app, multipart_with("/v1/render", &request_json(32), 32, &[])).await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    assert_eq!(headers["content-type"], "image/png");
    assert!(headers["x-model-id"].to_str().unwrap().starts_with("scnerf-scnerf-"));
    assert!(headers["server-timing"].to_str().unwrap().contains("renderer;dur="));
    let img = image::load_from_memory(&body).unwrap();
    assert_eq!((img.width(), img.height()), (8, 6));
    assert_fed_the_cameras(&fed, &request_json(32), 1);
}

#[tokio::test]
async fn json_body_and_json_response_with_all_outputs() {
    let mut req = json_with_images(40); // not a multiple of 32: padded
    req["outputs"] = json!(["rgb", "depth", "opacity"]);
    let (app, fed) = recording_app("scnerf", "near_far");
    let (status, headers, body) = send(app, json_to("/v1/render", &req, &[("accept", "application/json")])).await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    assert_eq!(headers["content-type"], "application/json");
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!((v["width"].as_u64(), v["height"].as_u64()), (Some(8), Some(6)));
    assert!(v["model_id"].as_str().unwrap().starts_with("scnerf-"));
    let b64 = |v: &Value| base64::engine::general_purpose::STANDARD.decode(v.as_str().unwrap()).unwrap();
    let png = image::load_from_memory(&b64(&v["rgb"]["data"])).unwrap();
    assert_eq!((png.width(), png.height()), (8, 6));
    let depth = b64(&v["depth"]["data"]);
    assert_eq!(depth.len(), 8 * 6 * 4);
    assert_eq!(v["depth"]["dtype"], "float32");
    let opacity: Vec<f32> =
        b64(&v["opacity"]["data"]).chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
    assert!(opacity.iter().all(|o| (0.5..=1.0).contains(o)));
    for stage in ["decode", "encoder", "volume", "renderer", "assemble", "encode", "total"] {
        assert!(v["timings_ms"][stage].as_f64().is_some(), "missing timing {stage}");
    }
    // Sources padded to the image multiple (40 -> 64) keep their K.
    assert_fed_the_cameras(&fed, &req, 1);
}

#[tokio::test]
async fn depth_only_defaults_to_json() {
    let mut req = request_json(32);
    req["outputs"] = json!(["depth"]);
    let (status, headers, body) = send(app(), multipart_with("/v1/render", &req, 32, &[])).await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    assert_eq!(headers["content-type"], "application/json");
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert!(v.get("rgb").is_none() && v.get("opacity").is_none() && v["depth"].is_object());
}

/// `request_json(32)` as protobuf, asking for rgb and depth.
fn proto_render() -> pb::RenderRequest {
    let outputs = vec!["rgb".into(), "depth".into()];
    pb::RenderRequest { outputs, ..proto_request(&request_json(32), &images(32)) }
}

fn proto_req(msg: &pb::RenderRequest) -> Request<Body> {
    let accept = [("accept", "application/x-protobuf")];
    raw_to("POST", "/v1/render", "application/x-protobuf", msg.encode_to_vec(), &accept)
}

#[tokio::test]
async fn protobuf_in_protobuf_out_matches_multipart() {
    let (recording, fed) = recording_app("scnerf", "near_far");
    let (status, headers, body) = send(recording, proto_req(&proto_render())).await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    assert_eq!(headers["content-type"], "application/x-protobuf");
    let resp = pb::RenderResponse::decode(body).unwrap();
    assert_eq!((resp.width, resp.height), (8, 6));
    assert_eq!(resp.depth.as_ref().unwrap().data.len(), 8 * 6 * 4);
    assert!(resp.opacity.is_none());
    assert!(resp.timings_ms.contains_key("renderer"));
    assert_fed_the_cameras(&fed, &request_json(32), 1);
    // Same request as multipart: same pixels.
    let (_, _, png_body) = send(app(), multipart_with("/v1/render", &request_json(32), 32, &[])).await;
    assert_eq!(resp.rgb_png, png_body.to_vec());
}

#[tokio::test]
async fn k_matrix_and_opencv_world_to_camera_are_accepted() {
    let mut req = request_json(32);
    req["target"] = json!({
        "width": 4, "height": 4, "K": [[4.0, 0.0, 2.0], [0.0, 4.0, 2.0], [0.0, 0.0, 1.0]],
        "pose": {"matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]], "kind": "world_to_camera", "axes": "opencv"}
    });
    // And a source in the same form: its K and pose reach the renderer as they are.
    req["sources"][1]["camera"] = json!({
        "width": 32, "height": 32, "K": [[30.0, 0.0, 15.5], [0.0, 31.0, 16.0], [0.0, 0.0, 1.0]],
        "pose": {"matrix": [[0, 0, -1, 0.5], [0, 1, 0, 0], [1, 0, 0, 4], [0, 0, 0, 1]], "kind": "world_to_camera", "axes": "opencv"}
    });
    let (app, fed) = recording_app("scnerf", "near_far");
    let (status, _, body) = send(app, multipart_with("/v1/render", &req, 32, &[])).await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    assert_fed_the_cameras(&fed, &req, 1);
}

#[tokio::test]
async fn other_variants_and_two_pass_depth_norm() {
    for (variant, norm, passes) in [("mvsnerf", "near_far", 1), ("scnerf-geometry", "image_minmax", 2)] {
        let (app, fed) = recording_app(variant, norm);
        let (status, _, body) = send(app, multipart_with("/v1/render", &request_json(32), 32, &[])).await;
        assert_eq!(status, 200, "{variant}: {}", String::from_utf8_lossy(&body));
        assert_fed_the_cameras(&fed, &request_json(32), passes);
    }
}

/// image_minmax renders a view twice (the depth image, then the colours fed its range) only when
/// the renderer takes that range; the rule has one home (pipeline::DepthRange).
#[tokio::test]
async fn two_renderer_passes_only_when_the_renderer_takes_the_depth_range() {
    for (variant, norm, passes) in
        [("scnerf-geometry", "image_minmax", 2), ("mvsnerf", "image_minmax", 1), ("scnerf", "near_far", 1)]
    {
        let b = bundle(variant, norm);
        let runner = FakeRunner::new(&b);
        let calls = runner.calls.clone();
        let app = router(state_with(b, runner, Limits::default(), Duration::from_secs(60)));
        // 8x6 rays: one renderer run per pass.
        let (status, _, body) = send(app, multipart_with("/v1/render", &request_json(32), 32, &[])).await;
        assert_eq!(status, 200, "{variant}: {}", String::from_utf8_lossy(&body));
        assert_eq!(
            calls[GraphKind::Renderer.index()].load(std::sync::atomic::Ordering::SeqCst),
            passes,
            "{variant}, {norm}"
        );
    }
}

#[tokio::test]
async fn model_health_and_readiness() {
    let (status, _, body) = send(app(), Request::get("/v1/model").body(Body::empty()).unwrap()).await;
    assert_eq!(status, 200);
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(v["variant"], "scnerf");
    assert_eq!(v["config"]["views"], 3);
    assert_eq!(v["config"]["mlp_width"], 128, "extra config keys are served as is");
    assert_eq!(v["provenance"]["source_checkpoint"], "fake");
    assert!(v["model_id"].as_str().unwrap().starts_with("scnerf-scnerf-"));
    for path in ["/healthz", "/readyz"] {
        let (status, _, _) = send(app(), Request::get(path).body(Body::empty()).unwrap()).await;
        assert_eq!(status, 200, "{path}");
    }
}

// ---------------------------------------------------------------------------------------------
// Service state errors

#[tokio::test]
async fn not_ready_is_503_with_retry_after_but_alive() {
    let state = fake_state();
    state.set_draining();
    let app = router(state);
    let got = send(app.clone(), Request::get("/readyz").body(Body::empty()).unwrap()).await;
    assert_error(&got, 503, "unavailable", None);
    assert!(got.1.contains_key("retry-after"));
    let got = send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[])).await;
    assert_error(&got, 503, "unavailable", None);
    let (status, _, _) = send(app, Request::get("/healthz").body(Body::empty()).unwrap()).await;
    assert_eq!(status, 200);
}

#[tokio::test]
async fn deadline_is_504() {
    let b = testing::bundle("scnerf", "near_far");
    let mut runner = FakeRunner::new(&b);
    runner.delay = Duration::from_millis(300);
    let app = router(state_with(b, runner, Limits::default(), Duration::from_millis(100)));
    assert_error(
        &send(app, multipart_with("/v1/render", &request_json(32), 32, &[])).await,
        504,
        "deadline_exceeded",
        None,
    );
}

#[tokio::test]
async fn backend_failure_is_500_and_the_server_keeps_serving() {
    let b = testing::bundle("scnerf", "near_far");
    let mut runner = FakeRunner::new(&b);
    runner.fail_with = Some("boom".into());
    let app = router(state_with(b, runner, Limits::default(), Duration::from_secs(10)));
    assert_error(
        &send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[])).await,
        500,
        "internal",
        None,
    );
    let (status, _, _) = send(app, Request::get("/healthz").body(Body::empty()).unwrap()).await;
    assert_eq!(status, 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_queue_is_503_with_retry_after() {
    let b = testing::bundle("scnerf", "near_far");
    let mut runner = FakeRunner::new(&b);
    runner.delay = Duration::from_millis(400);
    let app = router(testing::state_with_queue(b, runner, Limits::default(), Duration::from_secs(60), 1));
    let tasks: Vec<_> = (0..6)
        .map(|_| tokio::spawn(send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[]))))
        .collect();
    let mut busy = 0;
    for t in tasks {
        let got = t.await.unwrap();
        if got.0 == 503 {
            assert_error(&got, 503, "unavailable", None);
            assert!(got.1.contains_key("retry-after"));
            busy += 1;
        } else {
            assert_eq!(got.0, 200);
        }
    }
    assert!(busy > 0, "six concurrent requests on a queue of one: some must be refused");
}

#[tokio::test]
async fn unknown_route_and_wrong_method() {
    assert_error(
        &send(app(), Request::get("/v2/render").body(Body::empty()).unwrap()).await,
        404,
        "not_found",
        Some("path"),
    );
    assert_error(
        &send(app(), Request::get("/v1/render").body(Body::empty()).unwrap()).await,
        405,
        "method_not_allowed",
        Some("method"),
    );
}

// ---------------------------------------------------------------------------------------------
// Media types and negotiation

#[tokio::test]
async fn content_type_errors_are_415() {
    let no_ct = Request::post("/v1/render").body(Body::from("{}")).unwrap();
    assert_error(&send(app(), no_ct).await, 415, "unsupported_media_type", Some("content-type"));
    let text = Request::post("/v1/render").header("content-type", "text/plain").body(Body::from("{}")).unwrap();
    assert_error(&send(app(), text).await, 415, "unsupported_media_type", Some("content-type"));
}

#[tokio::test]
async fn accept_errors() {
    assert_error(
        &send(app(), multipart_with("/v1/render", &request_json(32), 32, &[("accept", "text/html")])).await,
        406,
        "not_acceptable",
        Some("accept"),
    );
    let mut req = request_json(32);
    req["outputs"] = json!(["rgb", "depth"]);
    assert_error(
        &send(app(), multipart_with("/v1/render", &req, 32, &[("accept", "image/png")])).await,
        422,
        "invalid_request",
        Some("outputs"),
    );
}

// ---------------------------------------------------------------------------------------------
// Malformed bodies (400)

#[tokio::test]
async fn json_syntax_error() {
    let req = Request::post("/v1/render")
        .header("content-type", "application/json")
        .body(Body::from("{\"sources\": ["))
        .unwrap();
    assert_error(&send(app(), req).await, 400, "malformed_request", Some("sources"));
    let req =
        Request::post("/v1/render").header("content-type", "application/json").body(Body::from("not json")).unwrap();
    assert_error(&send(app(), req).await, 400, "malformed_request", Some("body"));
}

#[tokio::test]
async fn unknown_fields_are_named() {
    let mut req = request_json(32);
    req["sources"][1]["camera"]["pose"]["extra"] = json!(1);
    render_multipart_error(req, 400, "malformed_request", Some("sources[1].camera.pose.extra")).await;
    let mut req = request_json(32);
    req["seed"] = json!(1);
    render_multipart_error(req, 400, "malformed_request", Some("seed")).await;
    let mut req = request_json(32);
    req["target"]["intrinsics"]["skew"] = json!(0);
    render_multipart_error(req, 400, "malformed_request", Some("target.intrinsics.skew")).await;
}

#[tokio::test]
async fn missing_and_mistyped_fields_are_named() {
    let mut req = request_json(32);
    req.as_object_mut().unwrap().remove("near");
    let got = send(app(), multipart_with("/v1/render", &req, 32, &[])).await;
    assert_error(&got, 400, "malformed_request", Some("near"));
    let mut req = request_json(32);
    req["sources"][2]["camera"]["pose"].as_object_mut().unwrap().remove("axes");
    render_multipart_error(req, 400, "malformed_request", Some("sources[2].camera.pose.axes")).await;
    let mut req = request_json(32);
    req["target"]["pose"]["kind"] = json!("camera_to_sky");
    render_multipart_error(req, 400, "malformed_request", Some("target.pose.kind")).await;
    let mut req = request_json(32);
    req["sources"][0]["camera"]["width"] = json!(-5);
    render_multipart_error(req, 400, "malformed_request", Some("sources[0].camera.width")).await;
    let mut req = request_json(32);
    req["target"]["pose"]["matrix"] = json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]]);
    render_multipart_error(req, 400, "malformed_request", Some("target.pose.matrix[0]")).await;
    let mut req = request_json(32);
    req["outputs"] = json!(["rgb", "normals"]);
    render_multipart_error(req, 400, "malformed_request", Some("outputs[1]")).await;
    let mut req = request_json(32);
    req["target"].as_object_mut().unwrap().remove("intrinsics");
    render_multipart_error(req, 400, "malformed_request", Some("target.intrinsics")).await;
    let mut req = request_json(32);
    req["target"]["K"] = json!([[8.0, 0.0, 4.0], [0.0, 8.0, 3.0], [0.0, 0.0, 1.0]]);
    render_multipart_error(req, 400, "malformed_request", Some("target.K")).await;
}

#[tokio::test]
async fn json_body_image_errors() {
    let mut req = json_with_images(32);
    req["sources"][2]["image"] = json!("not base64 !!!");
    assert_error(
        &send(app(), json_to("/v1/render", &req, &[])).await,
        400,
        "malformed_request",
        Some("sources[2].image"),
    );
    let mut req = json_with_images(32);
    req["sources"][1].as_object_mut().unwrap().remove("image");
    assert_error(
        &send(app(), json_to("/v1/render", &req, &[])).await,
        400,
        "malformed_request",
        Some("sources[1].image"),
    );
}

#[tokio::test]
async fn multipart_structure_errors() {
    let json = serde_json::to_vec(&request_json(32)).unwrap();
    let imgs = images(32);
    type Parts<'a> = Vec<(&'a str, &'a [u8])>;
    let cases: Vec<(Parts, &str)> = vec![
        (vec![("source_0", &imgs[0]), ("source_1", &imgs[1]), ("source_2", &imgs[2])], "request"),
        (vec![("request", &json), ("source_0", &imgs[0]), ("source_2", &imgs[2])], "source_1"),
        (
            vec![
                ("request", &json),
                ("source_0", &imgs[0]),
                ("source_1", &imgs[1]),
                ("source_2", &imgs[2]),
                ("thumbnail", b"x"),
            ],
            "thumbnail",
        ),
        (vec![("request", &json), ("request", &json), ("source_0", &imgs[0])], "request"),
        (vec![("request", &json), ("source_0", &imgs[0]), ("source_0", &imgs[0])], "source_0"),
        (
            vec![
                ("request", &json),
                ("source_0", &imgs[0]),
                ("source_1", &imgs[1]),
                ("source_2", &imgs[2]),
                ("source_3", &imgs[2]),
            ],
            "source_3",
        ),
    ];
    for (parts, field) in cases {
        assert_error(
            &send(app(), multipart_to("/v1/render", &parts, &[])).await,
            400,
            "malformed_request",
            Some(field),
        );
    }
    let mut with_image = request_json(32);
    with_image["sources"][0]["image"] = json!("AAAA");
    render_multipart_error(with_image, 400, "malformed_request", Some("sources[0].image")).await;
}

#[tokio::test]
async fn broken_multipart_framing() {
    let no_boundary =
        Request::post("/v1/render").header("content-type", "multipart/form-data").body(Body::from("x")).unwrap();
    assert_error(&send(app(), no_boundary).await, 400, "malformed_request", Some("content-type"));
    let truncated = Request::post("/v1/render")
        .header("content-type", format!("multipart/form-data; boundary={BOUNDARY}"))
        .body(Body::from(format!("--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"request\"\r\n\r\n{{\"sou")))
        .unwrap();
    assert_error(&send(app(), truncated).await, 400, "malformed_request", Some("request"));
}

#[tokio::test]
async fn image_errors() {
    let json = serde_json::to_vec(&request_json(32)).unwrap();
    let imgs = images(32);
    let mut broken_png = imgs[1][..40].to_vec();
    broken_png.extend_from_slice(b"garbage");
    let got = send(
        app(),
        multipart_to(
            "/v1/render",
            &[("request", &json), ("source_0", &imgs[0]), ("source_1", &broken_png), ("source_2", &imgs[2])],
            &[],
        ),
    )
    .await;
    assert_error(&got, 400, "malformed_request", Some("source_1"));
    let got = send(
        app(),
        multipart_to(
            "/v1/render",
            &[("request", &json), ("source_0", &imgs[0]), ("source_1", &imgs[1]), ("source_2", b"GIF89a....")],
            &[],
        ),
    )
    .await;
    assert_error(&got, 415, "unsupported_media_type", Some("source_2"));
    let got = send(
        app(),
        multipart_to(
            "/v1/render",
            &[("request", &json), ("source_0", b"hello"), ("source_1", &imgs[1]), ("source_2", &imgs[2])],
            &[],
        ),
    )
    .await;
    assert_error(&got, 415, "unsupported_media_type", Some("source_0"));
}

#[tokio::test]
async fn protobuf_errors() {
    let garbage = Request::post("/v1/render")
        .header("content-type", "application/x-protobuf")
        .body(Body::from(vec![0xff, 0xff, 0xff]))
        .unwrap();
    assert_error(&send(app(), garbage).await, 400, "malformed_request", Some("body"));
    let mut msg = proto_render();
    msg.sources[1].camera.as_mut().unwrap().pose.as_mut().unwrap().kind = 0;
    assert_error(&send(app(), proto_req(&msg)).await, 400, "malformed_request", Some("sources[1].camera.pose.kind"));
    let mut msg = proto_render();
    msg.target.as_mut().unwrap().pose.as_mut().unwrap().matrix.pop();
    assert_error(&send(app(), proto_req(&msg)).await, 400, "malformed_request", Some("target.pose.matrix"));
    let mut msg = proto_render();
    msg.target = None;
    assert_error(&send(app(), proto_req(&msg)).await, 400, "malformed_request", Some("target"));
    let mut msg = proto_render();
    msg.outputs = vec!["alpha".into()];
    assert_error(&send(app(), proto_req(&msg)).await, 400, "malformed_request", Some("outputs[0]"));
    // Protobuf can carry non-finite numbers, JSON cannot.
    let mut msg = proto_render();
    msg.sources[0].camera.as_mut().unwrap().pose.as_mut().unwrap().matrix[3] = f64::NAN;
    assert_error(&send(app(), proto_req(&msg)).await, 422, "invalid_request", Some("sources[0].camera.pose.matrix"));
    let mut msg = proto_render();
    msg.far = f64::INFINITY;
    assert_error(&send(app(), proto_req(&msg)).await, 422, "invalid_request", Some("far"));
}

// ---------------------------------------------------------------------------------------------
// Too large (413)

#[tokio::test]
async fn bodies_over_the_limit_are_413() {
    let b = testing::bundle("scnerf", "near_far");
    let runner = FakeRunner::new(&b);
    let limits = Limits { max_body_bytes: 2000, ..Limits::default() };
    let app = router(state_with(b, runner, limits, Duration::from_secs(10)));
    let big = json_with_images(64);
    assert_error(&send(app.clone(), json_to("/v1/render", &big, &[])).await, 413, "payload_too_large", Some("body"));
    assert_error(
        &send(app.clone(), multipart_with("/v1/render", &request_json(64), 64, &[])).await,
        413,
        "payload_too_large",
        Some("body"),
    );
    let proto = Request::post("/v1/render")
        .header("content-type", "application/x-protobuf")
        .body(Body::from(vec![0u8; 5000]))
        .unwrap();
    assert_error(&send(app, proto).await, 413, "payload_too_large", Some("body"));
}

// ---------------------------------------------------------------------------------------------
// Semantically invalid (422)

#[tokio::test]
async fn wrong_view_count() {
    let mut req = request_json(32);
    req["sources"].as_array_mut().unwrap().pop();
    let json = serde_json::to_vec(&req).unwrap();
    let imgs = images(32);
    let got = send(
        app(),
        multipart_to("/v1/render", &[("request", &json), ("source_0", &imgs[0]), ("source_1", &imgs[1])], &[]),
    )
    .await;
    assert_error(&got, 422, "invalid_request", Some("sources"));
}

#[tokio::test]
async fn depth_range_errors() {
    for (near, far, field) in [(6.0, 2.0, "far"), (2.0, 2.0, "far"), (0.0, 2.0, "near"), (-1.0, 2.0, "near")] {
        let mut req = request_json(32);
        req["near"] = json!(near);
        req["far"] = json!(far);
        render_multipart_error(req, 422, "invalid_request", Some(field)).await;
    }
}

#[tokio::test]
async fn camera_errors() {
    let mut req = request_json(32);
    req["sources"][2]["camera"]["pose"]["matrix"][0] = json!([2.0, 0.0, 0.0, 0.0]);
    render_multipart_error(req, 422, "invalid_request", Some("sources[2].camera.pose.matrix")).await;
    let mut req = request_json(32);
    req["target"]["pose"]["matrix"] = json!([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]);
    render_multipart_error(req, 422, "invalid_request", Some("target.pose.matrix")).await;
    let mut req = request_json(32);
    req["target"]["pose"]["matrix"][3] = json!([0, 0, 0, 2]);
    render_multipart_error(req, 422, "invalid_request", Some("target.pose.matrix")).await;
    let mut req = request_json(32);
    req["target"]["intrinsics"]["fy"] = json!(0.0);
    render_multipart_error(req, 422, "invalid_request", Some("target.intrinsics")).await;
    let mut req = request_json(32);
    req["target"]["width"] = json!(0);
    render_multipart_error(req, 422, "invalid_request", Some("target.width")).await;
}

#[tokio::test]
async fn size_errors() {
    // CanonicalCamera says 32x32, images are 40x40.
    let json = serde_json::to_vec(&request_json(32)).unwrap();
    let imgs = images(40);
    let got = send(
        app(),
        multipart_to(
            "/v1/render",
            &[("request", &json), ("source_0", &imgs[0]), ("source_1", &imgs[1]), ("source_2", &imgs[2])],
            &[],
        ),
    )
    .await;
    assert_error(&got, 422, "invalid_request", Some("source_0"));
    // Sources of different sizes.
    let mut req = request_json(32);
    req["sources"][1]["camera"] = camera_json(64, 32, 0.0);
    render_multipart_error(req, 422, "invalid_request", Some("sources[1].camera.width")).await;
}

#[tokio::test]
async fn pixel_limits() {
    let b = testing::bundle("scnerf", "near_far");
    let runner = FakeRunner::new(&b);
    let limits = Limits { max_source_pixels: 32 * 32, max_target_pixels: 40, ..Limits::default() };
    let app = router(state_with(b, runner, limits, Duration::from_secs(10)));
    let got = send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("target.width"));
    let mut req = request_json(40);
    req["target"] = camera_json(4, 4, 0.0);
    let got = send(app.clone(), multipart_with("/v1/render", &req, 40, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("sources[0].camera.width"));
    // The image header is checked before decoding, even if the camera claims a small size.
    let mut req = request_json(32);
    req["target"] = camera_json(4, 4, 0.0);
    let json = serde_json::to_vec(&req).unwrap();
    let small = images(32);
    let huge = png(64, 64, [0, 0, 0, 255]);
    let got = send(
        app,
        multipart_to(
            "/v1/render",
            &[("request", &json), ("source_0", &small[0]), ("source_1", &huge), ("source_2", &small[2])],
            &[],
        ),
    )
    .await;
    assert_error(&got, 422, "invalid_request", Some("source_1"));
}

#[tokio::test]
async fn background_and_output_errors() {
    for (bg, field) in [(json!([1.0, 2.0, 0.0]), "background"), (json!([1.0, 1.0]), "background")] {
        let mut req = request_json(32);
        req["background"] = bg;
        render_multipart_error(req, 422, "invalid_request", Some(field)).await;
    }
    let mut req = request_json(32);
    req["outputs"] = json!([]);
    render_multipart_error(req, 422, "invalid_request", Some("outputs")).await;
    let mut req = request_json(32);
    req["outputs"] = json!(["rgb", "rgb"]);
    render_multipart_error(req, 422, "invalid_request", Some("outputs[1]")).await;
}
