//! Admission by memory over the fake runner: requests are admitted while their estimates fit the
//! budget together; beyond it 503 + Retry-After; a request that could never fit gets 422 naming
//! the sources' size before anything is decoded; /metrics shows the budget, the estimate in use
//! and the refusals.

mod common;

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use common::*;
use scnerf_server::backend::{ExecutorOptions, MemoryBudget};
use scnerf_server::bundle::{GraphKind, VolumeBuild};
use scnerf_server::http::{router, ServiceOptions};
use scnerf_server::pipeline::chunks::ChunkPolicy;
use scnerf_server::pipeline::estimate::{estimate, MemoryPlan, RequestSizes};
use scnerf_server::pipeline::volume::SlabPolicy;
use scnerf_server::request::Limits;
use scnerf_server::testing::{bundle, camera_json, png_header, request_json, state_with_executor, FakeRunner};

/// The estimate of `request_json(32)` (32x32 sources, an 8x6 target) on the fake bundle.
fn small_request_estimate() -> u64 {
    let b = bundle("scnerf", "near_far");
    let plan = MemoryPlan {
        build: VolumeBuild::Whole,
        slabs: SlabPolicy::default(),
        chunking: ChunkPolicy { max_rays: 100, memory_budget_bytes: usize::MAX },
    };
    estimate(&b.config, &plan, &RequestSizes::render(&b.config, (32, 32), 48))
}

/// A router whose executor may hold `total` bytes of estimates; each graph run takes `delay`.
type Calls = std::sync::Arc<[std::sync::atomic::AtomicUsize; GraphKind::ALL.len()]>;

fn app(total: u64, delay: Duration) -> (axum::Router, Calls) {
    let b = bundle("scnerf", "near_far");
    let mut runner = FakeRunner::new(&b);
    runner.delay = delay;
    let calls = runner.calls.clone();
    let executor = ExecutorOptions { memory: MemoryBudget { total, reserved: 0 }, ..ExecutorOptions::with_capacity(8) };
    let limits = Limits { max_source_pixels: 4096 * 4096, ..Limits::default() };
    let options = ServiceOptions { request_timeout: Duration::from_secs(60), ..Default::default() };
    (router(state_with_executor(b, runner, limits, options, executor)), calls)
}

fn sample(metrics: &str, key: &str) -> Option<f64> {
    metrics.lines().find_map(|l| l.strip_prefix(key)?.strip_prefix(' ')?.trim().parse().ok())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn admits_while_the_estimates_fit_then_503_with_retry_after() {
    let one = small_request_estimate();
    // Room for one request, not two.
    let (app, calls) = app(one * 3 / 2, Duration::from_millis(100));
    let first = tokio::spawn(send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[])));
    let start = Instant::now();
    while calls[GraphKind::Encoder.index()].load(Ordering::SeqCst) == 0 {
        assert!(start.elapsed() < Duration::from_secs(20), "the first request never started");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let second = send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[])).await;
    assert_error(&second, 503, "unavailable", None);
    assert!(second.1["retry-after"].to_str().unwrap().parse::<u64>().unwrap() >= 1);
    assert!(String::from_utf8_lossy(&second.2).contains("MiB"), "{:?}", second.2);

    let metrics = String::from_utf8(send(app.clone(), get("/metrics", &[])).await.2.to_vec()).unwrap();
    assert_eq!(sample(&metrics, "scnerf_memory_budget_bytes"), Some((one * 3 / 2) as f64), "{metrics}");
    assert_eq!(sample(&metrics, "scnerf_memory_admitted_bytes"), Some(one as f64), "{metrics}");
    assert_eq!(sample(&metrics, r#"scnerf_memory_refusals_total{reason="busy"}"#), Some(1.0), "{metrics}");

    assert_eq!(first.await.unwrap().0, 200);
    // The first one's estimate is released with it: the next request fits again.
    assert_eq!(send(app.clone(), multipart_with("/v1/render", &request_json(32), 32, &[])).await.0, 200);
    let metrics = String::from_utf8(send(app.clone(), get("/metrics", &[])).await.2.to_vec()).unwrap();
    assert_eq!(sample(&metrics, "scnerf_memory_admitted_bytes"), Some(0.0), "{metrics}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_that_can_never_fit_gets_422_naming_its_sources_before_decoding() {
    let (app, calls) = app(small_request_estimate() * 4, Duration::ZERO);
    // 2048x2048 sources whose PNGs only claim that size (decoding them would fail): the 422 is
    // about memory, so nothing was decoded.
    let mut req = request_json(32);
    for (i, x) in [-0.2, 0.0, 0.2].into_iter().enumerate() {
        req["sources"][i]["camera"] = camera_json(2048, 2048, x);
    }
    let (png, request) = (png_header(2048, 2048), serde_json::to_vec(&req).unwrap());
    let parts: [(&str, &[u8]); 4] = [("request", &request), ("source_0", &png), ("source_1", &png), ("source_2", &png)];
    let got = send(app.clone(), multipart_to("/v1/render", &parts, &[])).await;
    assert_error(&got, 422, "invalid_request", Some("sources"));
    let message = json_of(&got)["error"]["message"].as_str().unwrap().to_string();
    assert!(message.contains("3 source views of 2048x2048") && message.contains("MiB"), "{message}");
    assert_eq!(calls[GraphKind::Encoder.index()].load(Ordering::SeqCst), 0);

    let metrics = String::from_utf8(send(app.clone(), get("/metrics", &[])).await.2.to_vec()).unwrap();
    assert_eq!(sample(&metrics, r#"scnerf_memory_refusals_total{reason="too_large"}"#), Some(1.0), "{metrics}");
    // A request that fits is still served.
    assert_eq!(send(app, multipart_with("/v1/render", &request_json(32), 32, &[])).await.0, 200);
}

/// A scene cache full of idle scenes, for [`a_3000_mib_budget_admits_a_1024_view`].
struct IdleCache(std::sync::atomic::AtomicU64);

impl scnerf_server::backend::Reclaim for IdleCache {
    fn held(&self) -> u64 {
        self.0.load(Ordering::SeqCst)
    }

    fn reclaim(&self, bytes: u64) -> u64 {
        let held = self.held();
        let freed = bytes.min(held);
        self.0.store(held - freed, Ordering::SeqCst);
        freed
    }
}

/// With `--memory-budget-mb 3000` and no other flag, the scene cache takes a third of the budget,
/// and it is not set aside up front: a 1024x1024 view from 1024x1024 sources of the default
/// bundle is admitted with what the process holds at rest (its sessions loaded) and one renderer
/// run set aside, even while the cache is full, its idle scenes evicted to make room.
#[test]
fn a_3000_mib_budget_admits_a_1024_view() {
    use clap::Parser;
    use scnerf_server::backend::Work;
    use scnerf_server::config::Config;
    let config = Config::try_parse_from(["scnerf-server", "--memory-budget-mb", "3000"]).unwrap();
    assert_eq!(config.scene_cache_bytes(), 1000 << 20);
    let executor = config.executor_options();
    assert_eq!(executor.memory.total, 3000 << 20);
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../bundles/default");
    let limits = Limits { max_source_pixels: 1024 * 1024, ..Limits::default() };
    let pipeline = scnerf_server::testing::ort_pipeline_with(&dir, limits, executor);
    let at_rest = scnerf_server::sysmem::resident().map_or(0, |r| r.now);
    let reserved = pipeline.executor().reserve(at_rest + pipeline.renderer_run_bytes()).unwrap();
    let cache = std::sync::Arc::new(IdleCache((config.scene_cache_bytes() as u64).into()));
    pipeline.executor().set_reclaim(cache.clone());

    let bundle = scnerf_server::bundle::Bundle::load(&dir).unwrap();
    let plan = MemoryPlan { build: bundle.volume_build(), slabs: config.slabs(), chunking: config.chunking() };
    let view = estimate(&bundle.config, &plan, &RequestSizes::render(&bundle.config, (1024, 1024), 1024 * 1024));
    println!(
        "at rest {} MiB, reserved {} MiB, a 1024x1024 view {} MiB",
        at_rest >> 20,
        reserved.reserved >> 20,
        view >> 20
    );
    let due = Instant::now() + Duration::from_secs(60);
    let ticket = pipeline.admit(due, Work::default(), view).expect("a 1024x1024 view within a 3000 MiB budget");
    drop(ticket);
    // The cache's old default (2048 MiB) set aside up front left too little.
    assert!(view > (3000 << 20) - reserved.reserved - (2048 << 20));
    // A second view while the first renders: the cache's idle scenes make the room.
    let first = pipeline.admit(due, Work::default(), view).unwrap();
    let second = pipeline.admit(due, Work::default(), reserved.for_requests() - view);
    assert!(second.is_ok(), "{:?}", second.err());
    assert_eq!(cache.0.load(Ordering::SeqCst), 0, "the whole idle cache went for it");
    drop((first, second));
}
