//! A capture read into a scene request: the readers over the files, the image set picked, the
//! views thinned, and each view's photo as the client would send it.

use std::path::Path;

use bytes::Bytes;
use scnerf_capture::files::MemoryFiles;
use scnerf_capture::image_sets::{load_picked, ImageSet, Picked};
use scnerf_capture::readers::{Capture, CapturedView};
use scnerf_capture::upload::{fit_to_limit, image_bytes, resample_bytes};
use scnerf_capture::wire::WireCamera;

use super::files::Interruptible;
use super::limits::CaptureLimits;
use super::options::CaptureOptions;
use super::refusals::capture_error;
use crate::backend::MemoryLease;
use crate::blocking::Cancel;
use crate::error::ApiError;
use crate::request::cameras::CameraSpec;
use crate::request::{Limits, SceneRequest, SourceSpec};

/// A capture read from `files`, as a scene request (at most `max_views` views) of its cameras as
/// the client would send them.
pub(super) struct ReadCapture {
    pub(super) request: SceneRequest,
    pub(super) cameras: Vec<WireCamera>,
    pub(super) names: Vec<String>,
    pub(super) format: String,
    pub(super) image_set: Option<String>,
    pub(super) warnings: Vec<String>,
}

pub(super) fn read_capture(
    mut files: MemoryFiles,
    options: &CaptureOptions,
    (limits, sizes): (&Limits, &CaptureLimits),
    parsing: &mut MemoryLease,
    cancel: &Cancel,
) -> Result<ReadCapture, ApiError> {
    let (opts, rule) = (options.read_options(), options.pick(limits));
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
