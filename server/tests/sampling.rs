//! The `sampling` field of render requests: `full` and `guided` both answer and say how they
//! sampled, a bad value is 422 naming the field, and a bundle without guided graphs renders full
//! (over the fake graph runner; guided pixels against PyTorch are in tests/tests/parity.rs).

use std::sync::atomic::Ordering;
use std::time::Duration;

use axum::Router;
use base64::Engine;
use prost::Message;
use scnerf_proto::v1 as pb;
use scnerf_server::bundle::GraphKind;
use scnerf_server::http::router;
use scnerf_server::request::Limits;
use scnerf_server::testing::{bundle, guided_bundle, request_json, state_with, FakeRunner};
use serde_json::{json, Value};

mod common;
use common::*;

/// A server over a bundle with guided sampling's graphs, and its runner's call counts.
fn guided_app() -> (Router, std::sync::Arc<[std::sync::atomic::AtomicUsize; GraphKind::ALL.len()]>) {
    let b = guided_bundle("scnerf");
    let runner = FakeRunner::new(&b);
    let calls = runner.calls.clone();
    (router(state_with(b, runner, Limits::default(), Duration::from_secs(60))), calls)
}

fn with_sampling(sampling: Option<&str>) -> Value {
    let mut req = request_json(32);
    req["target"]["width"] = json!(24);
    req["target"]["height"] = json!(20);
    if let Some(s) = sampling {
        req["sampling"] = json!(s);
    }
    req
}

async fn render_json(app: Router, req: &Value) -> (u16, Value, axum::http::HeaderMap) {
    let (status, headers, body) =
        send(app, multipart_with("/v1/render", req, 32, &[("accept", "application/json")])).await;
    let v: Value = serde_json::from_slice(&body).unwrap_or(Value::Null);
    (status.as_u16(), v, headers)
}

#[tokio::test]
async fn full_and_guided_both_answer_and_say_how_they_sampled() {
    for (asked, runs) in [("full", [GraphKind::Renderer]), ("guided", [GraphKind::RendererGuide])] {
        let (app, calls) = guided_app();
        let (status, v, headers) = render_json(app, &with_sampling(Some(asked))).await;
        assert_eq!(status, 200, "{asked}: {v}");
        assert_eq!(v["sampling"], asked);
        assert_eq!(headers["x-scnerf-sampling"], asked);
        let samples = v["samples_per_ray"].as_f64().unwrap();
        assert_eq!(headers["x-scnerf-samples-per-ray"].to_str().unwrap(), format!("{samples:.2}"));
        match asked {
            // The fake bundle: 16 samples per ray.
            "full" => assert_eq!(samples, 16.0),
            _ => assert!(samples > 0.0 && samples < 16.0, "guided used {samples} samples per ray"),
        }
        for kind in runs {
            assert!(calls[kind.index()].load(Ordering::SeqCst) > 0, "{asked}: {kind} never ran");
        }
        let other = if asked == "full" { GraphKind::RendererGuide } else { GraphKind::Renderer };
        assert_eq!(calls[other.index()].load(Ordering::SeqCst), 0, "{asked} ran {other}");
        let data = base64::engine::general_purpose::STANDARD.decode(v["rgb"]["data"].as_str().unwrap()).unwrap();
        let png = image::load_from_memory(&data).unwrap();
        assert_eq!((png.width(), png.height()), (24, 20));
    }
}

#[tokio::test]
async fn guided_is_the_default_when_the_bundle_has_it() {
    let (app, calls) = guided_app();
    let (status, v, _) = render_json(app, &with_sampling(None)).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["sampling"], "guided");
    assert!(calls[GraphKind::RendererFine.index()].load(Ordering::SeqCst) > 0);
    let (app, _) = guided_app();
    let (_, _, body) = send(app, get("/v1/model", &[])).await;
    let model: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(model["sampling"]["default"], "guided");
    assert_eq!(model["sampling"]["modes"], json!(["full", "guided"]));
    assert_eq!(model["sampling"]["guided"]["step"], 4);
}

#[tokio::test]
async fn a_bad_sampling_is_422_naming_the_field() {
    for bad in ["fast", "", "GUIDED"] {
        let (app, _) = guided_app();
        let got = send(app, multipart_with("/v1/render", &with_sampling(Some(bad)), 32, &[])).await;
        assert_error(&got, 422, "invalid_request", Some("sampling"));
    }
    let mut req = with_sampling(None);
    req["sampling"] = json!(3);
    let (app, _) = guided_app();
    let got = send(app, multipart_with("/v1/render", &req, 32, &[])).await;
    assert_eq!(got.0, 400, "a number is not a sampling: malformed");
}

#[tokio::test]
async fn guided_on_a_bundle_without_its_graphs_is_422_and_the_default_is_full() {
    let b = bundle("scnerf", "near_far");
    let app = || router(state_with(b.clone(), FakeRunner::new(&b), Limits::default(), Duration::from_secs(60)));
    let got = send(app(), multipart_with("/v1/render", &with_sampling(Some("guided")), 32, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("sampling"));
    let (status, v, _) = render_json(app(), &with_sampling(None)).await;
    assert_eq!((status, v["sampling"].as_str()), (200, Some("full")));
}

#[tokio::test]
async fn protobuf_and_scene_renders_carry_the_field() {
    let (app, _) = guided_app();
    let req = with_sampling(Some("full"));
    let msg = pb::RenderRequest { sampling: "full".into(), ..proto_request(&req, &images(32)) };
    let accept = [("accept", "application/x-protobuf")];
    let (status, _, body) =
        send(app, raw_to("POST", "/v1/render", "application/x-protobuf", msg.encode_to_vec(), &accept)).await;
    assert_eq!(status, 200);
    let resp = pb::RenderResponse::decode(body).unwrap();
    assert_eq!((resp.sampling.as_str(), resp.samples_per_ray), ("full", 16.0));

    let (app, _) = guided_app();
    let created = send(app.clone(), multipart_with("/v1/scenes", &scene_json(32), 32, &[])).await;
    assert_eq!(created.0, 201);
    let scene = json_of(&created)["scene_id"].as_str().unwrap().to_string();
    let target = json!({"target": with_sampling(None)["target"], "sampling": "guided"});
    let (status, headers, body) = send(app.clone(), json_to(&format!("/v1/scenes/{scene}/render"), &target, &[])).await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    assert_eq!(headers["x-scnerf-sampling"], "guided");
    let bad = json!({"target": with_sampling(None)["target"], "sampling": "fast"});
    let got = send(app, json_to(&format!("/v1/scenes/{scene}/render"), &bad, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("sampling"));
}

#[tokio::test]
async fn metrics_count_views_by_sampling() {
    let (app, _) = guided_app();
    for asked in ["full", "guided", "guided"] {
        let (status, ..) = render_json(app.clone(), &with_sampling(Some(asked))).await;
        assert_eq!(status, 200);
    }
    let (_, _, body) = send(app, get("/metrics", &[])).await;
    let text = String::from_utf8_lossy(&body);
    assert!(text.contains("scnerf_samples_per_ray_count{sampling=\"full\",model=\"fake\"} 1"), "{text}");
    assert!(text.contains("scnerf_samples_per_ray_count{sampling=\"guided\",model=\"fake\"} 2"), "{text}");
}
