//! Command line and environment configuration: one clap struct, every flag also `SCNERF_*`.

use std::net::SocketAddr;
use std::path::PathBuf;

use clap::{Parser, ValueEnum};

/// Where the server looks for the default bundle when `--bundle` is not given: the repository's
/// `bundles/default`, resolved when the binary is compiled (the binary is built from the repo).
pub fn default_bundle_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../bundles/default"))
}

/// Graph optimisation level handed to ONNX Runtime.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum GraphOptLevel {
    Disable,
    Basic,
    Extended,
    All,
}

#[derive(Debug, Clone, Parser)]
#[command(name = "scnerf-server", version, about = "SC-NeRF novel-view inference server")]
pub struct Config {
    /// Bundle directory (manifest.json + ONNX graphs). Default: <repo>/bundles/default.
    #[arg(long, env = "SCNERF_BUNDLE")]
    pub bundle: Option<PathBuf>,

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

    /// Upper bound on rays per renderer run.
    #[arg(long, env = "SCNERF_MAX_RAYS_PER_CHUNK", default_value_t = 4096)]
    pub max_rays_per_chunk: usize,

    /// Memory budget of one renderer run in MiB; the chunk size is derived from it and the
    /// bundle's samples per ray (see pipeline::chunks).
    #[arg(long, env = "SCNERF_CHUNK_MEMORY_MB", default_value_t = 4096)]
    pub chunk_memory_mb: usize,

    /// Largest accepted request body in bytes.
    #[arg(long, env = "SCNERF_MAX_BODY_BYTES", default_value_t = 64 * 1024 * 1024)]
    pub max_body_bytes: usize,

    /// Largest accepted source image, in pixels (width x height), checked before decoding.
    /// Memory grows with it: the volume net over 800x800 sources peaks near 10 GB.
    #[arg(long, env = "SCNERF_MAX_SOURCE_PIXELS", default_value_t = 1024 * 1024)]
    pub max_source_pixels: u64,

    /// Largest accepted target view, in pixels (width x height).
    #[arg(long, env = "SCNERF_MAX_TARGET_PIXELS", default_value_t = 2048 * 2048)]
    pub max_target_pixels: u64,

    /// Per-request deadline in seconds; past it the request fails with 504.
    #[arg(long, env = "SCNERF_REQUEST_TIMEOUT_SECS", default_value_t = 900)]
    pub request_timeout_secs: u64,

    /// Graph runs waiting for the inference thread before new requests are refused with 503.
    #[arg(long, env = "SCNERF_QUEUE_CAPACITY", default_value_t = 64)]
    pub queue_capacity: usize,

    /// Skip the warm-up render at start (tests only; /readyz is then ready at once).
    #[arg(long, env = "SCNERF_SKIP_WARMUP", default_value_t = false)]
    pub skip_warmup: bool,
}

impl Config {
    pub fn bundle_dir(&self) -> PathBuf {
        self.bundle.clone().unwrap_or_else(default_bundle_dir)
    }

    pub fn intra_threads(&self) -> usize {
        self.threads.filter(|&t| t > 0).unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
    }

    pub fn limits(&self) -> crate::request::Limits {
        crate::request::Limits {
            max_body_bytes: self.max_body_bytes,
            max_source_pixels: self.max_source_pixels,
            max_target_pixels: self.max_target_pixels,
        }
    }

    pub fn chunking(&self) -> crate::pipeline::chunks::ChunkPolicy {
        crate::pipeline::chunks::ChunkPolicy {
            max_rays: self.max_rays_per_chunk.max(1),
            memory_budget_bytes: self.chunk_memory_mb.saturating_mul(1024 * 1024),
        }
    }
}
