//! Prometheus metrics (`GET /metrics`, OpenMetrics text format) with `prometheus-client`.
//!
//! No global recorder: each `AppState` owns its `Metrics` (its own registry), so tests run
//! side by side without sharing counters. Queue and cache figures are read from their owners at
//! scrape time (a `Collector`), so they cannot drift from the truth.

use std::sync::Arc;
use std::time::Duration;

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeLabelSet, EncodeMetric};
use prometheus_client::metrics::counter::{ConstCounter, Counter};
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::{Registry, Unit};

use crate::backend::BackendHandle;
use crate::cache::SceneCache;
use crate::models::Model;
use crate::pipeline::scene::SamplingReport;
use crate::pipeline::scene::Timings;
use crate::sysmem;

/// Content type of the exposition format written by `Metrics::render`.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RequestLabels {
    /// The route template (`/v1/scenes/{id}/render`), never the raw path: bounded cardinality.
    route: String,
    /// One of [`METHODS`] or `other`: a client may send any token as a method.
    method: &'static str,
    status: u16,
}

/// The methods counted by name (RFC 9110's and PATCH); any other is counted as `other`.
const METHODS: [&str; 9] = ["GET", "HEAD", "POST", "PUT", "DELETE", "CONNECT", "OPTIONS", "TRACE", "PATCH"];

/// A method as a label value from a fixed set.
fn method_label(method: &str) -> &'static str {
    METHODS.into_iter().find(|m| *m == method).unwrap_or("other")
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RouteLabels {
    route: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StageLabels {
    stage: String,
    /// A served model's name (`models::Model::name`), never text from a request: the label's
    /// values are the configured models.
    model: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct SamplingLabels {
    sampling: String,
    model: String,
}

type HistogramFamily<L> = Family<L, Histogram, fn() -> Histogram>;

/// Network samples per pixel of a view: 1 .. 256 in factors of 2 (full sampling: the model's S).
fn samples_histogram() -> Histogram {
    Histogram::new(exponential_buckets(1.0, 2.0, 9))
}

/// Request latencies: 1 ms .. ~9 min in factors of 2 (CPU renders take seconds to minutes).
fn latency_histogram() -> Histogram {
    Histogram::new(exponential_buckets(0.001, 2.0, 20))
}

pub struct Metrics {
    registry: Registry,
    requests: Family<RequestLabels, Counter>,
    request_seconds: HistogramFamily<RouteLabels>,
    stage_seconds: HistogramFamily<StageLabels>,
    samples_per_ray: HistogramFamily<SamplingLabels>,
}

impl Metrics {
    pub fn new(backend: BackendHandle, scenes: Arc<SceneCache>) -> Metrics {
        let mut registry = Registry::with_prefix("scnerf");
        let requests = Family::<RequestLabels, Counter>::default();
        registry.register("http_requests", "HTTP requests by route, method and status", requests.clone());
        let request_seconds: HistogramFamily<RouteLabels> = Family::new_with_constructor(latency_histogram);
        registry.register_with_unit(
            "http_request_duration",
            "HTTP request latency by route, until the response head",
            Unit::Seconds,
            request_seconds.clone(),
        );
        let stage_seconds: HistogramFamily<StageLabels> = Family::new_with_constructor(latency_histogram);
        registry.register_with_unit(
            "stage_duration",
            "Render pipeline stage latency (decode, encoder, volume, renderer, assemble, encode)",
            Unit::Seconds,
            stage_seconds.clone(),
        );
        let samples_per_ray: HistogramFamily<SamplingLabels> = Family::new_with_constructor(samples_histogram);
        registry.register(
            "samples_per_ray",
            "Network samples per pixel of each rendered view, by sampling (full, guided); the count is the views",
            samples_per_ray.clone(),
        );
        registry.register_collector(Box::new(StateCollector { backend, scenes }));
        Metrics { registry, requests, request_seconds, stage_seconds, samples_per_ray }
    }

    pub fn observe_request(&self, route: &str, method: &str, status: u16, elapsed: Duration) {
        let labels = RequestLabels { route: route.to_string(), method: method_label(method), status };
        self.requests.get_or_create(&labels).inc();
        self.request_seconds.get_or_create(&RouteLabels { route: route.to_string() }).observe(elapsed.as_secs_f64());
    }

    /// Records the stages of a finished request of `model` (`total` is the request histogram's job).
    pub fn observe_stages(&self, model: &Model, timings: &Timings) {
        for (stage, d) in timings.0.iter().filter(|(s, _)| *s != "total") {
            let labels = StageLabels { stage: stage.to_string(), model: model.name.to_string() };
            self.stage_seconds.get_or_create(&labels).observe(d.as_secs_f64());
        }
    }

    /// Records how a view of `model` was sampled.
    pub fn observe_sampling(&self, model: &Model, report: &SamplingReport) {
        let labels = SamplingLabels { sampling: report.mode.name().to_string(), model: model.name.to_string() };
        self.samples_per_ray.get_or_create(&labels).observe(report.samples_per_ray);
    }

    pub fn render(&self) -> String {
        let mut out = String::new();
        // Writing into a String cannot fail.
        let _ = prometheus_client::encoding::text::encode(&mut out, &self.registry);
        out
    }
}

/// Executor queue and scene cache figures, read at scrape time.
struct StateCollector {
    backend: BackendHandle,
    scenes: Arc<SceneCache>,
}

impl std::fmt::Debug for StateCollector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("StateCollector")
    }
}

fn gauge(encoder: &mut DescriptorEncoder, name: &str, help: &str, value: i64) -> Result<(), std::fmt::Error> {
    let metric = ConstGauge::new(value);
    metric.encode(encoder.encode_descriptor(name, help, None, metric.metric_type())?)
}

fn counter(encoder: &mut DescriptorEncoder, name: &str, help: &str, value: u64) -> Result<(), std::fmt::Error> {
    let metric = ConstCounter::new(value);
    metric.encode(encoder.encode_descriptor(name, help, None, metric.metric_type())?)
}

/// One metric with a value per label set.
fn family<L: EncodeLabelSet, M: EncodeMetric>(
    encoder: &mut DescriptorEncoder,
    name: &str,
    help: &str,
    values: &[(L, M)],
) -> Result<(), std::fmt::Error> {
    let Some((_, first)) = values.first() else { return Ok(()) };
    let mut metric = encoder.encode_descriptor(name, help, None, first.metric_type())?;
    for (labels, value) in values {
        value.encode(metric.encode_family(labels)?)?;
    }
    Ok(())
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ReasonLabels {
    reason: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StageName {
    stage: &'static str,
}

impl Collector for StateCollector {
    fn encode(&self, mut e: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let q = self.backend.stats();
        let c = self.scenes.stats();
        let n = |v: usize| i64::try_from(v).unwrap_or(i64::MAX);
        gauge(&mut e, "inference_queue_requests", "Requests admitted to the inference executor", n(q.admitted))?;
        gauge(&mut e, "inference_queue_jobs", "Graph runs waiting for the inference executor", n(q.queued_jobs))?;
        gauge(&mut e, "inference_queue_capacity", "Requests the executor admits at once", n(q.capacity))?;
        let bytes = |v: u64| i64::try_from(v).unwrap_or(i64::MAX);
        gauge(&mut e, "memory_budget_bytes", "Memory the process may use (--memory-budget-mb)", bytes(q.memory.total))?;
        gauge(
            &mut e,
            "memory_reserved_bytes",
            "Part of the budget held apart from requests: the process at rest and the scene cache",
            bytes(q.memory.reserved),
        )?;
        gauge(
            &mut e,
            "memory_admitted_bytes",
            "Sum of the estimated peak memory of the requests admitted now",
            bytes(q.memory_in_use - q.memory_leased),
        )?;
        gauge(
            &mut e,
            "memory_leased_bytes",
            "Memory held against the budget beside the admitted requests: bodies as they arrive, captures being parsed",
            bytes(q.memory_leased),
        )?;
        let refusals = [
            (ReasonLabels { reason: "busy" }, ConstCounter::new(q.refusals.busy)),
            (ReasonLabels { reason: "too_large" }, ConstCounter::new(q.refusals.too_large)),
        ];
        family(
            &mut e,
            "memory_refusals",
            "Requests refused for memory: busy (503, the budget is in use), too_large (422, larger than the budget)",
            &refusals,
        )?;
        if let Some(r) = sysmem::resident() {
            gauge(&mut e, "process_resident_bytes", "Resident set of the process", bytes(r.now))?;
            gauge(&mut e, "process_peak_resident_bytes", "Peak resident set of the process (VmHWM)", bytes(r.peak))?;
        }
        if let Some(probe) = self.backend.probe() {
            let stages = probe.stages();
            let peaks: Vec<_> =
                stages.iter().map(|(stage, m)| (StageName { stage }, ConstGauge::new(bytes(m.peak)))).collect();
            let after: Vec<_> =
                stages.iter().map(|(stage, m)| (StageName { stage }, ConstGauge::new(bytes(m.after)))).collect();
            family(
                &mut e,
                "stage_peak_resident_bytes",
                "--memory-probe: the process's peak resident set while the stage ran (largest over its runs)",
                &peaks,
            )?;
            family(
                &mut e,
                "stage_resident_after_bytes",
                "--memory-probe: the process's resident set after the stage's latest run",
                &after,
            )?;
        }
        gauge(&mut e, "scene_cache_entries", "Scenes in the cache", n(c.entries))?;
        gauge(
            &mut e,
            "scene_cache_bytes",
            "Memory held by cached scenes, their triples' volumes included",
            n(c.bytes),
        )?;
        counter(&mut e, "scene_cache_hits", "Scene lookups that found the scene", c.hits)?;
        counter(&mut e, "scene_cache_misses", "Scene lookups for unknown, expired or other clients' scenes", c.misses)?;
        counter(&mut e, "scene_cache_evictions", "Scenes evicted to stay within the byte limit", c.evictions)?;
        counter(&mut e, "scene_cache_expirations", "Scenes dropped after their idle TTL", c.expirations)?;
        gauge(&mut e, "volume_cache_entries", "Volumes of source triples cached in scenes", n(c.volumes))?;
        gauge(
            &mut e,
            "volume_cache_bytes",
            "Memory held by cached volumes (part of scene_cache_bytes)",
            n(c.volume_bytes),
        )?;
        counter(&mut e, "volume_cache_hits", "Scene renders whose sources' volume was cached", c.volume_hits)?;
        counter(&mut e, "volume_cache_misses", "Scene renders that built their sources' volume", c.volume_misses)?;
        counter(&mut e, "volume_cache_evictions", "Volumes evicted to stay within the byte limit", c.volume_evictions)?;
        Ok(())
    }
}
