//! What reaches the logs: the binary's JSON subscriber, request ids in every line of a request,
//! and no tokens or image data. Alone in its test binary: tracing caches per-callsite interest
//! process-wide, and tests running on other threads without this (thread-local) subscriber
//! would race with it.

mod common;

use std::io::Write;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::*;
use scnerf_server::config::LogFormat;
use scnerf_server::testing::request_json;
use serde_json::json;

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
}

/// The binary's JSON subscriber at TRACE: every line is a JSON object, request lines carry the
/// request id, and neither the token nor image data appear, even when a client puts them where
/// they do not belong.
#[tokio::test]
async fn logs_are_json_with_request_ids_and_carry_no_tokens_or_images() {
    let captured = Captured::default();
    let writer = captured.clone();
    let filter = tracing_subscriber::EnvFilter::new("trace");
    let subscriber = scnerf_server::logging::subscriber(LogFormat::Json, filter, move || writer.clone(), false);
    let _guard = tracing::subscriber::set_default(subscriber);

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
