//! Command line and environment configuration: one clap struct, every flag also `SCNERF_*`.
//! The parts of the server take their settings from it (`limits`, `chunking`, ...); each
//! setting's default lives with the part that uses it (its `Default`), and the flag shows it.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use clap::{Parser, ValueEnum};

use crate::auth::Auth;
use crate::backend::device::{Device, GraphOptLevel};
use crate::backend::ort::{ExecOptions, OrtOptions};
use crate::backend::{ExecutorOptions, MemoryBudget};
use crate::cache::{CacheConfig, Clock};
use crate::http::body::UploadPolicy;
use crate::http::serve::ServeOptions;
use crate::http::ServiceOptions;
use crate::models::{Deadlines, ModelSettings};
use crate::pipeline::band::BandFill;
use crate::pipeline::chunks::ChunkPolicy;
use crate::pipeline::volume::SlabPolicy;
use crate::request::Limits;
use crate::request::Sampling;
use crate::sysmem;

mod parts;

/// Where the server looks for the default bundle when `--bundle` is not given: the repository's
/// `bundles/default`, resolved when the binary is compiled (the binary is built from the repo).
pub fn default_bundle_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../bundles/default"))
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LogFormat {
    Text,
    Json,
}

#[derive(Debug, Clone, Parser)]
#[command(name = "scnerf-server", version, about = "SC-NeRF novel-view inference server")]
pub struct Config {
    /// Bundle directory (manifest.json + ONNX graphs): a model, named by the folder's name.
    /// Repeatable (`SCNERF_BUNDLE=a:b`). Default, without --bundle and --models:
    /// <repo>/bundles/default.
    #[arg(long, env = "SCNERF_BUNDLE", value_delimiter = ':')]
    pub bundle: Vec<PathBuf>,

    /// Serve every bundle folder below DIR too (a folder with a manifest.json, each named by its
    /// folder), and load new ones on `POST /v1/models/reload`. An invalid bundle found there is
    /// skipped with a warning; an invalid --bundle fails the start.
    #[arg(long, env = "SCNERF_MODELS")]
    pub models: Option<PathBuf>,

    /// Deadline of a search of --models (the scan, and reading and hashing the new bundles), at
    /// start and on each reload: the folders not verified by then are skipped.
    #[arg(long, env = "SCNERF_MODELS_TIMEOUT_SECS", default_value_t = 120)]
    pub models_timeout_secs: u64,

    /// Deadline of each model's warm-up render: a model that misses it is not served.
    #[arg(long, env = "SCNERF_WARMUP_TIMEOUT_SECS", default_value_t = 30)]
    pub warmup_timeout_secs: u64,

    /// The model of requests that name none (a model's name). Default: the first --bundle, else
    /// the first bundle folder of --models by path.
    #[arg(long, env = "SCNERF_DEFAULT_MODEL")]
    pub default_model: Option<String>,

    /// Address to listen on. Port 0 picks a free port; the bound address is printed on stdout
    /// as `listening on http://ADDR`.
    #[arg(long, env = "SCNERF_ADDR", default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,

    /// Intra-op threads of ONNX Runtime (one pool shared by all graphs).
    /// Default: the CPUs this process may use (respects container limits).
    #[arg(long, env = "SCNERF_THREADS")]
    pub threads: Option<usize>,

    /// ONNX Runtime graph optimisation level.
    #[arg(long, env = "SCNERF_GRAPH_OPT_LEVEL", value_enum, default_value = "all")]
    pub graph_opt_level: GraphOptLevel,

    /// Path of libonnxruntime.so (1.31.x). Default: next to the executable, then
    /// <repo>/third_party/onnxruntime/ (filled by scripts/fetch-onnxruntime.sh).
    #[arg(long, env = "SCNERF_ORT_DYLIB")]
    pub ort_dylib: Option<PathBuf>,

    /// Where the graphs run: cpu, cuda or cuda:N. cuda needs the onnxruntime-gpu 1.31.1 library
    /// (--ort-dylib) and its CUDA 13 / cuDNN 9 libraries; start-up fails if it cannot be used.
    #[arg(long, env = "SCNERF_DEVICE", default_value = "cpu")]
    pub device: Device,

    /// ONNX Runtime's CPU memory arena for the renderer graphs, one shared by every model's
    /// (on: a chunk's buffers are kept for the next chunk, full, guide or fine, and released
    /// after a request's last chunk when nothing else waits; off: returned to the allocator after
    /// every chunk). The encoder and the volume's graphs, which run once per request, never keep
    /// theirs. Accepts on/off, true/false.
    #[arg(long, env = "SCNERF_ORT_ARENA", default_value = "on", action = clap::ArgAction::Set,
          value_parser = clap::builder::BoolishValueParser::new())]
    pub ort_arena: bool,

    /// Whether ONNX Runtime's idle intra-op workers spin before sleeping. On: each of the
    /// renderer's few hundred operators per run starts without waking threads (measured 5-10%
    /// faster, docs/results.md), at the price of busy workers for a moment after each
    /// run; off for machines shared with other work. Accepts on/off, true/false.
    #[arg(long, env = "SCNERF_ORT_SPIN", default_value = "on", action = clap::ArgAction::Set,
          value_parser = clap::builder::BoolishValueParser::new())]
    pub ort_spin: bool,

    /// How views are sampled when a request does not say (`sampling` in the request): `guided`
    /// (coarse to fine, the network near the surface only; docs/api.md) or `full` (the paper's
    /// uniform samples on every ray). A bundle without guided-sampling graphs renders full.
    #[arg(long, env = "SCNERF_SAMPLING", value_enum, default_value_t = Sampling::Guided)]
    pub sampling: Sampling,

    /// What colours the pixels whose surface some of the sources do not see: `sources` (where
    /// the network renders them too dark, the dark band along the edges of forward-facing views,
    /// the mean colour of the sources that see them) or `network` (the model's own colour, as the
    /// paper renders it: for parity with the reference code). docs/design.md, "The band".
    #[arg(long, env = "SCNERF_BAND", value_enum, default_value_t = BandFill::Sources)]
    pub band: BandFill,

    /// Upper bound on rays per renderer run. Small runs keep the activations in cache: 512 rays
    /// rendered the default bundle faster than 4096 with a fifth to three fifths of the memory
    /// (docs/results.md, "What made the server faster").
    #[arg(long, env = "SCNERF_MAX_RAYS_PER_CHUNK", default_value_t = ChunkPolicy::default().max_rays)]
    pub max_rays_per_chunk: usize,

    /// Memory budget of one renderer run in MiB; the chunk size is derived from it and the
    /// bundle's samples per ray (see pipeline::chunks).
    #[arg(long, env = "SCNERF_CHUNK_MEMORY_MB", default_value_t = ChunkPolicy::default().memory_budget_bytes >> 20)]
    pub chunk_memory_mb: usize,

    /// Working memory of one cost-volume slab run in MiB, for bundles that build the volume slab
    /// by slab (cost_slab.onnx): the planes per run are derived from it and the sources' size
    /// (see pipeline::volume).
    #[arg(long, env = "SCNERF_VOLUME_SLAB_MB", default_value_t = SlabPolicy::default().memory_budget_bytes >> 20)]
    pub volume_slab_mb: usize,

    /// Largest accepted request body in bytes.
    #[arg(long, env = "SCNERF_MAX_BODY_BYTES", default_value_t = Limits::default().max_body_bytes)]
    pub max_body_bytes: usize,

    /// Largest accepted source image, in pixels (width x height), checked before decoding.
    /// Memory grows with it: a server given one scene of 800x800 sources peaks near 811 MiB
    /// (docs/results.md).
    #[arg(long, env = "SCNERF_MAX_SOURCE_PIXELS", default_value_t = Limits::default().max_source_pixels)]
    pub max_source_pixels: u64,

    /// Largest accepted target view, in pixels (width x height).
    #[arg(long, env = "SCNERF_MAX_TARGET_PIXELS", default_value_t = Limits::default().max_target_pixels)]
    pub max_target_pixels: u64,

    /// Largest JSON document without images, in bytes: the multipart `request` part,
    /// scene-render bodies and a capture's listing (`POST /v1/captures/plan`) (413 beyond).
    #[arg(long, env = "SCNERF_MAX_JSON_BYTES", default_value_t = Limits::default().max_json_bytes)]
    pub max_json_bytes: usize,

    /// Deepest accepted nesting of JSON arrays and objects (400 beyond). Valid requests nest 7 deep.
    #[arg(long, env = "SCNERF_MAX_JSON_DEPTH", default_value_t = Limits::default().max_json_depth)]
    pub max_json_depth: usize,

    /// Most views a scene may hold (POST /v1/scenes with a whole capture; at least 3). Each view
    /// is kept decoded (3 x W x H float32); per target the server renders from the 3 nearest.
    #[arg(long, env = "SCNERF_MAX_SCENE_VIEWS", default_value_t = Limits::default().max_scene_views as u64,
          value_parser = clap::value_parser!(u64).range(3..=4096))]
    pub max_scene_views: u64,

    /// Largest body of POST /v1/captures (a capture folder's files), in bytes (413 beyond).
    #[arg(long, env = "SCNERF_MAX_CAPTURE_BYTES", default_value_t = Limits::default().max_capture_bytes)]
    pub max_capture_bytes: usize,

    /// Most bytes of a capture's files that are not images (transforms*.json, COLMAP models,
    /// poses_bounds.npy, DTU cameras), in all (413 naming the file beyond): the readers parse
    /// them in memory, and real captures keep them small.
    #[arg(long, env = "SCNERF_MAX_CAPTURE_METADATA_BYTES", default_value_t = Limits::default().max_capture_metadata_bytes)]
    pub max_capture_metadata_bytes: usize,

    /// Memory for cached scenes (POST /v1/scenes), in MiB; least recently used scenes are evicted
    /// beyond it. A paper-size scene of 640x512 sources takes ~150 MiB. What the cache holds
    /// counts against --memory-budget-mb as it holds it, and idle scenes are evicted to admit a
    /// request. Default: a third of the memory budget (2048 MiB without one).
    #[arg(long, env = "SCNERF_SCENE_CACHE_MB")]
    pub scene_cache_mb: Option<usize>,

    /// Each token's share of the scene cache, in MiB. A token over its share makes room from
    /// its own scenes first, and never evicts another token's scenes while that token holds no
    /// more than its share. Default: an equal share (--scene-cache-mb divided by the number of
    /// tokens); without auth every client shares the one cache.
    #[arg(long, env = "SCNERF_SCENE_CACHE_MB_PER_TOKEN")]
    pub scene_cache_mb_per_token: Option<usize>,

    /// A cached scene expires this many seconds after its last use.
    #[arg(long, env = "SCNERF_SCENE_TTL_SECS", default_value_t = CacheConfig::default().ttl.as_secs())]
    pub scene_ttl_secs: u64,

    /// Per-request deadline in seconds (body, decoding, inference, encoding); past it the request
    /// fails with 504 and its remaining graph runs are dropped. A client may ask for less with
    /// the `x-scnerf-deadline-ms` header.
    #[arg(long, env = "SCNERF_REQUEST_TIMEOUT_SECS", default_value_t = ServiceOptions::default().request_timeout.as_secs())]
    pub request_timeout_secs: u64,

    /// The longest a request without `x-scnerf-deadline-ms` may expect to wait for the inference
    /// executor, or its own expected service time when that is longer: with more work admitted
    /// ahead of it, it is refused at once with 429 + Retry-After (a request with the header may
    /// wait as long as its deadline allows). Without it such a request has the whole
    /// --request-timeout-secs, and an overloaded server queues it for minutes. 1 s keeps work
    /// waiting for the executor (goodput holds) while an admitted view waits at most about a
    /// second, or one render of its own (docs/results.md, "Overload").
    #[arg(long, env = "SCNERF_MAX_QUEUE_WAIT_SECS", default_value_t = 1.0, value_parser = non_negative_secs)]
    pub max_queue_wait_secs: f64,

    /// Requests admitted to the inference executor at once (rendering, or waiting for their turn
    /// in the round-robin over requests); beyond it new requests get 503 + Retry-After.
    #[arg(long, env = "SCNERF_QUEUE_CAPACITY", default_value_t = 32)]
    pub queue_capacity: usize,

    /// Memory the whole process may use, in MiB: what it holds at rest (measured after the
    /// warm-up), what the scene cache holds (its idle scenes evicted to admit a request) and the
    /// estimated peaks of the requests in progress. A request that would exceed it waits for none: 503 + Retry-After; one that could
    /// never fit: 422. Default: 3/4 of the cgroup's memory limit, or of physical memory.
    #[arg(long, env = "SCNERF_MEMORY_BUDGET_MB")]
    pub memory_budget_mb: Option<u64>,

    /// Measure each stage's memory (the process's peak resident set while a graph runs or the
    /// sources are decoded, and what it holds after), served in /metrics as
    /// scnerf_stage_peak_resident_bytes and scnerf_stage_resident_after_bytes. A diagnostic: exact
    /// only with one request at a time. Accepts on/off, true/false.
    #[arg(long, env = "SCNERF_MEMORY_PROBE", default_value = "off", action = clap::ArgAction::Set,
          value_parser = clap::builder::BoolishValueParser::new())]
    pub memory_probe: bool,

    /// POST requests handled at once (their bodies are in memory meanwhile); beyond it 503 +
    /// Retry-After before the body is read.
    #[arg(long, env = "SCNERF_MAX_CONCURRENT_REQUESTS", default_value_t = ServiceOptions::default().max_concurrent_requests)]
    pub max_concurrent_requests: usize,

    /// POST requests handled at once from one client (peer IP address); beyond it 429 +
    /// Retry-After, so that one source cannot hold every slot. 0: no per-client cap (behind a
    /// reverse proxy every request comes from the proxy's address).
    #[arg(long, env = "SCNERF_MAX_REQUESTS_PER_CLIENT", default_value_t = ServiceOptions::default().max_requests_per_client)]
    pub max_requests_per_client: usize,

    /// Time any request body may take to arrive, whatever its rate (separate from the render
    /// deadline). Past it the body must keep up --min-body-bytes-per-sec, or the request ends
    /// with 408.
    #[arg(long, env = "SCNERF_BODY_TIMEOUT_SECS", default_value_t = UploadPolicy::default().grace.as_secs())]
    pub body_timeout_secs: u64,

    /// Slowest accepted upload: past --body-timeout-secs, each byte received buys the body
    /// 1/N s more. A stalled or trickling upload ends with 408 and frees its slot and memory.
    #[arg(long, env = "SCNERF_MIN_BODY_BYTES_PER_SEC", default_value_t = UploadPolicy::default().min_bytes_per_sec)]
    pub min_body_bytes_per_sec: u64,

    /// Longest pause in a request body, whatever it sent before: a body that sends nothing for
    /// this many seconds ends with 408 (bytes sent early buy no right to stall).
    #[arg(long, env = "SCNERF_BODY_STALL_SECS", default_value_t = UploadPolicy::default().stall.as_secs())]
    pub body_stall_secs: u64,

    /// Open connections at most; beyond it a new connection is answered 503 and closed, except
    /// for a reserve of 8 that serve /healthz, /readyz and /metrics only (one request each), so
    /// that probes are answered whoever holds the others. Must fit in the open-file limit with 72
    /// to spare: checked at start (the soft limit is raised when the hard limit allows).
    #[arg(long, env = "SCNERF_MAX_CONNECTIONS", default_value_t = 512)]
    pub max_connections: usize,

    /// Open connections from one client (peer IP address) at most; beyond it a new connection
    /// is answered 429 and closed, so that one source cannot hold every connection. 0: no cap
    /// (behind a reverse proxy every connection comes from the proxy's address).
    #[arg(long, env = "SCNERF_MAX_CONNECTIONS_PER_CLIENT", default_value_t = 64)]
    pub max_connections_per_client: usize,

    /// A connection must send a complete request head within this many seconds of opening or
    /// of its previous response (idle keep-alive), or it is closed.
    #[arg(long, env = "SCNERF_HEADER_READ_TIMEOUT_SECS", default_value_t = 30)]
    pub header_read_timeout_secs: u64,

    /// Largest request head (request line and headers) in bytes; beyond it 431.
    #[arg(long, env = "SCNERF_MAX_HEADER_BYTES", default_value_t = 16 * 1024)]
    pub max_header_bytes: usize,

    /// Accepted bearer token (repeat the flag; in the environment, comma-separated). With any
    /// token configured every route but /healthz, /readyz, /metrics and /openapi.json needs
    /// `Authorization: Bearer <token>`. Prefer --auth-token-file: command lines are visible to
    /// other users of the machine.
    #[arg(long = "auth-token", env = "SCNERF_AUTH_TOKENS", value_delimiter = ',', hide_env_values = true)]
    pub auth_tokens: Vec<String>,

    /// File of accepted bearer tokens, one per line (`#` comments).
    #[arg(long, env = "SCNERF_AUTH_TOKEN_FILE")]
    pub auth_token_file: Option<PathBuf>,

    /// Origins (`https://studio.example.com`, repeatable) besides the server's own whose browser
    /// pages may POST, PUT, DELETE; other sites' pages get 403 (non-browsers send no `Origin`).
    #[arg(long = "allowed-origin", env = "SCNERF_ALLOWED_ORIGINS", value_delimiter = ',')]
    pub allowed_origins: Vec<String>,

    /// Log format on stderr: `text` (human) or `json` (one object per line, with the request's
    /// span fields, for log pipelines). Levels: RUST_LOG (default info,ort=warn).
    #[arg(long, env = "SCNERF_LOG_FORMAT", value_enum, default_value = "text")]
    pub log_format: LogFormat,

    /// On SIGTERM/SIGINT: stop accepting, close connections without a request in progress, and
    /// give in-flight requests this many seconds to finish; those still running then get 503
    /// and the process exits with status 1.
    #[arg(long, env = "SCNERF_SHUTDOWN_GRACE_SECS", default_value_t = 30)]
    pub shutdown_grace_secs: u64,

    /// Serve the browser viewer at `/` (docs/viewer.md). Its page and the example scene are
    /// public even with --auth-token (a browser cannot send a token with a page load); the API
    /// calls it makes carry the token its user types. Accepts on/off, true/false.
    #[arg(long, env = "SCNERF_VIEWER", default_value = "on", action = clap::ArgAction::Set,
          value_parser = clap::builder::BoolishValueParser::new())]
    pub viewer: bool,

    /// Folder of the example scene the viewer opens on (`request.json`, `source_N.png`), served
    /// at /viewer/example/. Default: the repository's example (`http::viewer::DEFAULT_EXAMPLE`).
    #[arg(long, env = "SCNERF_VIEWER_EXAMPLE")]
    pub viewer_example: Option<PathBuf>,

    /// Skip the warm-up render at start (tests only; /readyz is then ready at once).
    #[arg(long, env = "SCNERF_SKIP_WARMUP", default_value_t = false)]
    pub skip_warmup: bool,
}

/// Seconds: a finite number >= 0.
fn non_negative_secs(s: &str) -> Result<f64, String> {
    s.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite() && *v >= 0.0)
        .ok_or_else(|| format!("\"{s}\" is not a number of seconds >= 0"))
}

#[cfg(test)]
mod device_tests {
    use super::*;

    #[test]
    fn device_arena_and_spin_flags() {
        assert_eq!("cpu".parse::<Device>(), Ok(Device::Cpu));
        assert_eq!("CUDA".parse::<Device>(), Ok(Device::Cuda { device_id: 0 }));
        assert_eq!("cuda:2".parse::<Device>(), Ok(Device::Cuda { device_id: 2 }));
        assert!("cuda:-1".parse::<Device>().is_err());
        assert!("tpu".parse::<Device>().is_err());
        let c = Config::try_parse_from(["scnerf-server"]).unwrap();
        assert_eq!((c.device, c.ort_arena, c.ort_spin), (Device::Cpu, true, true));
        let c = Config::try_parse_from(["scnerf-server", "--device", "cuda:1", "--ort-arena", "off", "--ort-spin=off"])
            .unwrap();
        assert_eq!((c.device, c.ort_arena, c.ort_spin), (Device::Cuda { device_id: 1 }, false, false));
        assert_eq!(c.exec_options().device.to_string(), "cuda:1");
    }
}
