//! Bearer-token authentication, per-token scene visibility, and what reaches the logs.

mod common;

use axum::body::Body;
use axum::http::Request;
use common::*;
use scnerf_server::testing::request_json;

#[tokio::test]
async fn requests_without_a_valid_token_are_401() {
    let app = two_token_app();
    let render = |headers: &[(&str, &str)]| multipart_with("/v1/render", &request_json(32), 32, headers);
    let cases: [(&str, Option<String>); 5] = [
        ("no header", None),
        ("wrong token", Some(bearer("mallory"))),
        ("prefix of a token", Some(bearer(&ALICE[..10]))),
        ("basic auth", Some(format!("Basic {}", b64(format!("alice:{ALICE}").as_bytes())))),
        ("empty bearer", Some("Bearer ".into())),
    ];
    for (what, header) in cases {
        let headers: Vec<(&str, &str)> = header.iter().map(|h| ("authorization", h.as_str())).collect();
        let got = send(app.clone(), render(&headers)).await;
        assert_error(&got, 401, "unauthorized", Some("authorization"));
        assert!(got.1["www-authenticate"].to_str().unwrap().starts_with("Bearer"), "{what}");
    }
    let got = send(app.clone(), render(&[("authorization", &bearer(ALICE))])).await;
    assert_eq!(got.0, 200, "{}", String::from_utf8_lossy(&got.2));
    let got = send(app.clone(), render(&[("authorization", &format!("bearer {BOB}"))])).await;
    assert_eq!(got.0, 200, "the scheme is case-insensitive");
    // Other protected routes.
    assert_error(&send(app.clone(), get("/v1/model", &[])).await, 401, "unauthorized", Some("authorization"));
    let del = Request::delete("/v1/scenes/0123456789abcdef0123456789abcdef").body(Body::empty()).unwrap();
    assert_error(&send(app.clone(), del).await, 401, "unauthorized", Some("authorization"));
    assert_error(&send(app, get("/v2/anything", &[])).await, 401, "unauthorized", Some("authorization"));
}

#[tokio::test]
async fn health_metrics_and_openapi_stay_public() {
    let app = two_token_app();
    for path in ["/healthz", "/readyz", "/metrics", "/openapi.json"] {
        assert_eq!(send(app.clone(), get(path, &[])).await.0, 200, "{path}");
    }
    // Public, so it names no model (/v1/model does, with a token).
    let ready = send(app, get("/readyz", &[])).await;
    assert_eq!(json_of(&ready), serde_json::json!({"status": "ready"}));
}

#[tokio::test]
async fn a_scene_is_visible_only_to_the_token_that_created_it() {
    let app = two_token_app();
    let alice = bearer(ALICE);
    let bob = bearer(BOB);
    let got = send(app.clone(), multipart_with("/v1/scenes", &scene_json(32), 32, &[("authorization", &alice)])).await;
    assert_eq!(got.0, 201);
    let id = json_of(&got)["scene_id"].as_str().unwrap().to_string();
    let path = format!("/v1/scenes/{id}/render");
    let got = send(app.clone(), json_to(&path, &target_json(32), &[("authorization", &bob)])).await;
    assert_error(&got, 404, "scene_not_found", Some("scene_id"));
    let del = Request::delete(format!("/v1/scenes/{id}")).header("authorization", &bob).body(Body::empty()).unwrap();
    assert_error(&send(app.clone(), del).await, 404, "scene_not_found", Some("scene_id"));
    let got = send(app.clone(), json_to(&path, &target_json(32), &[("authorization", &alice)])).await;
    assert_eq!(got.0, 200, "bob's delete must not have removed alice's scene");
    let del = Request::delete(format!("/v1/scenes/{id}")).header("authorization", &alice).body(Body::empty()).unwrap();
    assert_eq!(send(app, del).await.0, 204);
}
