//! What reaches the logs: the binary's JSON subscriber, request ids in every line of a request,
//! no tokens or image data, and the level of each response (refusals are not errors). Alone in its test binary: tracing caches per-callsite interest
//! process-wide, and tests running on other threads without this (thread-local) subscriber
//! would race with it.

mod common;

use std::io::Write;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::*;
use scnerf_server::config::LogFormat;
use scnerf_server::http::{router, ServiceOptions};
use scnerf_server::request::Limits;
use scnerf_server::testing::{bundle, request_json, state_with_options, FakeRunner};
use serde_json::{json, Value};
use tracing::subscriber::DefaultGuard;

/// A `MakeWriter` into a shared buffer.
#[derive(Clone, Default)]
struct Captured(Arc<Mutex<Vec<u8>>>);

impl Write for Captured {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Captured {
    fn text(&self) -> String {
        String::from_utf8_lossy(&self.0.lock().unwrap()).into_owned()
    }

    /// The binary's JSON subscriber at TRACE, writing here, for this thread until the guard drops.
    fn install(&self) -> DefaultGuard {
        let writer = self.clone();
        let filter = tracing_subscriber::EnvFilter::new("trace");
        let subscriber = scnerf_server::logging::subscriber(LogFormat::Json, filter, move || writer.clone(), false);
        tracing::subscriber::set_default(subscriber)
    }
}

/// The binary's JSON subscriber at TRACE: every line is a JSON object, request lines carry the
/// request id, and neither the token nor image data appear, even when a client puts them where
/// they do not belong.
#[tokio::test]
async fn logs_are_json_with_request_ids_and_carry_no_tokens_or_images() {
    let captured = Captured::default();
    let _guard = captured.install();

    let app = two_token_app();
    let alice = bearer(ALICE);
    let headers = [("authorization", alice.as_str()), ("x-request-id", "req-0042")];
    assert_eq!(send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &headers)).await.0, 200);
    let image_b64 = b64(&images(32)[0]);
    // An image and the token pasted into number fields: refused, and echoed only clipped.
    let mut bad = json_with_images(32);
    bad["near"] = json!(image_b64);
    let got = send(app.clone(), json_to("/v1/render", &bad, &[("authorization", &alice)])).await;
    assert_error(&got, 400, "malformed_request", Some("near"));
    assert!(!String::from_utf8_lossy(&got.2).contains(&image_b64[..64]));
    let mut bad = request_json(32);
    bad["far"] = json!(BOB);
    let got = send(app.clone(), multipart_with("/v1/render", &bad, 32, &[("authorization", &alice)])).await;
    assert_error(&got, 400, "malformed_request", Some("far"));
    let got = send(
        app.clone(),
        multipart_with("/v1/render", &request_json(32), 32, &[("authorization", &bearer("mallory-secret"))]),
    )
    .await;
    assert_eq!(got.0, 401);
    tokio::time::sleep(Duration::from_millis(50)).await;

    let logs = captured.text();
    assert!(logs.lines().count() >= 4, "{logs}");
    for line in logs.lines() {
        serde_json::from_str::<serde_json::Value>(line).unwrap_or_else(|e| panic!("not JSON ({e}): {line}"));
    }
    assert!(logs.lines().any(|l| l.contains("\"request_id\":\"req-0042\"")), "{logs}");
    let rendered = logs.lines().find(|l| l.contains("\"message\":\"rendered\"")).expect("a rendered line");
    assert!(rendered.contains("\"request_id\":\"req-0042\""), "events inside a request carry its id: {rendered}");
    for secret in [ALICE, BOB, "mallory-secret", &image_b64[..40]] {
        assert!(!logs.contains(secret), "{secret} leaked into the logs:\n{logs}");
    }
}

/// Refusals are the API working as documented, not failures: a warming server's `/readyz` 503
/// and a 404 for a scene the server does not hold are logged at DEBUG, while a failure of the
/// server (a graph run that fails: 500) is logged at ERROR.
#[tokio::test]
async fn refusals_are_not_logged_as_errors_and_failures_are() {
    let captured = Captured::default();
    let _guard = captured.install();
    let b = bundle("scnerf", "near_far");
    let runner = FakeRunner { fail_with: Some("the graph broke".into()), ..FakeRunner::new(&b) };
    let state = state_with_options(b, runner, Limits::default(), ServiceOptions::default(), 8);
    let app = router(state.clone());

    state.set_draining();
    assert_eq!(send(app.clone(), get("/readyz", &[])).await.0, 503);
    state.set_ready();
    let missing = send(app.clone(), json_to("/v1/scenes/nowhere/render", &target_json(32), &[])).await;
    assert_error(&missing, 404, "scene_not_found", Some("scene_id"));
    assert_eq!(send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[])).await.0, 500);

    let logs = captured.text();
    let lines: Vec<Value> = logs.lines().map(|l| serde_json::from_str(l).expect("JSON")).collect();
    let response_level = |path: &str| {
        let line = lines
            .iter()
            .find(|l| l["fields"]["message"] == "response" && l["span"]["path"] == path)
            .unwrap_or_else(|| panic!("no response line for {path}:\n{logs}"));
        line["level"].as_str().unwrap().to_string()
    };
    assert_eq!(response_level("/readyz"), "DEBUG");
    assert_eq!(response_level("/v1/scenes/nowhere/render"), "DEBUG");
    assert_eq!(response_level("/v1/render"), "ERROR");
    for line in lines.iter().filter(|l| l["level"] == "ERROR" || l["level"] == "WARN") {
        assert_eq!(line["span"]["path"], "/v1/render", "only the failed render warns:\n{logs}");
    }
}

/// A corrupt bundle found by a reload is skipped with a warning that names its folder and the
/// reason, and the server keeps serving.
#[tokio::test]
async fn a_skipped_bundle_is_logged_with_its_reason() {
    use scnerf_server::testing::{models_state, FakeModel};
    let captured = Captured::default();
    let _guard = captured.install();
    let dir = std::env::temp_dir().join(format!("scnerf-logging-{}", std::process::id()));
    let broken = dir.join("broken");
    std::fs::create_dir_all(&broken).unwrap();
    std::fs::write(broken.join("manifest.json"), "not json").unwrap();
    let state = models_state(vec![FakeModel::new("lego", 1.0)], None, Some(&dir), ServiceOptions::default()).unwrap();
    let app = router(state);
    let got = send(app.clone(), raw_to("POST", "/v1/models/reload", "application/json", vec![], &[])).await;
    assert_eq!(got.0, 200);
    let warning = captured
        .text()
        .lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap())
        .find(|l| l["fields"]["message"] == "bundle skipped")
        .unwrap_or_else(|| panic!("no warning:\n{}", captured.text()));
    assert_eq!(warning["level"], "WARN");
    assert_eq!(warning["fields"]["path"], broken.display().to_string());
    assert!(warning["fields"]["reason"].as_str().unwrap().contains("not a valid manifest"), "{warning}");
    assert_eq!(send(app, multipart_with("/v1/render", &request_json(32), 32, &[])).await.0, 200);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The binary's text subscriber escapes control characters in fields and messages: a folder's
/// name or a manifest's text with a newline cannot end its line and forge another module's.
#[test]
fn text_logs_escape_what_could_forge_a_line() {
    let captured = Captured::default();
    let writer = captured.clone();
    let filter = tracing_subscriber::EnvFilter::new("trace");
    let subscriber = scnerf_server::logging::subscriber(LogFormat::Text, filter, move || writer.clone(), false);
    let forged = "lego\n2026-01-01T00:00:00.000000Z  INFO scnerf_server::auth: token accepted\r\u{1b}[2K";
    tracing::subscriber::with_default(subscriber, || {
        let span = tracing::info_span!("request", path = %forged);
        let _entered = span.enter();
        tracing::warn!(path = %forged, reason = forged, "bundle skipped: {forged}");
    });
    let text = captured.text();
    assert_eq!(text.lines().count(), 1, "{text}");
    assert!(!text.contains('\r') && !text.contains('\u{1b}'), "{text:?}");
    assert_eq!(text.matches("lego\\n2026").count(), 4, "span, field, quoted field, message: {text}");
}
