//! COLMAP sparse models, text (`cameras.txt`, `images.txt`, `points3D.txt`) or binary (`.bin`),
//! with the images in `<scene>/images/`.
//!
//! Convention (`exporter/scnerf_export/data/dataparsers/colmap.py::ColmapParser`, which reads both
//! forms too): the model is looked for in `<scene>`, `<scene>/sparse/0`, `<scene>/sparse` (text
//! first, then binary). Poses are world-to-camera in OpenCV axes already (qw qx qy qz tx ty tz).
//! COLMAP's first pixel centre is at (0.5, 0.5): cx, cy are shifted by -0.5. PINHOLE and
//! SIMPLE_PINHOLE are used as they are; the photos of the radial, OpenCV and fisheye models are
//! undistorted (`crate::undistort`; with `--ignore-distortion`, used as pinhole); FOV and
//! THIN_PRISM_FISHEYE are refused. Intrinsics are rescaled when the image on disk has another size
//! than the camera, which is how a downscaled set beside `images/` (`images_N`, `--downscale N`) is
//! read. near/far: 0.9 x the 1st and 1.1 x the 99th percentile of the z-depths of the 3D points in
//! the views that observe them (every view for a point without a track). Views are in natural
//! order of their image names; names drop the extension.

mod binary;
mod depth;
mod lens;
mod records;
mod text;

pub use depth::MAX_DEPTHS;
pub use lens::lens_model;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use super::{
    cameras_of, folder_name, natural_cmp, without_extension, Capture, CapturedView, DepthSource, Format, ReadOptions,
};
use crate::camera::Camera;
use crate::depth_range;
use crate::error::{Error, Result};
use crate::files::Files;
use crate::undistort::lens_of;
use depth::points_near_far;
use lens::pinhole;
use records::CameraModel;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    Text,
    Binary,
}

/// The folder and encoding of the model: text anywhere first (the Python loader's rule), then
/// binary.
pub fn find_model(fs: &dyn Files, root: &Path) -> Option<(PathBuf, Encoding)> {
    let dirs = [root.to_path_buf(), root.join("sparse").join("0"), root.join("sparse")];
    [(Encoding::Text, "txt"), (Encoding::Binary, "bin")].into_iter().find_map(|(encoding, ext)| {
        dirs.iter()
            .find(|d| fs.is_file(&d.join(format!("cameras.{ext}"))) && fs.is_file(&d.join(format!("images.{ext}"))))
            .map(|d| (d.clone(), encoding))
    })
}

pub fn load(fs: &dyn Files, path: &Path, opts: ReadOptions) -> Result<Capture> {
    let (dir, encoding) = find_model(fs, path).ok_or_else(|| {
        Error::dataset(path, "no COLMAP model (cameras + images, .txt or .bin) in ., sparse/0 or sparse")
    })?;
    let ext = if encoding == Encoding::Text { "txt" } else { "bin" };
    let (cameras_file, images_file) = (dir.join(format!("cameras.{ext}")), dir.join(format!("images.{ext}")));
    let (cameras, mut images) = match encoding {
        Encoding::Text => (text::cameras(fs, &cameras_file)?, text::images(fs, &images_file)?),
        Encoding::Binary => (binary::cameras(fs, &cameras_file)?, binary::images(fs, &images_file)?),
    };
    let image_dir = path.join(folder_name(opts.downscale.unwrap_or(1)));
    if !fs.is_dir(&image_dir) {
        return Err(Error::dataset(&image_dir, "COLMAP images folder not found"));
    }
    let mut warnings = Vec::new();
    let mut intrinsics = HashMap::new();
    for (id, cam) in &cameras {
        intrinsics.insert(*id, pinhole(cam, *id, &cameras_file)?);
    }
    images.sort_by(|a, b| natural_cmp(&a.name, &b.name));
    let mut views = Vec::new();
    for img in &images {
        let (cam, declared, distortion) = intrinsics.get(&img.camera_id).ok_or_else(|| {
            Error::dataset(&images_file, format!("image {} uses unknown camera {}", img.name, img.camera_id))
        })?;
        let image_path = image_dir.join(&img.name);
        if !fs.is_file(&image_path) {
            continue;
        }
        let declared = Camera { width: declared.0, height: declared.1, intrinsics: *cam, w2c: img.w2c };
        let (w, h) = fs.image_size(&image_path)?;
        let photo = if (w, h) == (declared.width, declared.height) { declared } else { declared.resized(w, h) };
        let what = format!("camera {} ({})", img.camera_id, cameras_model(&cameras, img.camera_id));
        let (camera, lens) =
            lens_of(photo, *distortion, opts.ignore_distortion, opts.undistort, &what, &cameras_file, &mut warnings)?;
        views.push(CapturedView { name: without_extension(&img.name), image_path, camera, lens });
    }
    let missing = images.len() - views.len();
    if missing > 0 {
        warnings.push(format!(
            "{}: {missing} of {} images are missing from {}; skipped",
            images_file.display(),
            images.len(),
            image_dir.display()
        ));
    }
    if views.is_empty() {
        return Err(Error::dataset(
            &images_file,
            format!("none of the listed images exists in {}", image_dir.display()),
        ));
    }
    let points_file = dir.join(format!("points3D.{ext}"));
    // The points serve only the depth range: not read when the options give it.
    let given = opts.near.is_some() && opts.far.is_some();
    let from_points = if fs.is_file(&points_file) && !given {
        let points = match encoding {
            Encoding::Text => text::points(fs, &points_file)?,
            Encoding::Binary => binary::points(fs, &points_file)?,
        };
        points_near_far(&points, &images, &points_file)?
    } else {
        None
    };
    let from_data = (from_points.map(|p| p.0), from_points.map(|p| p.1), DepthSource::Points);
    let (near, far, depth_source) = depth_range::resolve((opts.near, opts.far), from_data, &cameras_of(&views), &dir)?;
    Ok(Capture { format: Format::Colmap, views, near, far, depth_source, background: [0.0; 3], warnings })
}

fn cameras_model(cameras: &[(i64, CameraModel)], id: i64) -> &str {
    cameras.iter().find(|(i, _)| *i == id).map_or("", |(_, c)| c.model.as_str())
}
