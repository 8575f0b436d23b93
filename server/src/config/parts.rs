//! What each part of the server takes from the configuration: its settings, derived from the
//! flags (`Config`'s fields, in `mod.rs`).

use super::*;

impl Config {
    /// The --bundle folders; the default bundle when neither --bundle nor --models is given.
    pub fn bundle_dirs(&self) -> Vec<PathBuf> {
        match (self.bundle.is_empty(), &self.models) {
            (true, None) => vec![default_bundle_dir()],
            _ => self.bundle.clone(),
        }
    }

    /// What every model's pipeline is built with.
    pub fn model_settings(&self) -> ModelSettings {
        ModelSettings {
            chunking: self.chunking(),
            slabs: self.slabs(),
            limits: self.limits(),
            sampling: self.sampling,
            band: self.band,
        }
    }

    pub fn model_deadlines(&self) -> Deadlines {
        let secs = |s: u64| Duration::from_secs(s.max(1));
        Deadlines { search: secs(self.models_timeout_secs), warm_up: secs(self.warmup_timeout_secs) }
    }

    pub fn intra_threads(&self) -> usize {
        self.threads.filter(|&t| t > 0).unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
    }

    pub fn ort_options(&self) -> OrtOptions {
        OrtOptions {
            dylib: self.ort_dylib.clone(),
            intra_threads: self.intra_threads(),
            opt_level: self.graph_opt_level,
            spin: self.ort_spin,
        }
    }

    pub fn exec_options(&self) -> ExecOptions {
        ExecOptions { device: self.device, cpu_arena: self.ort_arena }
    }

    pub fn limits(&self) -> Limits {
        Limits {
            max_body_bytes: self.max_body_bytes,
            max_source_pixels: self.max_source_pixels,
            max_target_pixels: self.max_target_pixels,
            max_json_bytes: self.max_json_bytes,
            max_json_depth: self.max_json_depth,
            max_scene_views: self.max_scene_views as usize,
            max_capture_bytes: self.max_capture_bytes,
            max_capture_metadata_bytes: self.max_capture_metadata_bytes,
        }
    }

    /// Fails when the token file cannot be read.
    pub fn service_options(&self) -> Result<ServiceOptions, String> {
        Ok(ServiceOptions {
            request_timeout: Duration::from_secs(self.request_timeout_secs),
            cache: CacheConfig {
                max_bytes: self.scene_cache_bytes(),
                ttl: Duration::from_secs(self.scene_ttl_secs),
                per_owner_bytes: self.scene_cache_mb_per_token.map(|mb| mb.saturating_mul(1024 * 1024)),
            },
            max_concurrent_requests: self.max_concurrent_requests,
            max_requests_per_client: self.max_requests_per_client,
            uploads: UploadPolicy {
                grace: Duration::from_secs(self.body_timeout_secs),
                min_bytes_per_sec: self.min_body_bytes_per_sec.max(1),
                stall: Duration::from_secs(self.body_stall_secs.max(1)),
            },
            auth: Auth::from_config(&self.auth_tokens, self.auth_token_file.as_deref())?,
            clock: Clock::System,
            allowed_origins: self.allowed_origins.clone(),
        })
    }

    pub fn serve_options(&self) -> ServeOptions {
        ServeOptions {
            max_connections: self.max_connections.max(1),
            max_connections_per_client: self.max_connections_per_client,
            header_read_timeout: Duration::from_secs(self.header_read_timeout_secs.max(1)),
            // hyper needs room for at least a request line and a few headers.
            max_header_bytes: self.max_header_bytes.max(1024),
            shutdown_grace: Duration::from_secs(self.shutdown_grace_secs),
        }
    }

    /// `--scene-cache-mb` in bytes, or a third of the memory budget (without one, 2 GiB).
    pub fn scene_cache_bytes(&self) -> usize {
        match (self.scene_cache_mb, self.memory_budget().0) {
            (Some(mb), _) => mb.saturating_mul(1 << 20),
            (None, u64::MAX) => CacheConfig::default().max_bytes,
            (None, budget) => usize::try_from(budget / 3).unwrap_or(usize::MAX),
        }
    }

    /// `--memory-budget-mb` in bytes, or the default (3/4 of the memory limit), and where it
    /// comes from; no bound where the limit cannot be read.
    pub fn memory_budget(&self) -> (u64, String) {
        match (self.memory_budget_mb, sysmem::memory_limit()) {
            (Some(mb), _) => (mb.saturating_mul(1 << 20), "--memory-budget-mb".into()),
            (None, Some((limit, source))) => (limit / 4 * 3, format!("3/4 of the {source} limit")),
            (None, None) => (u64::MAX, "no memory limit found".into()),
        }
    }

    pub fn executor_options(&self) -> ExecutorOptions {
        ExecutorOptions {
            capacity: self.queue_capacity,
            memory: MemoryBudget { total: self.memory_budget().0, reserved: 0 },
            probe: self.memory_probe.then(Arc::default),
            max_queue_wait: Some(Duration::from_secs_f64(self.max_queue_wait_secs)),
        }
    }

    pub fn slabs(&self) -> SlabPolicy {
        SlabPolicy {
            memory_budget_bytes: self.volume_slab_mb.saturating_mul(1024 * 1024),
            threads: self.intra_threads(),
        }
    }

    pub fn chunking(&self) -> ChunkPolicy {
        ChunkPolicy {
            max_rays: self.max_rays_per_chunk.max(1),
            memory_budget_bytes: self.chunk_memory_mb.saturating_mul(1024 * 1024),
        }
    }
}
