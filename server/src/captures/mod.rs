//! `POST /v1/captures`'s use case: a capture folder's files, held in memory, made a scene. They
//! are read by the readers the `scnerf` client uses (`scnerf_capture`: COLMAP, nerfstudio,
//! Blender, LLFF, DTU), from the image set the client names (`downscale`) or else the largest
//! within `--max-source-pixels`, each photo as the client would send it (undistorted, fitted to
//! the source limit), thinned to `--max-scene-views` and validated as any scene is. Nothing is
//! written to disk.
//!
//! Memory: the files are the body, held against the memory budget as it arrived; what parsing
//! the files other than images takes is held against the budget before it starts
//! (`estimate::capture_parse_bytes`), and that lease grows to the most any one photo's
//! resampling takes. Parsing runs on a blocking thread and stops when the request is gone
//! (`files.rs`).
//!
//! `options.rs` holds what the client chooses, `read.rs` the capture read into a scene request,
//! `refusals.rs` what the readers and validation refuse, as the client knows the files.

mod files;
mod limits;
mod options;
mod read;
mod refusals;

pub use limits::CaptureLimits;

pub use options::CaptureOptions;

use scnerf_capture::files::MemoryFiles;
use scnerf_capture::wire::WireCamera;

use crate::backend::{BackendError, BackendHandle, MemoryLease};
use crate::blocking;
use crate::error::ApiError;
use crate::pipeline::estimate::capture_parse_bytes;
use crate::pipeline::Pipeline;
use crate::request::ValidScene;
use refusals::name_the_file;

/// A capture folder's files as sent, by their paths in the folder, and how many bytes the files
/// other than images hold (what the readers parse).
pub struct CaptureFiles {
    pub files: MemoryFiles,
    pub metadata_bytes: usize,
}

/// A capture made a scene, and what the answer reports of how it was read.
pub struct CaptureScene {
    pub scene: ValidScene,
    /// Every view of the scene, as the client would send it.
    pub cameras: Vec<WireCamera>,
    /// The image file of each camera (its path in the capture).
    pub names: Vec<String>,
    pub format: String,
    /// The image set read, when the capture keeps sets.
    pub image_set: Option<String>,
    pub warnings: Vec<String>,
}

/// `files` read as `options` say and validated for `pipeline`'s model, its size checked against
/// `sizes` before any photo is decoded; the memory parsing takes is leased from `executor`'s
/// budget.
pub async fn read_scene(
    files: CaptureFiles,
    options: CaptureOptions,
    executor: &BackendHandle,
    pipeline: &Pipeline,
    sizes: CaptureLimits,
) -> Result<CaptureScene, ApiError> {
    let CaptureFiles { files, metadata_bytes } = files;
    let mut parsing = lease_for_parsing(executor, metadata_bytes)?;
    let (config, limits) = (pipeline.config().clone(), pipeline.limits().clone());
    blocking::run(move |cancel| {
        let read = read::read_capture(files, &options, (&limits, &sizes), &mut parsing, cancel)?;
        let scene = read.request.validate(&config, &limits).map_err(|e| name_the_file(e, &read.names))?;
        Ok(CaptureScene {
            scene,
            cameras: read.cameras,
            names: read.names,
            format: read.format,
            image_set: read.image_set,
            warnings: read.warnings,
        })
    })
    .await
}

fn lease_for_parsing(executor: &BackendHandle, metadata_bytes: usize) -> Result<MemoryLease, ApiError> {
    executor.lease(capture_parse_bytes(metadata_bytes as u64)).map_err(|e| match e {
        BackendError::TooLarge { .. } => {
            ApiError::invalid("file", format!("parsing {metadata_bytes} bytes of capture files needs {e}"))
        }
        other => other.into(),
    })
}
