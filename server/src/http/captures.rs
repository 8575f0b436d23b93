//! `POST /v1/captures`: a capture folder's files (multipart, every part named `file`, its
//! filename the file's path in the folder: `transforms.json`, `images/r_0.png`,
//! `sparse/0/cameras.txt`, ...) read in memory by the readers the `scnerf` client uses
//! (`scnerf_capture`: COLMAP, nerfstudio, Blender, LLFF, DTU), from the image set the client
//! names (`downscale`) or else the largest within `--max-source-pixels`, thinned to
//! `--max-scene-views` and kept as a scene. Nothing is written to disk.
//!
//! Memory: the files are the body (held against the memory budget as it arrives, see
//! `middleware::limit_in_flight`); the files other than images, which the readers parse, are
//! capped (`--max-capture-metadata-bytes`), and what parsing them takes is held against the
//! budget before it starts (`estimate::capture_parse_bytes`); the views are then decoded as any
//! scene's are, admitted by their estimate. Parsing stops when the request is gone.

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use axum::extract::rejection::QueryRejection;
use axum::extract::{FromRequest, Multipart, Query, Request, State};
use axum::http::StatusCode;
use axum::response::Response;
use bytes::Bytes;
use scnerf_capture::files::{Files, MemoryFiles};
use scnerf_capture::image_sets::{load_picked, ImageSet, Pick, Picked};
use scnerf_capture::readers::{self, Capture, CapturedView, ReadOptions};
use scnerf_capture::undistort::Fit;
use scnerf_capture::upload::{fit_to_limit, image_bytes, resample_bytes};
use scnerf_capture::wire::WireCamera;
use serde::{Deserialize, Serialize};

use super::body::multipart_error;
use super::capture_limits::CaptureLimits;
use super::deadline::Deadline;
use super::negotiate::{request_format, RequestFormat};
use super::openapi::refusals::CaptureRefusals;
use super::respond::rfc3339;
use super::scenes::{owner_of, proxy_scene_id, scene_response, store_scene, SceneIdHeader};
use super::state::AppState;
use crate::backend::{BackendError, MemoryLease};
use crate::blocking::{self, Cancel};
use crate::error::ApiError;
use crate::pipeline::estimate::capture_parse_bytes;
use crate::pipeline::scene::Timings;
use crate::request::cameras::CameraSpec;
use crate::request::{Limits, SceneRequest, SourceSpec};

/// What the readers take from the command line in the client, as query parameters.
#[derive(Debug, Default, Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct CaptureOptions {
    /// Near depth, overriding the capture's (its files', COLMAP's points' or else its poses'; the
    /// readers' messages call it `--near`).
    near: Option<f64>,
    /// Far depth, overriding the capture's.
    far: Option<f64>,
    /// Use photos with lens distortion as they are, as pinhole, instead of undistorting them.
    #[serde(default)]
    ignore_distortion: bool,
    /// The pinhole camera distorted photos are undistorted to: `largest_rectangle` (default)
    /// crops to valid pixels, `all_pixels` keeps every pixel (corners no pixel reaches take the
    /// background).
    #[serde(default)]
    #[param(value_type = Option<String>, pattern = "^(largest_rectangle|all_pixels)$")]
    undistort_to: Fit,
    /// Read the image set `images_N` (LLFF, nerfstudio, COLMAP); without it, the largest set
    /// sent whose images fit `max_source_pixels` (GET /v1/limits).
    #[param(value_type = Option<u32>, minimum = 1)]
    downscale: Option<std::num::NonZeroU32>,
    /// The model the scene belongs to (a name `GET /v1/models` lists); default: the server's.
    model: Option<String>,
}

/// `201 Created` body of `POST /v1/captures`: the scene, and what the capture was read as.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct CaptureCreated {
    pub scene_id: String,
    /// The model the scene belongs to.
    pub model: String,
    /// RFC 3339 UTC, as for `POST /v1/scenes`.
    pub expires_at: String,
    /// Every view of the scene (canonical: OpenCV world-to-camera), in the order of the indices
    /// that renders report in `sources` and may pin.
    pub cameras: Vec<WireCamera>,
    /// The image file of each camera (its path in the capture).
    pub names: Vec<String>,
    pub near: f64,
    pub far: f64,
    /// colmap, nerfstudio, blender, llff or dtu.
    pub format: String,
    /// The image set read (`images`, `images_4`, ...), when the capture keeps sets.
    pub image_set: Option<String>,
    /// What the reader skipped or ignored, the image sets sent but not read, and whether the
    /// capture was thinned.
    pub warnings: Vec<String>,
}

#[utoipa::path(
    post, path = "/v1/captures", tag = "render", operation_id = "create_capture_scene",
    request_body(content((crate::http::schema::CaptureMultipart = "multipart/form-data")),
        description = "A capture folder's files: COLMAP (cameras/images/points3D .txt or .bin, in ., sparse/0 or sparse; images/), nerfstudio or Blender (transforms*.json + images), LLFF (poses_bounds.npy + images/), DTU (Cameras/ + Rectified/)"),
    params(
        CaptureOptions,
        Deadline,
        SceneIdHeader,
    ),
    responses(
        (status = 201, description = "The capture is a scene", body = CaptureCreated,
         headers(("location" = String, description = "/v1/scenes/{scene_id}"))),
        CaptureRefusals,
    ),
    security((), ("bearer" = [])),
)]
pub async fn create(
    State(state): State<AppState>,
    deadline: Deadline,
    query: Result<Query<CaptureOptions>, QueryRejection>,
    req: Request,
) -> Result<Response, ApiError> {
    let Query(options) = query.map_err(|e| ApiError::malformed(Some("query".to_string()), e.body_text()))?;
    let id = proxy_scene_id(req.headers())?;
    deadline.run(create_within(state, deadline, options, id, req)).await
}

async fn create_within(
    state: AppState,
    deadline: Deadline,
    options: CaptureOptions,
    id: Option<String>,
    req: Request,
) -> Result<Response, ApiError> {
    if request_format(req.headers())? != RequestFormat::Multipart {
        return Err(ApiError::UnsupportedMediaType {
            field: Some("content-type".into()),
            message: "a capture is sent as multipart/form-data, one part named `file` per file".into(),
        });
    }
    let owner = owner_of(&req);
    // Before the upload is read: a wrong name costs the client no upload.
    let model = state.models.get(options.model.as_deref())?;
    let (files, metadata_bytes) = read_files(req, state.pipeline().limits()).await?;
    let mut parsing =
        state.pipeline().executor().lease(capture_parse_bytes(metadata_bytes as u64)).map_err(|e| match e {
            BackendError::TooLarge { .. } => {
                ApiError::invalid("file", format!("parsing {metadata_bytes} bytes of capture files needs {e}"))
            }
            other => other.into(),
        })?;
    let (config, limits) = (model.pipeline.config().clone(), model.pipeline.limits().clone());
    let sizes = CaptureLimits::new(&model, &state.scenes);
    let parsed = blocking::run(move |cancel| {
        let read = read_capture(files, &options, (&limits, &sizes), &mut parsing, cancel)?;
        let names = read.names.clone();
        let valid = read.request.validate(&config, &limits).map_err(|e| name_the_file(e, &names))?;
        Ok((valid, read.cameras, read.names, read.format, read.image_set, read.warnings))
    })
    .await?;
    let (valid, cameras, names, format, image_set, warnings) = parsed;
    let (near, far) = (valid.near, valid.far);
    let mut timings = Timings::default();
    let stored = store_scene(&state, &model, valid, id, owner, &deadline, &mut timings).await?;
    let body = CaptureCreated {
        scene_id: stored.id.clone(),
        model: model.name.to_string(),
        expires_at: rfc3339(stored.expires_at),
        cameras,
        names,
        near,
        far,
        format,
        image_set,
        warnings,
    };
    let status = if stored.replaced { StatusCode::OK } else { StatusCode::CREATED };
    Ok(scene_response(&model, status, &stored.id, body, &timings))
}

/// Every `file` part, by its filename, and the bytes of those that are not images (at most
/// `--max-capture-metadata-bytes`: 413 naming the file that goes past it, as it arrives).
async fn read_files(req: Request, limits: &Limits) -> Result<(MemoryFiles, usize), ApiError> {
    let limit = limits.max_capture_bytes;
    let mut multipart = Multipart::from_request(req, &()).await.map_err(|e| {
        ApiError::malformed(Some("content-type".to_string()), format!("invalid multipart request: {}", e.body_text()))
    })?;
    let (mut files, mut metadata) = (MemoryFiles::new(), 0usize);
    while let Some(mut field) = multipart.next_field().await.map_err(|e| multipart_error(e, "body", limit))? {
        let name = field.name().unwrap_or_default().to_string();
        if name != "file" {
            return Err(ApiError::malformed(
                Some(name.clone()),
                format!("unknown multipart part \"{name}\": every part is a file named `file`"),
            ));
        }
        let filename = field.file_name().map(str::to_string).ok_or_else(|| missing_filename(field.headers()))?;
        let is_image = readers::has_image_extension(Path::new(&filename));
        let mut chunks = Vec::new();
        while let Some(chunk) = field.chunk().await.map_err(|e| multipart_error(e, &filename, limit))? {
            if !is_image {
                metadata += chunk.len();
                if metadata > limits.max_capture_metadata_bytes {
                    return Err(ApiError::TooLarge {
                        field: Some(filename),
                        message: format!(
                            "a capture's files other than images (transforms, COLMAP models, poses) may hold {} \
                             bytes in all (--max-capture-metadata-bytes)",
                            limits.max_capture_metadata_bytes
                        ),
                    });
                }
            }
            chunks.push(chunk);
        }
        if !files.insert(&filename, chunks.concat()) {
            return Err(ApiError::malformed(
                Some(filename),
                "sent twice, or not a relative path inside the capture folder",
            ));
        }
    }
    if files.is_empty() {
        return Err(ApiError::invalid("file", "no files: send the capture folder's files as parts named `file`"));
    }
    Ok((files, metadata))
}

/// A file part without a (UTF-8) filename: which of the two it is.
fn missing_filename(headers: &axum::http::HeaderMap) -> ApiError {
    let disposition = headers.get(axum::http::header::CONTENT_DISPOSITION).map(|v| v.as_bytes()).unwrap_or_default();
    let has_one = disposition.windows(9).any(|w| w.eq_ignore_ascii_case(b"filename="));
    let message = match has_one {
        true => "the part's filename is not UTF-8: name the file's path in UTF-8",
        false => "a file part needs a filename: its path in the capture",
    };
    ApiError::malformed(Some("file".to_string()), message)
}

/// A capture read from `files`, as a scene request (at most `max_views` views) of its cameras as
/// the client would send them.
struct ReadCapture {
    request: SceneRequest,
    cameras: Vec<WireCamera>,
    names: Vec<String>,
    format: String,
    image_set: Option<String>,
    warnings: Vec<String>,
}

fn read_capture(
    mut files: MemoryFiles,
    options: &CaptureOptions,
    (limits, sizes): (&Limits, &CaptureLimits),
    parsing: &mut MemoryLease,
    cancel: &Cancel,
) -> Result<ReadCapture, ApiError> {
    let opts = ReadOptions {
        near: options.near,
        far: options.far,
        ignore_distortion: options.ignore_distortion,
        downscale: None,
        undistort: options.undistort_to,
    };
    let rule = match options.downscale {
        Some(factor) => Pick::Downscale(factor.get()),
        None => Pick::Fit { max_pixels: limits.max_source_pixels },
    };
    let read = load_picked(&Interruptible { files: &files, cancel }, Path::new(""), None, opts, rule);
    cancel.check()?;
    let (mut capture, picked) = read.map_err(capture_error)?;
    let fitted = fit_to_limit(&mut capture, limits.max_source_pixels);
    let Capture { format, views, near, far, background, mut warnings, .. } = capture;
    let image_set = picked.map(|p| picked_set(p, &mut warnings));
    warnings.extend(fitted);
    let kept = scnerf_capture::thin_evenly(views.len(), limits.max_scene_views);
    if kept.len() < views.len() {
        warnings.push(format!(
            "the capture has {} views; the scene keeps {} of them, evenly spread (the server's --max-scene-views)",
            views.len(),
            kept.len()
        ));
    }
    sizes.check(kept.iter().map(|&v| &views[v]), (near, far))?;
    let (mut sources, mut cameras, mut names) =
        (Vec::with_capacity(kept.len()), Vec::with_capacity(kept.len()), Vec::with_capacity(kept.len()));
    for (i, view) in kept.into_iter().map(|v| &views[v]).enumerate() {
        let name = MemoryFiles::normal_path(&view.image_path).unwrap_or_default().to_string_lossy().into_owned();
        let photo = files.remove(&view.image_path).ok_or_else(|| {
            ApiError::invalid(name.clone(), format!("{name}: the image of two views (\"{}\" and another)", view.name))
        })?;
        cancel.check()?;
        let image = image_as_sent(view, photo, background, parsing)?;
        // As the client would send it: validated as an upload's camera is, and what the answer reports.
        let camera = WireCamera::from(&view.camera);
        let spec = CameraSpec::from_wire(&camera, &format!("sources[{i}].camera"))?;
        sources.push(SourceSpec { camera: spec, image: Some(image), image_field: name.clone() });
        cameras.push(camera);
        names.push(name);
    }
    let background = Some(background.to_vec());
    Ok(ReadCapture {
        request: SceneRequest { sources, near, far, background, model: None },
        cameras,
        names,
        format: format.name().to_string(),
        image_set,
        warnings,
    })
}

/// The folder of the image set read; the sets sent but not read are named in a warning.
fn picked_set(picked: Picked, warnings: &mut Vec<String>) -> String {
    let unused: Vec<String> =
        picked.sets.iter().filter(|s| s.factor != picked.set.factor).map(ImageSet::describe).collect();
    if !unused.is_empty() {
        warnings.push(format!("read the image set {}; not read: {}", picked.set.describe(), unused.join(", ")));
    }
    picked.set.folder.to_string_lossy().into_owned()
}

/// The image of `view` as its camera sees it ([`scnerf_capture::upload::image_bytes`]: the photo
/// undistorted and fitted to the source limit as the `scnerf` client does). The lease that held
/// the parsing (done by now) is grown to the most that any one photo's resampling takes.
fn image_as_sent(
    view: &CapturedView,
    photo: Vec<u8>,
    background: [f64; 3],
    lease: &mut MemoryLease,
) -> Result<Bytes, ApiError> {
    let need = resample_bytes(view, &photo);
    if need == 0 {
        return Ok(Bytes::from(photo));
    }
    if need > lease.bytes() {
        lease.grow(need - lease.bytes())?;
    }
    let image = image_bytes(view, &photo, background).map_err(capture_error)?;
    Ok(Bytes::from(image.into_owned()))
}

/// `files`, failing every access once the request is gone: the readers then stop at their next
/// look at a file.
struct Interruptible<'a> {
    files: &'a MemoryFiles,
    cancel: &'a Cancel,
}

impl Interruptible<'_> {
    fn check(&self, path: &Path) -> scnerf_capture::Result<()> {
        match self.cancel.is_set() {
            true => Err(scnerf_capture::Error::io(path, std::io::ErrorKind::Interrupted.into())),
            false => Ok(()),
        }
    }
}

impl Files for Interruptible<'_> {
    fn is_file(&self, path: &Path) -> bool {
        !self.cancel.is_set() && self.files.is_file(path)
    }

    fn is_dir(&self, path: &Path) -> bool {
        !self.cancel.is_set() && self.files.is_dir(path)
    }

    fn read(&self, path: &Path) -> scnerf_capture::Result<Cow<'_, [u8]>> {
        self.check(path)?;
        self.files.read(path)
    }

    fn list(&self, dir: &Path) -> scnerf_capture::Result<Vec<PathBuf>> {
        self.check(dir)?;
        self.files.list(dir)
    }
}

/// A capture the readers refuse: 422 naming the file (relative to the capture's folder).
fn capture_error(e: scnerf_capture::Error) -> ApiError {
    if let scnerf_capture::Error::UnknownImageSet { .. } = e {
        return ApiError::invalid("downscale", e.to_string());
    }
    let field = e.path().map(|p| p.to_string_lossy().into_owned()).filter(|p| !p.is_empty());
    ApiError::invalid(field.unwrap_or_else(|| "file".to_string()), e.to_string())
}

/// Validation names a view `sources[i]...`; a capture's client knows it by its file.
fn name_the_file(e: ApiError, names: &[String]) -> ApiError {
    let file = |field: &str| {
        let index: usize = field.strip_prefix("sources[")?.split(']').next()?.parse().ok()?;
        names.get(index).cloned()
    };
    match e {
        ApiError::Invalid { field, message } => match file(&field) {
            Some(name) => ApiError::Invalid { message: format!("{name}: {message} ({field})"), field: name },
            None => ApiError::Invalid { field, message },
        },
        other => other,
    }
}
