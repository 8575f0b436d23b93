//! /metrics, request ids, /openapi.json.

mod common;

use axum::body::Body;
use axum::http::Request;
use common::*;
use scnerf_server::http::router;
use scnerf_server::testing::{fake_state, request_json};
use serde_json::Value;

/// The value of the sample `name{labels}` (labels as written by the exporter, or "").
fn sample(metrics: &str, name: &str, labels: &str) -> Option<f64> {
    let key = if labels.is_empty() { name.to_string() } else { format!("{name}{{{labels}}}") };
    metrics.lines().find_map(|l| l.strip_prefix(&key)?.strip_prefix(' ')?.trim().parse().ok())
}

async fn scrape(app: &axum::Router) -> String {
    let got = send(app.clone(), get("/metrics", &[])).await;
    assert_eq!(got.0, 200);
    assert!(got.1["content-type"].to_str().unwrap().starts_with("application/openmetrics-text"));
    String::from_utf8(got.2.to_vec()).unwrap()
}

#[tokio::test]
async fn metrics_count_requests_stages_queue_and_cache() {
    let app = router(fake_state());
    assert_eq!(send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[])).await.0, 200);
    let created = send(app.clone(), multipart_with("/v1/scenes", &scene_json(32), 32, &[])).await;
    let id = json_of(&created)["scene_id"].as_str().unwrap().to_string();
    let path = format!("/v1/scenes/{id}/render");
    assert_eq!(send(app.clone(), json_to(&path, &target_json(32), &[])).await.0, 200);
    assert_eq!(send(app.clone(), json_to(&path, &target_json(32), &[])).await.0, 200);
    let missing = "/v1/scenes/00000000000000000000000000000000/render";
    assert_eq!(send(app.clone(), json_to(missing, &target_json(32), &[])).await.0, 404);
    assert_eq!(send(app.clone(), get("/nowhere", &[])).await.0, 404);

    let m = scrape(&app).await;
    let requests = "scnerf_http_requests_total";
    assert_eq!(sample(&m, requests, r#"route="/v1/render",method="POST",status="200""#), Some(1.0), "{m}");
    assert_eq!(sample(&m, requests, r#"route="/v1/scenes",method="POST",status="201""#), Some(1.0));
    assert_eq!(sample(&m, requests, r#"route="/v1/scenes/{id}/render",method="POST",status="200""#), Some(2.0));
    assert_eq!(sample(&m, requests, r#"route="/v1/scenes/{id}/render",method="POST",status="404""#), Some(1.0));
    assert_eq!(sample(&m, requests, r#"route="unmatched",method="GET",status="404""#), Some(1.0));
    let render_latency = sample(&m, "scnerf_http_request_duration_seconds_count", r#"route="/v1/render""#);
    assert_eq!(render_latency, Some(1.0));
    for (stage, n) in [("decode", 2.0), ("encoder", 2.0), ("volume", 2.0), ("renderer", 3.0), ("encode", 3.0)] {
        let labels = format!(r#"stage="{stage}",model="fake""#);
        assert_eq!(sample(&m, "scnerf_stage_duration_seconds_count", &labels), Some(n), "{stage}\n{m}");
    }
    assert_eq!(sample(&m, "scnerf_inference_queue_requests", ""), Some(0.0));
    assert_eq!(sample(&m, "scnerf_inference_queue_jobs", ""), Some(0.0));
    assert_eq!(sample(&m, "scnerf_inference_queue_capacity", ""), Some(8.0));
    assert_eq!(sample(&m, "scnerf_scene_cache_entries", ""), Some(1.0));
    assert!(sample(&m, "scnerf_scene_cache_bytes", "").unwrap() > 0.0);
    assert_eq!(sample(&m, "scnerf_scene_cache_hits_total", ""), Some(2.0));
    assert_eq!(sample(&m, "scnerf_scene_cache_misses_total", ""), Some(1.0));
    assert!(m.trim_end().ends_with("# EOF"));
}

#[tokio::test]
async fn each_app_state_has_its_own_metrics() {
    let a = router(fake_state());
    let b = router(fake_state());
    send(a.clone(), get("/healthz", &[])).await;
    send(a.clone(), get("/healthz", &[])).await;
    let labels = r#"route="/healthz",method="GET",status="200""#;
    assert_eq!(sample(&scrape(&a).await, "scnerf_http_requests_total", labels), Some(2.0));
    assert_eq!(sample(&scrape(&b).await, "scnerf_http_requests_total", labels), None);
}

#[tokio::test]
async fn request_ids_are_generated_kept_or_replaced() {
    let app = router(fake_state());
    let got = send(app.clone(), get("/healthz", &[])).await;
    let id = got.1["x-request-id"].to_str().unwrap();
    assert_eq!(id.len(), 36, "a UUID: {id}");
    let got = send(app.clone(), get("/healthz", &[("x-request-id", "client-42.a:b_c")])).await;
    assert_eq!(got.1["x-request-id"], "client-42.a:b_c");
    // Errors carry it too.
    let got = send(app.clone(), get("/nowhere", &[("x-request-id", "trace-me")])).await;
    assert_eq!(got.1["x-request-id"], "trace-me");
    for hostile in ["x".repeat(65), "a b".into(), "<script>".into()] {
        let got = send(app.clone(), get("/healthz", &[("x-request-id", &hostile)])).await;
        let id = got.1["x-request-id"].to_str().unwrap();
        assert_ne!(id, hostile);
        assert_eq!(id.len(), 36);
    }
}

#[tokio::test]
async fn openapi_document_describes_the_real_routes_and_types() {
    let got = send(router(fake_state()), Request::get("/openapi.json").body(Body::empty()).unwrap()).await;
    assert_eq!(got.0, 200);
    let doc: Value = json_of(&got);
    assert!(doc["openapi"].as_str().unwrap().starts_with("3."));
    let paths = doc["paths"].as_object().unwrap();
    for (path, method) in [
        ("/v1/render", "post"),
        ("/v1/scenes", "post"),
        ("/v1/scenes/{id}/render", "post"),
        ("/v1/scenes/{id}", "delete"),
        ("/v1/model", "get"),
        ("/healthz", "get"),
        ("/readyz", "get"),
        ("/metrics", "get"),
        ("/openapi.json", "get"),
    ] {
        assert!(paths.get(path).and_then(|p| p.get(method)).is_some(), "{method} {path} missing");
    }
    let schemas = &doc["components"]["schemas"];
    let required = |name: &str| -> Vec<String> {
        let mut r: Vec<String> =
            schemas[name]["required"].as_array().unwrap().iter().map(|v| v.as_str().unwrap().to_string()).collect();
        r.sort();
        r
    };
    // The parser's required fields, as the schema says.
    assert_eq!(required("RenderRequest"), ["far", "near", "sources", "target"]);
    assert_eq!(required("SceneRequest"), ["far", "near", "sources"]);
    assert_eq!(required("SceneRenderRequest"), ["target"]);
    assert_eq!(required("Camera"), ["height", "pose", "width"]);
    assert_eq!(required("Pose"), ["axes", "kind", "matrix"]);
    assert_eq!(required("Error"), ["error"]);
    assert_eq!(schemas["RenderRequest"]["additionalProperties"], false, "unknown fields are refused");
    let render = &paths["/v1/render"]["post"];
    for ctype in ["multipart/form-data", "application/json", "application/x-protobuf"] {
        assert!(render["requestBody"]["content"][ctype].is_object(), "{ctype}");
    }
    for ctype in ["image/png", "application/json", "application/x-protobuf"] {
        assert!(render["responses"]["200"]["content"][ctype].is_object(), "{ctype}");
    }
    assert_eq!(doc["components"]["securitySchemes"]["bearer"]["scheme"], "bearer");
    let mut ids: Vec<&str> = paths
        .values()
        .flat_map(|p| p.as_object().unwrap().values())
        .filter_map(|op| op["operationId"].as_str())
        .collect();
    let n = ids.len();
    ids.sort();
    ids.dedup();
    assert_eq!(ids.len(), n, "operation ids must be unique: {ids:?}");
    let links = &paths["/v1/scenes"]["post"]["responses"]["201"]["links"];
    assert_eq!(links["RenderScene"]["operationId"], "render_scene");
    assert_eq!(links["DeleteScene"]["parameters"]["id"], "$response.body#/scene_id");
}

/// The served document is committed as docs/openapi.json (as text-generation-inference does):
/// an API change shows in review, and a stale file fails here.
#[tokio::test]
async fn committed_openapi_document_is_the_served_one() {
    let served = json_of(&send(router(fake_state()), get("/openapi.json", &[])).await);
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/openapi.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let committed: Value = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    if let Some(at) = first_difference(&committed, &served, "") {
        panic!(
            "docs/openapi.json differs from the served /openapi.json at {at}; regenerate it with\n  \
             cargo run -q -p scnerf-server --example openapi > docs/openapi.json"
        );
    }
}

/// The JSON pointer of the first place where `a` and `b` differ.
fn first_difference(a: &Value, b: &Value, at: &str) -> Option<String> {
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
            keys.into_iter().find_map(|k| match (x.get(k), y.get(k)) {
                (Some(v), Some(w)) => first_difference(v, w, &format!("{at}/{k}")),
                _ => Some(format!("{at}/{k}")),
            })
        }
        (Value::Array(x), Value::Array(y)) if x.len() == y.len() => {
            x.iter().zip(y).enumerate().find_map(|(i, (v, w))| first_difference(v, w, &format!("{at}/{i}")))
        }
        _ => (a != b).then(|| if at.is_empty() { "/".to_string() } else { at.to_string() }),
    }
}

/// The `scnerf_http_requests_total` series in a scrape.
fn request_series(metrics: &str) -> usize {
    metrics.lines().filter(|l| l.starts_with("scnerf_http_requests_total{")).count()
}

/// Any token is a valid method name in HTTP; each one must not become a series of its own, with
/// or without a valid token (401 and 405 alike).
#[tokio::test]
async fn unknown_methods_add_no_series() {
    let app = two_token_app();
    scrape(&app).await; // a scrape is counted once it is answered: its series, before counting
    for path in ["/healthz", "/v1/render"] {
        let req = Request::builder().method("BREW").uri(path).body(Body::empty()).unwrap();
        send(app.clone(), req).await;
    }
    let before = request_series(&scrape(&app).await);
    for i in 0..1000 {
        for path in ["/healthz", "/v1/render"] {
            let req = Request::builder().method(format!("M{i:06}X").as_str()).uri(path).body(Body::empty()).unwrap();
            let got = send(app.clone(), req).await;
            assert!([401, 405].contains(&got.0.as_u16()), "{path}: {}", got.0);
        }
    }
    let m = scrape(&app).await;
    assert_eq!(request_series(&m), before, "{m}");
    let other = r#"route="/healthz",method="other",status="405""#;
    assert_eq!(sample(&m, "scnerf_http_requests_total", other), Some(1001.0), "{m}");
}
