//! ONNX Runtime backend (`ort` 2.0.0-rc.15, library loaded at run time).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use ort::environment::{Environment, GlobalThreadPoolOptions};
use ort::ep;
use ort::memory::{AllocationDevice, AllocatorType, MemoryInfo, MemoryType};
use ort::session::builder::{GraphOptimizationLevel, SessionBuilder};
use ort::session::{RunOptions, Session};
use ort::value::{TensorElementType, TensorRef, ValueType};
use ort::AsPointer;

use super::device::{Device, GraphOptLevel};
use super::{BackendError, GraphRunner, Interrupt, NamedTensors};
use crate::bundle::{check_signature, ActualTensor, Bundle, GraphKind};

pub const ORT_VERSION: &str = "1.31.1";
const LIB_NAMES: [&str; 2] = ["libonnxruntime.so.1.31.1", "libonnxruntime.so"];

#[derive(Debug, Clone)]
pub struct OrtOptions {
    /// Explicit library path (`--ort-dylib`); `None` searches the default places.
    pub dylib: Option<PathBuf>,
    pub intra_threads: usize,
    pub opt_level: GraphOptLevel,
    /// Idle intra-op workers spin before they sleep (`--ort-spin`).
    pub spin: bool,
}

/// Per-session execution settings (`--device`, `--ort-arena`). The default is what the server
/// always did: the CPU execution provider with ONNX Runtime's CPU memory arena.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExecOptions {
    pub device: Device,
    /// ONNX Runtime's CPU memory arena for the renderer (see `uses_arena`): keeps freed buffers
    /// for reuse (faster repeated runs, but the process keeps a run's working set); off returns
    /// memory to the allocator.
    pub cpu_arena: bool,
}

impl Default for ExecOptions {
    fn default() -> Self {
        ExecOptions { device: Device::Cpu, cpu_arena: true }
    }
}

/// Where the library is looked for when no path is given: next to the executable (a deployed
/// binary carries its library), then the repository's third_party/onnxruntime/ filled by
/// scripts/fetch-onnxruntime.sh (resolved when the binary is compiled).
pub fn default_dylib_candidates() -> Vec<PathBuf> {
    let mut dirs = Vec::new();
    if let Some(exe_dir) = std::env::current_exe().ok().and_then(|p| p.parent().map(Path::to_path_buf)) {
        dirs.push(exe_dir);
    }
    dirs.push(PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../third_party/onnxruntime")));
    dirs.iter().flat_map(|d| LIB_NAMES.iter().map(move |n| d.join(n))).collect()
}

pub fn resolve_dylib(explicit: Option<&Path>) -> Result<PathBuf, String> {
    if let Some(path) = explicit {
        return if path.is_file() {
            Ok(path.to_path_buf())
        } else {
            Err(format!("ONNX Runtime library {} (--ort-dylib / SCNERF_ORT_DYLIB) does not exist", path.display()))
        };
    }
    let candidates = default_dylib_candidates();
    candidates.iter().find(|p| p.is_file()).cloned().ok_or_else(|| {
        let tried: Vec<String> = candidates.iter().map(|p| p.display().to_string()).collect();
        format!(
            "ONNX Runtime {ORT_VERSION} not found (tried {}); run scripts/fetch-onnxruntime.sh or pass --ort-dylib",
            tried.join(", ")
        )
    })
}

/// The process's one ONNX Runtime environment (ort allows one per process): every model's
/// sessions are created in it and share its thread pool.
static ENVIRONMENT: std::sync::Mutex<Option<Environment>> = std::sync::Mutex::new(None);

/// Loads the library and creates the process's ONNX Runtime environment with one intra-op
/// thread pool shared by all sessions (the graphs run one at a time on the inference thread,
/// so one pool of `threads` workers never oversubscribes the CPU). Later calls (another model's
/// runner) get the same environment: the library and pool of the first.
pub fn init_environment(opts: &OrtOptions) -> Result<Environment, String> {
    let mut current = ENVIRONMENT.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(env) = current.as_ref() {
        return Ok(env.clone());
    }
    let path = resolve_dylib(opts.dylib.as_deref())?;
    let builder =
        ort::init_from(&path).map_err(|e| format!("cannot load ONNX Runtime from {}: {e}", path.display()))?;
    let pool = GlobalThreadPoolOptions::default()
        .with_intra_threads(opts.intra_threads)
        .and_then(|p| p.with_inter_threads(1))
        .and_then(|p| p.with_spin_control(opts.spin))
        .map_err(|e| format!("ONNX Runtime thread pool: {e}"))?;
    let env = builder
        .with_name("scnerf-server")
        .with_global_thread_pool(pool)
        .build()
        .map_err(|e| format!("ONNX Runtime environment: {e}"))?;
    tracing::info!(library = %path.display(), threads = opts.intra_threads, "ONNX Runtime loaded");
    *current = Some(env.clone());
    Ok(env)
}

pub struct OrtRunner {
    sessions: HashMap<GraphKind, Session>,
    /// The graphs whose session keeps the CPU arena (`uses_arena`).
    arenas: Vec<GraphKind>,
    /// The options of every run, which the executor's watchdog can end (`Terminate`).
    options: Arc<Terminate>,
    _env: Environment,
}

/// The two kinds of run options; ending a run sets their terminate flag, which ONNX Runtime
/// reads between operators (and between a `Loop`'s iterations): the run returns an error.
struct Terminate {
    plain: RunOptions,
    /// Shrinks the CPU arena once the run is done (`run_and_release`).
    shrink: RunOptions,
}

impl Interrupt for Terminate {
    fn interrupt(&self) {
        for options in [&self.plain, &self.shrink] {
            if let Err(e) = options.terminate() {
                tracing::warn!(error = %e, "cannot end the graph run in progress");
            }
        }
    }

    fn clear(&self) {
        for options in [&self.plain, &self.shrink] {
            if let Err(e) = options.unterminate() {
                tracing::warn!(error = %e, "cannot clear the graph runs' terminate flag");
            }
        }
    }
}

impl OrtRunner {
    /// Creates the three sessions and checks each graph's real signature against the manifest
    /// (CPU execution provider, default session options).
    pub fn load(bundle: &Bundle, opts: &OrtOptions) -> Result<OrtRunner, String> {
        Self::load_with(bundle, opts, &ExecOptions::default())
    }

    /// [`OrtRunner::load`] on the device and with the session options of `exec`. With
    /// `--device cuda` the loaded library must have the CUDA execution provider (the
    /// onnxruntime-gpu build) and it must register (CUDA/cuDNN libraries found, a GPU present):
    /// otherwise start-up fails here, naming the cause; there is no silent fallback to the CPU.
    pub fn load_with(bundle: &Bundle, opts: &OrtOptions, exec: &ExecOptions) -> Result<OrtRunner, String> {
        let env = init_environment(opts)?;
        if let Device::Cuda { .. } = exec.device {
            check_cuda_available(opts)?;
        }
        tracing::info!(device = %exec.device, cpu_arena = exec.cpu_arena, "execution settings");
        let mut sessions = HashMap::new();
        let arenas: Vec<GraphKind> = bundle.graphs().into_iter().filter(|&k| uses_arena(k, exec)).collect();
        if !arenas.is_empty() {
            register_renderer_arena(&env)?;
        }
        // ONNX Runtime frees the arena's unused chunks at the end of a run with this option;
        // "cpu:0" names the CPU arena (the option must not name an arena that is off).
        let run_options = || RunOptions::new().map_err(|e| format!("ONNX Runtime run options: {e}"));
        let mut shrink = run_options()?;
        shrink
            .set("memory.enable_memory_arena_shrinkage", "cpu:0")
            .map_err(|e| format!("ONNX Runtime run options: {e}"))?;
        let options = Arc::new(Terminate { plain: run_options()?, shrink });
        for kind in bundle.graphs() {
            let path = bundle.graph_path(kind);
            let builder = Session::builder(&env)
                .and_then(|b| b.with_optimization_level(opt_level(opts.opt_level)).map_err(Into::into))
                .map_err(|e| format!("cannot load {}: {e}", path.display()))?;
            let arena = arenas.contains(&kind);
            let mut builder = with_execution_providers(builder, exec, arena)?;
            if arena {
                builder = builder.with_env_allocators().map_err(|e| format!("cannot load {}: {e}", path.display()))?;
            }
            // From the verified bytes, not the file: nothing of the bundle stays mapped.
            let graph = bundle.read_graph(kind)?;
            let session =
                builder.commit_from_memory(&graph).map_err(|e| format!("cannot load {}: {e}", path.display()))?;
            let entry = bundle.graph(kind);
            check_signature(kind, "input", &entry.inputs, &describe(session.inputs()))?;
            check_signature(kind, "output", &entry.outputs, &describe(session.outputs()))?;
            sessions.insert(kind, session);
        }
        Ok(OrtRunner { sessions, arenas, options, _env: env })
    }
}

/// Whether a graph's session allocates from the renderers' CPU arena (`--ort-arena` on): the
/// renderer graphs run many times per request on buffers of the same few sizes, which the arena
/// serves without page faults. The graphs that run once per request (the encoder and the
/// volume's) allocate their working memory from the system and give it back when the run ends;
/// in an arena it would stay held at the largest request's peak for the life of the process.
fn uses_arena(kind: GraphKind, exec: &ExecOptions) -> bool {
    exec.cpu_arena && matches!(kind, GraphKind::Renderer | GraphKind::RendererGuide | GraphKind::RendererFine)
}

/// The one CPU arena of every renderer session of the process, every model's, registered with
/// the environment once (`session.use_env_allocators`). The executor runs one graph at a time,
/// so one arena sized for the largest run serves them all, where an arena per session would
/// each keep its own graph's largest working set (docs/results.md, "Memory at paper size").
fn register_renderer_arena(env: &Environment) -> Result<(), String> {
    static REGISTERED: std::sync::OnceLock<Result<(), String>> = std::sync::OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            let info = MemoryInfo::new(AllocationDevice::CPU, 0, AllocatorType::Arena, MemoryType::Default)
                .map_err(|e| format!("ONNX Runtime arena: {e}"))?;
            // SAFETY: both pointers are live for the call (the environment is the process's, kept
            // in `ENVIRONMENT`; ONNX Runtime copies the memory info); a null config asks for the
            // arena's defaults (growing to the next power of two: an arena that grows by what is
            // asked, tried, reached a higher peak, docs/results.md). The returned status is owned
            // and released by `result_from_status`.
            let status =
                unsafe { (ort::api().CreateAndRegisterAllocator)(env.ptr().cast_mut(), info.ptr(), std::ptr::null()) };
            unsafe { ort::Error::result_from_status(status) }.map_err(|e| format!("ONNX Runtime arena: {e}"))
        })
        .clone()
}

/// Registers the execution providers of `exec` on a session builder: CUDA (when asked; failing
/// to register is an error) and the CPU provider (always, last: it runs whatever CUDA cannot, and
/// carries the arena setting, `arena`).
fn with_execution_providers(
    builder: SessionBuilder,
    exec: &ExecOptions,
    arena: bool,
) -> Result<SessionBuilder, String> {
    let mut providers = Vec::new();
    if let Device::Cuda { device_id } = exec.device {
        providers.push(ep::CUDA::default().with_device_id(device_id).build().error_on_failure());
    }
    providers.push(ep::CPU::default().with_arena_allocator(arena).build().error_on_failure());
    builder.with_execution_providers(providers).map_err(|e| match exec.device {
        Device::Cuda { device_id } => format!(
            "--device {}: ONNX Runtime could not register the CUDA execution provider on GPU {device_id}: {e} \
             (needs an NVIDIA GPU and the CUDA 13 / cuDNN 9 libraries of the onnxruntime-gpu wheel on \
             LD_LIBRARY_PATH, e.g. the PyPI nvidia-* wheels' lib directories)",
            exec.device
        ),
        Device::Cpu => format!("cannot configure the CPU execution provider: {e}"),
    })
}

/// The library must be a build with the CUDA execution provider (onnxruntime-gpu): the CPU-only
/// library from scripts/fetch-onnxruntime.sh is not.
fn check_cuda_available(opts: &OrtOptions) -> Result<(), String> {
    use ort::ep::ExecutionProvider;
    match ep::CUDA::is_available() {
        Ok(true) => Ok(()),
        Ok(false) => {
            let lib = resolve_dylib(opts.dylib.as_deref()).map(|p| p.display().to_string()).unwrap_or_default();
            Err(format!(
                "--device cuda: the ONNX Runtime library {lib} has no CUDA execution provider; use the \
                 onnxruntime-gpu {ORT_VERSION} library (libonnxruntime.so.{ORT_VERSION} from the wheel's \
                 onnxruntime/capi/, next to libonnxruntime_providers_cuda.so) with --ort-dylib, or --device cpu"
            ))
        }
        Err(e) => Err(format!("--device cuda: cannot list ONNX Runtime's execution providers: {e}")),
    }
}

fn opt_level(level: GraphOptLevel) -> GraphOptimizationLevel {
    match level {
        GraphOptLevel::Disable => GraphOptimizationLevel::Disable,
        GraphOptLevel::Basic => GraphOptimizationLevel::Level1,
        GraphOptLevel::Extended => GraphOptimizationLevel::Level2,
        GraphOptLevel::All => GraphOptimizationLevel::All,
    }
}

fn describe(outlets: &[ort::value::Outlet]) -> Vec<ActualTensor> {
    outlets
        .iter()
        .map(|o| {
            let (dtype, shape) = match o.dtype() {
                ValueType::Tensor { ty, shape, .. } => {
                    (dtype_name(*ty), shape.iter().map(|&d| if d < 0 { None } else { Some(d) }).collect())
                }
                other => (format!("{other}"), Vec::new()),
            };
            ActualTensor { name: o.name().to_string(), shape, dtype }
        })
        .collect()
}

fn dtype_name(ty: TensorElementType) -> String {
    match ty {
        TensorElementType::Float32 => "float32".into(),
        TensorElementType::Float16 => "float16".into(),
        TensorElementType::Float64 => "float64".into(),
        TensorElementType::Int64 => "int64".into(),
        TensorElementType::Int32 => "int32".into(),
        other => format!("{other:?}").to_lowercase(),
    }
}

impl GraphRunner for OrtRunner {
    fn run(&mut self, graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
        self.run_with(graph, inputs, false)
    }

    /// The renderer's arena back to the system after a request's last chunk (docs/results.md, "Memory at paper size").
    fn run_and_release(&mut self, graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
        let shrink = self.arenas.contains(&graph);
        self.run_with(graph, inputs, shrink)
    }

    fn interrupter(&self) -> Option<Arc<dyn Interrupt>> {
        Some(self.options.clone())
    }
}

impl OrtRunner {
    fn run_with(
        &mut self,
        graph: GraphKind,
        inputs: &NamedTensors,
        shrink: bool,
    ) -> Result<NamedTensors, BackendError> {
        let err = |message: String| BackendError::Run { graph, message };
        let session = self.sessions.get_mut(&graph).ok_or_else(|| err("no session".into()))?;
        let mut values = Vec::with_capacity(inputs.len());
        for (name, tensor) in inputs {
            // Zero-copy views of our buffers; ONNX Runtime only reads them.
            let view = TensorRef::from_array_view(tensor.view()).map_err(|e| err(format!("input {name}: {e}")))?;
            values.push((std::borrow::Cow::from(name.as_str()), ort::session::SessionInputValue::from(view)));
        }
        let output_names: Vec<String> = session.outputs().iter().map(|o| o.name().to_string()).collect();
        let options = if shrink { &self.options.shrink } else { &self.options.plain };
        let outputs = session.run_with_options(values, options);
        let outputs = outputs.map_err(|e| err(e.to_string()))?;
        output_names
            .into_iter()
            .map(|name| {
                let value = outputs.get(&name).ok_or_else(|| err(format!("missing output {name}")))?;
                // Copied out: the session's output buffers are gone once `outputs` is dropped.
                let array = value.try_extract_array::<f32>().map_err(|e| err(format!("output {name}: {e}")))?;
                Ok((name, array.to_shared()))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture_bundle() -> Bundle {
        let dir = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/parity/bundle"));
        Bundle::load(&dir).expect("committed parity fixture bundle")
    }

    fn cpu_library_opts() -> OrtOptions {
        OrtOptions { dylib: None, intra_threads: 1, opt_level: GraphOptLevel::All, spin: false }
    }

    /// The library of scripts/fetch-onnxruntime.sh is the CPU build: asking for CUDA must fail at
    /// start with a message that says why, never fall back to the CPU silently. (The only test of
    /// this binary that creates an ONNX Runtime environment: one per process.)
    #[test]
    fn cuda_on_the_cpu_library_is_a_clear_error() {
        let exec = ExecOptions { device: Device::Cuda { device_id: 0 }, cpu_arena: true };
        let err = match OrtRunner::load_with(&fixture_bundle(), &cpu_library_opts(), &exec) {
            Ok(_) => panic!("the CPU-only ONNX Runtime accepted --device cuda"),
            Err(e) => e,
        };
        assert!(err.contains("--device cuda"), "{err}");
        assert!(err.contains("no CUDA execution provider") || err.contains("could not register"), "{err}");
    }
}
