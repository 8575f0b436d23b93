//! The state every handler and layer shares, and the service settings it is built from.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use super::body::UploadPolicy;
use super::origin::OriginPolicy;
use super::slots::Slots;
use crate::auth::Auth;
use crate::cache::{CacheConfig, Clock, SceneCache};
use crate::error::ApiError;
use crate::metrics::Metrics;
use crate::models::Models;
use crate::pipeline::Pipeline;

/// State shared by all handlers.
#[derive(Clone)]
pub struct AppState {
    /// Every model served, and the default.
    pub(super) models: Arc<Models>,
    /// Set once the warm-up render succeeded; cleared again when shutting down.
    ready: Arc<AtomicBool>,
    pub(super) request_timeout: Duration,
    pub(super) scenes: Arc<SceneCache>,
    pub(super) metrics: Arc<Metrics>,
    pub(super) auth: Arc<Auth>,
    /// Which sites may change state (`origin.rs`).
    pub(super) origins: Arc<OriginPolicy>,
    /// Slots for POST requests being handled at once (bodies in memory included).
    pub(super) in_flight: Arc<Slots>,
    /// How slowly a request body may arrive.
    pub(super) uploads: UploadPolicy,
    /// The time scenes expire by.
    pub(super) clock: Clock,
}

/// Service settings besides the pipeline (from the command line, or set by tests).
#[derive(Debug, Clone)]
pub struct ServiceOptions {
    pub request_timeout: Duration,
    pub cache: CacheConfig,
    /// POST requests handled at once; beyond it 503 before the body is read.
    pub max_concurrent_requests: usize,
    /// POST requests handled at once from one peer address (0: no cap); beyond it 429.
    pub max_requests_per_client: usize,
    pub uploads: UploadPolicy,
    pub auth: Auth,
    /// The time scenes expire by (tests set a manual one).
    pub clock: Clock,
    /// Origins besides the server's own whose browser requests may change state
    /// (`--allowed-origins`).
    pub allowed_origins: Vec<String>,
}

impl Default for ServiceOptions {
    fn default() -> Self {
        ServiceOptions {
            request_timeout: Duration::from_secs(900),
            cache: CacheConfig::default(),
            max_concurrent_requests: 256,
            max_requests_per_client: 32,
            uploads: UploadPolicy::default(),
            auth: Auth::disabled(),
            clock: Clock::System,
            allowed_origins: Vec::new(),
        }
    }
}

impl AppState {
    /// A server of one model. Not ready until `set_ready` (after the warm-up render).
    pub fn new(pipeline: Pipeline, options: ServiceOptions) -> AppState {
        AppState::with_models(Models::single(pipeline), options)
    }

    /// A server of `models`. Not ready until `set_ready` (after the warm-up renders).
    pub fn with_models(models: Models, options: ServiceOptions) -> AppState {
        let scenes = Arc::new(SceneCache::new(options.cache, options.auth.token_count()));
        models.default_model().pipeline.executor().set_reclaim(scenes.clone());
        let metrics = Arc::new(Metrics::new(models.default_model().pipeline.executor().clone(), scenes.clone()));
        AppState {
            models: Arc::new(models),
            ready: Arc::new(AtomicBool::new(false)),
            request_timeout: options.request_timeout,
            scenes,
            metrics,
            auth: Arc::new(options.auth),
            origins: Arc::new(OriginPolicy::new(&options.allowed_origins)),
            in_flight: Arc::new(Slots::new(options.max_concurrent_requests, options.max_requests_per_client)),
            uploads: options.uploads,
            clock: options.clock,
        }
    }

    /// The default model's pipeline: the limits and the executor, which are every model's.
    pub fn pipeline(&self) -> &Pipeline {
        &self.models.default_model().pipeline
    }

    pub fn models(&self) -> &Arc<Models> {
        &self.models
    }

    pub fn scenes(&self) -> &Arc<SceneCache> {
        &self.scenes
    }

    pub fn is_ready(&self) -> bool {
        self.ready.load(Ordering::Acquire)
    }

    pub fn set_ready(&self) {
        self.ready.store(true, Ordering::Release);
    }

    pub fn set_draining(&self) {
        self.ready.store(false, Ordering::Release);
    }

    /// 503 (with Retry-After) until the model is warm, and again while shutting down.
    pub(super) fn check_ready(&self) -> Result<(), ApiError> {
        if self.is_ready() {
            Ok(())
        } else {
            Err(ApiError::Unavailable { message: "the model is warming up".into(), retry_after_secs: 5 })
        }
    }
}
