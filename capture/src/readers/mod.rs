//! Dataset readers, one module per format (like nerfstudio's `data/dataparsers/`), all giving a
//! [`Capture`] in the canonical camera form of [`crate::camera`]. Each mirrors the Python parser
//! of the same format in `exporter/scnerf_export/data/dataparsers/`; the fixtures under
//! `tests/fixtures/datasets/` are read by both and compared with what the Python loader wrote.
//!
//! Readers read through [`Files`]: a folder on disk ([`load`]) or files held in memory
//! ([`load_from`] with [`crate::files::MemoryFiles`]). They do not decode images: they read image
//! headers for sizes, and the images are sent as they are (the server composites alpha on
//! `background`).

pub mod blender;
pub mod colmap;
pub mod dtu;
mod json;
pub mod llff;
mod names;
pub mod nerfstudio;

use std::path::{Path, PathBuf};

use crate::camera::Camera;
pub use crate::depth_range::DepthSource;
use crate::error::{Error, Result};
use crate::files::{Disk, Files};
use crate::undistort::{Fit, Lens};
use json::{json_f64, json_matrix4};
pub use json::{read_json, MAX_JSON_VALUES};
use names::{base_name, resolve_image, skipped_warning, without_extension};
pub use names::{folder_name, has_image_extension, list_images, natural_cmp, IMAGE_EXTENSIONS};

#[derive(Debug, Clone)]
pub struct CapturedView {
    /// Unique within the capture, as the Python loader names it ("r_6", "25", "frame_00001").
    pub name: String,
    pub image_path: PathBuf,
    /// The camera of the image as it is sent: the photo's, or with [`Self::lens`] the pinhole
    /// camera the photo is undistorted to; scaled when the image is resized to fit.
    pub camera: Camera,
    /// The photo's distortion, when it is undistorted before it is sent ([`crate::upload`]).
    pub lens: Option<Lens>,
}

#[derive(Debug, Clone)]
pub struct Capture {
    pub format: Format,
    pub views: Vec<CapturedView>,
    pub near: f64,
    pub far: f64,
    /// Where `near` and `far` come from.
    pub depth_source: DepthSource,
    /// What transparent pixels are composited on (white for Blender, black otherwise).
    pub background: [f64; 3],
    /// Things the user should know (skipped frames, ignored fields), printed by the CLI.
    pub warnings: Vec<String>,
}

impl Capture {
    pub fn view(&self, name: &str) -> Result<&CapturedView> {
        self.views.iter().find(|v| v.name == name).ok_or_else(|| Error::UnknownView {
            name: name.to_string(),
            known: self.views.iter().map(|v| v.name.clone()).collect(),
        })
    }
}

/// What the command line adds to a dataset.
#[derive(Debug, Clone, Copy, Default)]
pub struct ReadOptions {
    /// Each overrides the dataset's own.
    pub near: Option<f64>,
    pub far: Option<f64>,
    /// Use cameras with lens distortion as pinhole (what the Python loaders do, with a warning)
    /// instead of refusing them.
    pub ignore_distortion: bool,
    /// Read the downscaled image set `images_N` instead of `images/` (LLFF, nerfstudio, COLMAP;
    /// [`crate::image_sets`]); the cameras are scaled to its images.
    pub downscale: Option<u32>,
    /// Which pinhole camera distorted photos are undistorted to.
    pub undistort: Fit,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Colmap,
    Nerfstudio,
    Blender,
    Llff,
    Dtu,
}

impl Format {
    pub fn name(self) -> &'static str {
        match self {
            Format::Colmap => "colmap",
            Format::Nerfstudio => "nerfstudio",
            Format::Blender => "blender",
            Format::Llff => "llff",
            Format::Dtu => "dtu",
        }
    }
}

/// Which layout a folder holds. The order matters: LLFF and nerfstudio folders often carry the
/// COLMAP model they were made from, so COLMAP is the last guess.
pub fn detect(fs: &dyn Files, path: &Path) -> Result<Format> {
    if let Some(format) = detect_by_names(fs, path)? {
        return Ok(format);
    }
    let file = if fs.is_file(path) { path.to_path_buf() } else { path.join("transforms.json") };
    Ok(if is_blender_json(fs, &file)? { Format::Blender } else { Format::Nerfstudio })
}

/// What the file names alone say of a folder's layout ([`detect`]'s rule): its format, or `None`
/// for a transforms file (the one given, or a folder's single `transforms.json`), which is
/// Blender's or nerfstudio's by its content.
pub fn detect_by_names(fs: &dyn Files, path: &Path) -> Result<Option<Format>> {
    if fs.is_file(path) {
        // a transforms file given directly
        return match path.extension().and_then(|e| e.to_str()) {
            Some("json") => Ok(None),
            _ => Err(Error::dataset(path, "not a dataset folder or transforms JSON file")),
        };
    }
    if !fs.is_dir(path) {
        return Err(Error::dataset(path, "no such dataset folder"));
    }
    let format = if fs.is_file(&path.join("poses_bounds.npy")) {
        Format::Llff
    } else if fs.is_dir(&path.join("Cameras")) {
        Format::Dtu
    } else if ["train", "val", "test"].iter().any(|s| fs.is_file(&path.join(format!("transforms_{s}.json")))) {
        Format::Blender
    } else if fs.is_file(&path.join("transforms.json")) {
        return Ok(None);
    } else if colmap::find_model(fs, path).is_some() {
        Format::Colmap
    } else {
        return Err(Error::dataset(
            path,
            "cannot tell the dataset format: expected poses_bounds.npy (LLFF), Cameras/ (DTU), \
             transforms_*.json (Blender), transforms.json (nerfstudio) or a COLMAP model \
             (cameras/images .txt or .bin in ., sparse/0 or sparse); or pass --format",
        ));
    };
    Ok(Some(format))
}

/// Blender files give `camera_angle_x`; nerfstudio files give `fl_x`.
fn is_blender_json(fs: &dyn Files, path: &Path) -> Result<bool> {
    let data = read_json(fs, path)?;
    Ok(data.get("camera_angle_x").is_some() && data.get("fl_x").is_none())
}

/// Reads a capture folder on disk; `format` `None` detects it.
pub fn load(path: &Path, format: Option<Format>, opts: ReadOptions) -> Result<Capture> {
    load_from(&Disk, path, format, opts)
}

/// Reads the capture at `path` of `fs` (`""`: the root of an in-memory file set); `format`
/// `None` detects it.
pub fn load_from(fs: &dyn Files, path: &Path, format: Option<Format>, opts: ReadOptions) -> Result<Capture> {
    let format = match format {
        Some(f) => f,
        None => detect(fs, path)?,
    };
    let capture = match format {
        Format::Colmap => colmap::load(fs, path, opts),
        Format::Nerfstudio => nerfstudio::load(fs, path, opts),
        Format::Blender => blender::load(fs, path, opts),
        Format::Llff => llff::load(fs, path, opts),
        Format::Dtu => dtu::load(fs, path, opts),
    }?;
    if capture.views.len() < 3 {
        return Err(Error::dataset(
            path,
            format!("only {} view(s) have an image; a capture needs at least 3", capture.views.len()),
        ));
    }
    Ok(capture)
}

/// The views' cameras, for the depth range their poses give.
fn cameras_of(views: &[CapturedView]) -> Vec<&Camera> {
    views.iter().map(|v| &v.camera).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_order_matches_python() {
        let mut names = vec!["img10.png", "img2.png", "img02.png", "a", "10", "9b", "img2.jpg"];
        names.sort_by(|a, b| natural_cmp(a, b));
        // Python: sorted(names, key=natural_key)
        assert_eq!(names, vec!["9b", "10", "a", "img2.jpg", "img2.png", "img02.png", "img10.png"]);
    }

    #[test]
    fn python_style_path_helpers() {
        assert_eq!(without_extension("./images/frame_00001.png"), "./images/frame_00001");
        assert_eq!(without_extension("a.tar.gz"), "a.tar");
        // nerfstudio view names: the base name of the path without its extension
        assert_eq!(base_name(&without_extension("images/frame_00001.png")), "frame_00001");
        assert_eq!(base_name(&without_extension("./images/frame.v2.png")), "frame.v2");
    }
}
