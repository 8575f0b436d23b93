//! Eight concurrent renders through the real graphs (the parity fixture bundle: a size that fits
//! CI) under a memory budget that holds two of them: every request gets 200 or 503 (never
//! anything else, never a dead process), the process's peak resident set stays within the budget
//! above where it started, and a request that could never fit gets 422 naming its sources' size.
//! scripts/memory-concurrency.py runs the same check against the real server at paper size with
//! 800x800 sources.

use std::path::Path;

use axum::body::Body;
use axum::http::Request;
use http_body_util::BodyExt;
use scnerf_e2e::Case;
use scnerf_server::backend::{ExecutorOptions, MemoryBudget};
use scnerf_server::http::{router, ServiceOptions};
use scnerf_server::pipeline::chunks::ChunkPolicy;
use scnerf_server::pipeline::estimate::{estimate, MemoryPlan, RequestSizes};
use scnerf_server::pipeline::sources::padded_size;
use scnerf_server::pipeline::volume::SlabPolicy;
use scnerf_server::request::Limits;
use scnerf_server::sysmem;
use scnerf_server::testing::{ort_pipeline_with, ready_state};
use tower::ServiceExt;

const CONCURRENT: usize = 8;

async fn render(app: axum::Router, ctype: String, body: Vec<u8>) -> (u16, String) {
    let req = Request::post("/v1/render").header("content-type", ctype).body(Body::from(body)).unwrap();
    let resp = app.oneshot(req).await.unwrap();
    let status = resp.status().as_u16();
    let retry = resp.headers().get("retry-after").map(|v| v.to_str().unwrap().to_string());
    let bytes = resp.into_body().collect().await.unwrap().to_bytes();
    if status == 503 {
        assert!(retry.is_some(), "503 without Retry-After");
    }
    let text = if status == 200 { String::new() } else { String::from_utf8_lossy(&bytes).into_owned() };
    (status, text)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn eight_concurrent_renders_within_a_memory_budget() {
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/parity");
    let case_dir = std::fs::read_dir(fixtures.join("cases")).unwrap().next().unwrap().unwrap().path();
    let mut case = Case::load(&case_dir).unwrap();
    // Sampled in full: the estimate below is a full render's.
    case.request["sampling"] = serde_json::json!("full");
    let camera =
        |c: &serde_json::Value| (c["width"].as_u64().unwrap() as usize, c["height"].as_u64().unwrap() as usize);
    let (w, h) = camera(&case.request["sources"][0]["camera"]);
    let (tw, th) = camera(&case.request["target"]);

    // The budget holds two such requests' estimates, not three.
    let bundle = scnerf_server::bundle::Bundle::load(&fixtures.join("bundle")).unwrap();
    let plan =
        MemoryPlan { build: bundle.volume_build(), slabs: SlabPolicy::default(), chunking: ChunkPolicy::default() };
    let sizes = RequestSizes::render(&bundle.config, padded_size(w, h, 32), (tw * th) as u64);
    let one = estimate(&bundle.config, &plan, &sizes);
    let budget = one * 5 / 2;
    let executor =
        ExecutorOptions { memory: MemoryBudget { total: budget, reserved: 0 }, ..ExecutorOptions::with_capacity(32) };
    let pipeline = ort_pipeline_with(&fixtures.join("bundle"), Limits::default(), executor);
    let options = ServiceOptions { request_timeout: std::time::Duration::from_secs(600), ..Default::default() };
    let app = router(ready_state(pipeline, options));

    // One request first (sessions initialised, the renderer's arena grown): then the peak is reset
    // and the burst's peak measured from here.
    let (ctype, body) = case.multipart(&case.request);
    assert_eq!(render(app.clone(), ctype.clone(), body.clone()).await.0, 200);
    let rest = sysmem::resident().expect("Linux /proc").now;
    assert!(sysmem::reset_peak());

    let burst: Vec<_> =
        (0..CONCURRENT).map(|_| tokio::spawn(render(app.clone(), ctype.clone(), body.clone()))).collect();
    let mut statuses = Vec::new();
    for r in burst {
        let (status, text) = r.await.unwrap();
        assert!(matches!(status, 200 | 503), "status {status}: {text}");
        statuses.push(status);
    }
    let peak = sysmem::resident().unwrap().peak;
    let ok = statuses.iter().filter(|&&s| s == 200).count();
    eprintln!(
        "{CONCURRENT} concurrent: {ok} x 200, {} x 503; estimate {} MiB each, budget {} MiB; peak {} MiB above {} MiB at rest",
        CONCURRENT - ok,
        one >> 20,
        budget >> 20,
        peak.saturating_sub(rest) >> 20,
        rest >> 20
    );
    assert!(ok >= 1, "{statuses:?}");
    assert!(ok < CONCURRENT, "the budget holds two at once, all {CONCURRENT} were admitted: {statuses:?}");
    assert!(peak.saturating_sub(rest) <= budget, "peak {peak} above rest {rest} exceeds the budget {budget}");

    // Sources far larger than the budget allows: 422 naming their size.
    let mut huge = case.request.clone();
    for i in 0..3 {
        huge["sources"][i]["camera"]["width"] = 1024.into();
        huge["sources"][i]["camera"]["height"] = 1024.into();
    }
    let (ctype, body) = case.multipart(&huge);
    let (status, text) = render(app.clone(), ctype, body).await;
    assert_eq!(status, 422, "{text}");
    assert!(text.contains("3 source views of 1024x1024"), "{text}");
}
