//! Several models on one server, over fake runners: each answers with its own graphs, requests
//! name theirs (or get the default), scenes belong to the model they were created with, a
//! reload picks up new bundle folders and skips broken ones, and the metrics' model label takes
//! only the served models' names.

mod common;

use std::path::{Path, PathBuf};

use axum::Router;
use common::*;
use scnerf_server::backend::{ExecutorOptions, MemoryBudget};
use scnerf_server::http::{router, ServiceOptions};
use scnerf_server::testing::{models_state, models_state_with, request_json, write_bundle, FakeModel};
use serde_json::{json, Value};

/// A server of `lego` (the default) and `dtu`, whose fakes render different colours.
fn two_models() -> Router {
    let models = vec![FakeModel::new("lego", 1.0), FakeModel::new("dtu", 0.5)];
    router(models_state(models, None, None, ServiceOptions::default()).unwrap())
}

fn with_model(mut body: Value, model: &str) -> Value {
    body["model"] = json!(model);
    body
}

/// The decoded PNG of a 200 answer.
fn pixels(got: &Got) -> Vec<u8> {
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    image::load_from_memory(&got.2).unwrap().to_rgb8().into_raw()
}

async fn render(app: &Router, body: &Value) -> Got {
    send(app.clone(), multipart_with("/v1/render", body, 32, &[])).await
}

/// A scratch folder for bundles, empty, unique to the test.
fn scratch(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("scnerf-models-{}-{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[tokio::test]
async fn two_models_side_by_side_each_render_their_own_view() {
    let app = two_models();
    let lego = render(&app, &with_model(request_json(32), "lego")).await;
    let dtu = render(&app, &with_model(request_json(32), "dtu")).await;
    let default = render(&app, &request_json(32)).await;
    assert_eq!(lego.1["x-scnerf-model"], "lego");
    assert_eq!(dtu.1["x-scnerf-model"], "dtu");
    assert_eq!(default.1["x-scnerf-model"], "lego", "the first bundle is the default");
    let (lego, dtu, default) = (pixels(&lego), pixels(&dtu), pixels(&default));
    assert_ne!(lego, dtu, "each model renders with its own graphs");
    assert_eq!(lego, default);
    // dtu's fake renders half of lego's colours (before the white background).
    let sum = |p: &[u8]| p.iter().map(|&v| u64::from(v)).sum::<u64>();
    assert!(sum(&dtu) < sum(&lego), "{dtu:?} vs {lego:?}");
}

#[tokio::test]
async fn the_models_are_listed_with_the_default_marked() {
    let models = vec![FakeModel::new("lego", 1.0), FakeModel::new("dtu", 0.5)];
    let app = router(models_state(models, Some("dtu"), None, ServiceOptions::default()).unwrap());
    let got = send(app.clone(), get("/v1/models", &[])).await;
    assert_eq!(got.0, 200);
    let list = json_of(&got);
    assert_eq!(list["default"], "dtu");
    let names: Vec<&str> = list["models"].as_array().unwrap().iter().map(|m| m["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["lego", "dtu"]);
    let dtu = &list["models"][1];
    assert_eq!((dtu["default"].as_bool(), list["models"][0]["default"].as_bool()), (Some(true), Some(false)));
    assert_eq!(dtu["variant"], "scnerf");
    assert_eq!(dtu["views"], 3);
    assert_eq!(dtu["refined"], false);
    assert_eq!(dtu["source"], "fake");
    assert_eq!(dtu["path"], "/nonexistent/dtu");
    // --default-model: requests without a model render with it.
    assert_eq!(render(&app, &request_json(32)).await.1["x-scnerf-model"], "dtu");
}

#[tokio::test]
async fn a_default_or_a_name_that_no_model_has_is_refused() {
    let models = vec![FakeModel::new("lego", 1.0), FakeModel::new("lego", 0.5)];
    let err = models_state(models, None, None, ServiceOptions::default()).err().unwrap();
    assert!(err.contains("two bundles are named \"lego\"") && err.contains("/nonexistent/lego"), "{err}");
    let models = vec![FakeModel::new("lego", 1.0)];
    let err = models_state(models, Some("dtu"), None, ServiceOptions::default()).err().unwrap();
    assert!(err.contains("--default-model dtu: no such model (serving lego)"), "{err}");
}

/// An unknown model is 404 `model_not_found` naming it, on every endpoint that takes one, and in
/// every body form.
#[tokio::test]
async fn an_unknown_model_is_404_naming_it() {
    let app = two_models();
    let named = |got: &Got| {
        assert_error(got, 404, "model_not_found", Some("model"));
        let message = json_of(got)["error"]["message"].as_str().unwrap().to_string();
        assert!(message.contains("\"nerf\"") && message.contains("GET /v1/models"), "{message}");
    };
    named(&render(&app, &with_model(request_json(32), "nerf")).await);
    named(&send(app.clone(), json_to("/v1/render", &with_model(json_with_images(32), "nerf"), &[])).await);
    named(&send(app.clone(), multipart_with("/v1/scenes", &with_model(scene_json(32), "nerf"), 32, &[])).await);
    let put = multipart_with("/v1/scenes/mine", &with_model(scene_json(32), "nerf"), 32, &[]);
    let (mut parts, body) = put.into_parts();
    parts.method = axum::http::Method::PUT;
    named(&send(app.clone(), axum::http::Request::from_parts(parts, body)).await);
    let proto =
        scnerf_proto::v1::RenderRequest { model: "nerf".into(), ..proto_request(&request_json(32), &images(32)) };
    let body = prost::Message::encode_to_vec(&proto);
    named(&send(app.clone(), raw_to("POST", "/v1/render", "application/x-protobuf", body, &[])).await);
    let capture = multipart_to("/v1/captures?model=nerf", &[("file", b"x")], &[]);
    named(&send(app, capture).await);
}

/// A scene belongs to the model it was created with: its renders use that model, and a render
/// naming another is 409 `model_mismatch` naming both.
#[tokio::test]
async fn a_scene_renders_with_its_own_model_and_refuses_another() {
    let app = two_models();
    let created = send(app.clone(), multipart_with("/v1/scenes", &with_model(scene_json(32), "dtu"), 32, &[])).await;
    assert_eq!(created.0, 201, "{}", String::from_utf8_lossy(&created.2));
    assert_eq!(created.1["x-scnerf-model"], "dtu");
    let created = json_of(&created);
    assert_eq!(created["model"], "dtu");
    let path = format!("/v1/scenes/{}/render", created["scene_id"].as_str().unwrap());

    let unnamed = send(app.clone(), json_to(&path, &target_json(32), &[])).await;
    assert_eq!(unnamed.1["x-scnerf-model"], "dtu", "no model named: the scene's");
    let named = send(app.clone(), json_to(&path, &with_model(target_json(32), "dtu"), &[])).await;
    assert_eq!(pixels(&unnamed), pixels(&named));
    let one_shot = render(&app, &with_model(request_json(32), "dtu")).await;
    assert_eq!(pixels(&named), pixels(&one_shot));

    let other = send(app.clone(), json_to(&path, &with_model(target_json(32), "lego"), &[])).await;
    assert_error(&other, 409, "model_mismatch", Some("model"));
    let message = json_of(&other)["error"]["message"].as_str().unwrap().to_string();
    assert!(message.contains("\"dtu\"") && message.contains("\"lego\""), "{message}");
    let unknown = send(app, json_to(&path, &with_model(target_json(32), "nerf"), &[])).await;
    assert_error(&unknown, 404, "model_not_found", Some("model"));
}

/// The `model` label of the metrics takes the served models' names only: a request naming
/// something else adds no series.
#[tokio::test]
async fn the_metrics_model_label_holds_only_served_names() {
    let app = two_models();
    for model in ["lego", "dtu", "nerf", "{evil=\"x\"}"] {
        render(&app, &with_model(request_json(32), model)).await;
    }
    render(&app, &request_json(32)).await;
    let metrics = String::from_utf8(send(app, get("/metrics", &[])).await.2.to_vec()).unwrap();
    let mut labels: Vec<&str> = metrics
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| l.split("model=\"").nth(1)?.split('"').next())
        .collect();
    labels.sort_unstable();
    labels.dedup();
    assert_eq!(labels, ["dtu", "lego"], "{metrics}");
    let renderer =
        |model: &str| format!("scnerf_stage_duration_seconds_count{{stage=\"renderer\",model=\"{model}\"}} ");
    let count =
        |model: &str| metrics.lines().find_map(|l| l.strip_prefix(&renderer(model))?.trim().parse::<f64>().ok());
    assert_eq!((count("lego"), count("dtu")), (Some(2.0), Some(1.0)), "{metrics}");
}

async fn reload(app: &Router) -> Value {
    let got = send(app.clone(), raw_to("POST", "/v1/models/reload", "application/json", vec![], &[])).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    json_of(&got)
}

fn names(list: &Value) -> Vec<String> {
    list.as_array().unwrap().iter().map(|m| m["name"].as_str().unwrap().to_string()).collect()
}

/// A reload loads the bundle folders added below DIR, and not those it serves already; a
/// corrupt bundle is skipped with the reason and takes nothing down.
#[tokio::test]
async fn a_reload_loads_new_bundles_and_skips_corrupt_ones() {
    let dir = scratch("reload");
    write_bundle(&dir.join("lego"), 1.0).unwrap();
    let models = vec![FakeModel::new("first", 1.0)];
    let app = router(models_state(models, None, Some(&dir), ServiceOptions::default()).unwrap());
    let answer = reload(&app).await;
    assert_eq!(names(&answer["loaded"]), ["lego"], "{answer}");
    assert_error(&render(&app, &with_model(request_json(32), "dtu")).await, 404, "model_not_found", Some("model"));

    write_bundle(&dir.join("group/dtu"), 0.5).unwrap();
    corrupt(&dir.join("broken"), &dir.join("hashless"));
    let answer = reload(&app).await;
    assert_eq!(answer["dir"], dir.display().to_string());
    assert_eq!(names(&answer["loaded"]), ["dtu"], "{answer}");
    let skipped = &answer["skipped"];
    assert_eq!(names(skipped), ["broken", "hashless"], "{answer}");
    assert!(skipped[0]["reason"].as_str().unwrap().contains("not a valid manifest"), "{answer}");
    assert!(skipped[1]["reason"].as_str().unwrap().contains("sha256"), "{answer}");

    let listed = json_of(&send(app.clone(), get("/v1/models", &[])).await);
    assert_eq!(names(&listed["models"]), ["first", "lego", "dtu"]);
    let dtu = pixels(&render(&app, &with_model(request_json(32), "dtu")).await);
    let lego = pixels(&render(&app, &with_model(request_json(32), "lego")).await);
    assert_ne!(dtu, lego, "the new model runs its own graphs");
    assert_eq!(pixels(&render(&app, &request_json(32)).await), lego, "the default is unchanged");
    assert_eq!(send(app, get("/readyz", &[])).await.0, 200);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A folder whose manifest is not JSON, and one whose graph does not match its hash.
fn corrupt(broken: &Path, hashless: &Path) {
    std::fs::create_dir_all(broken).unwrap();
    std::fs::write(broken.join("manifest.json"), "{\"format_version\": 1,").unwrap();
    write_bundle(hashless, 1.0).unwrap();
    std::fs::write(hashless.join("renderer.onnx"), "another graph").unwrap();
}

/// A bundle folder of a served model's name elsewhere is skipped, naming both folders; the
/// served model stays.
#[tokio::test]
async fn a_reload_skips_a_second_bundle_of_a_served_name() {
    let dir = scratch("duplicate");
    write_bundle(&dir.join("a/lego"), 1.0).unwrap();
    let app = router(models_state(vec![FakeModel::new("lego", 0.5)], None, Some(&dir), Default::default()).unwrap());
    let answer = reload(&app).await;
    assert!(answer["loaded"].as_array().unwrap().is_empty(), "{answer}");
    let reason = answer["skipped"][0]["reason"].as_str().unwrap();
    assert!(reason.contains("/nonexistent/lego") && reason.contains("a/lego"), "{reason}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A bundle whose graphs alone exceed the memory budget left is skipped before its sessions are
/// made, and says so; the server keeps serving.
#[tokio::test]
async fn a_reload_skips_a_bundle_the_memory_budget_cannot_hold() {
    let dir = scratch("memory");
    write_bundle(&dir.join("lego"), 1.0).unwrap();
    let budget = MemoryBudget { total: 64, reserved: 0 };
    let executor = ExecutorOptions { memory: budget, ..ExecutorOptions::with_capacity(8) };
    let models = vec![FakeModel::new("first", 1.0)];
    let state = models_state_with(models, None, Some(&dir), ServiceOptions::default(), executor).unwrap();
    let app = router(state);
    let answer = reload(&app).await;
    assert!(answer["loaded"].as_array().unwrap().is_empty(), "{answer}");
    let reason = answer["skipped"][0]["reason"].as_str().unwrap();
    assert!(reason.starts_with("not enough memory: its graphs"), "{reason}");
    assert_eq!(names(&json_of(&send(app, get("/v1/models", &[])).await)["models"]), ["first"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Without --models there is nothing to rescan, and the reload says so.
#[tokio::test]
async fn a_reload_without_a_models_folder_loads_nothing() {
    let answer = reload(&two_models()).await;
    assert_eq!(answer, json!({"dir": null, "loaded": [], "skipped": [], "skipped_more": 0}));
}

/// Model names are NFC: `café` composed and decomposed are one model (the second folder is
/// skipped as a duplicate), and a request may name it either way; a folder whose name holds a
/// control character is skipped, saying so, and a request naming one is refused naming `model`.
#[tokio::test]
async fn model_names_are_nfc_without_control_characters() {
    let dir = scratch("names");
    let (composed, decomposed) = ("caf\u{e9}", "cafe\u{301}");
    write_bundle(&dir.join(composed), 1.0).unwrap();
    write_bundle(&dir.join(decomposed), 0.5).unwrap();
    write_bundle(&dir.join("lego\n2026-01-01T00:00:00Z  INFO forged"), 1.0).unwrap();
    let app = router(models_state(vec![FakeModel::new("first", 1.0)], None, Some(&dir), Default::default()).unwrap());
    let answer = reload(&app).await;
    assert_eq!(names(&answer["loaded"]), [composed], "{answer}");
    let skipped = answer["skipped"].as_array().unwrap();
    assert_eq!(skipped.len(), 2, "{answer}");
    let reason = |name: &str| {
        let entry = skipped.iter().find(|s| s["name"].as_str().unwrap().starts_with(name)).unwrap();
        entry["reason"].as_str().unwrap().to_string()
    };
    assert!(reason(composed).contains("caf"), "a second folder of the name: {answer}");
    assert!(reason("lego").contains("control character \\n"), "{answer}");
    for spelling in [composed, decomposed] {
        let got = render(&app, &with_model(request_json(32), spelling)).await;
        assert_eq!(got.0, 200, "{spelling:?}: {}", String::from_utf8_lossy(&got.2));
        assert_eq!(got.1["x-scnerf-model"].as_bytes(), composed.as_bytes());
    }
    let refused = render(&app, &with_model(request_json(32), "lego\n2026-01-01T00:00:00Z  INFO forged")).await;
    assert_error(&refused, 422, "invalid_request", Some("model"));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A server without tokens refuses a reload from another site's page (its browser sends
/// `Origin`, or `Sec-Fetch-Site`), and takes one from its own origin, a listed origin, or a
/// client that is not a browser.
#[tokio::test]
async fn a_reload_from_another_sites_page_is_refused() {
    let options = ServiceOptions { allowed_origins: vec!["https://studio.example.com".into()], ..Default::default() };
    let app = router(models_state(vec![FakeModel::new("first", 1.0)], None, None, options).unwrap());
    let post = |headers: &[(&str, &str)]| {
        let request = raw_to("POST", "/v1/models/reload", "application/json", vec![], headers);
        send(app.clone(), request)
    };
    let host = ("host", "scnerf.internal:8080");
    let refused = post(&[host, ("origin", "https://evil.example")]).await;
    assert_error(&refused, 403, "forbidden", Some("origin"));
    assert_error(&post(&[host, ("origin", "null")]).await, 403, "forbidden", Some("origin"));
    let no_origin = post(&[host, ("sec-fetch-site", "cross-site")]).await;
    assert_error(&no_origin, 403, "forbidden", Some("sec-fetch-site"));
    assert_eq!(post(&[host, ("origin", "http://scnerf.internal:8080")]).await.0, 200, "its own origin");
    assert_eq!(post(&[host, ("origin", "https://studio.example.com")]).await.0, 200, "a listed origin");
    assert_eq!(post(&[host]).await.0, 200, "not a browser");
    // Reading is not concerned.
    let listed = send(app.clone(), get("/v1/models", &[host, ("origin", "https://evil.example")])).await;
    assert_eq!(listed.0, 200);
}
