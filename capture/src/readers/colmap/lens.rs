//! COLMAP's camera models: their parameter counts (the binary model ids) and what each means as
//! pinhole intrinsics and lens distortion.

use std::path::Path;

use super::records::CameraModel;
use crate::camera::Intrinsics;
use crate::error::{Error, Result};
use crate::undistort::Distortion;

/// Intrinsics (shifted to integer pixel centres), declared size and lens distortion of a camera.
pub(super) fn pinhole(cam: &CameraModel, id: i64, file: &Path) -> Result<(Intrinsics, (u32, u32), Distortion)> {
    let ([fx, fy, cx, cy], distortion) = lens_model(&cam.model, &cam.params).ok_or_else(|| {
        Error::dataset(
            file,
            format!(
                "camera {id} uses the {} model, which cannot be undistorted here: undistort the images first \
                 (`colmap image_undistorter` writes PINHOLE cameras)",
                cam.model
            ),
        )
    })?;
    let size = (u32::try_from(cam.width).ok(), u32::try_from(cam.height).ok());
    match size {
        (Some(w), Some(h)) if fx > 0.0 && fy > 0.0 && w > 0 && h > 0 => {
            Ok((Intrinsics { fx, fy, cx: cx - 0.5, cy: cy - 0.5 }, (w, h), distortion))
        }
        _ => Err(Error::dataset(file, format!("camera {id}: non-positive focal length or image size"))),
    }
}

/// fx, fy, cx, cy (COLMAP's pixel centres) and the distortion of a COLMAP camera model's
/// parameters (colmap/src/colmap/sensor/models.h); `None` for FOV and THIN_PRISM_FISHEYE, which
/// OpenCV's models do not cover. `params` has the model's count ([`check_params`]).
pub fn lens_model(model: &str, p: &[f64]) -> Option<([f64; 4], Distortion)> {
    let perspective = |k: [f64; 6], tangential: [f64; 2]| Distortion { fisheye: false, k, p: tangential };
    let fisheye = |k: [f64; 6]| Distortion { fisheye: true, k, p: [0.0; 2] };
    let simple = || [p[0], p[0], p[1], p[2]];
    let full = || [p[0], p[1], p[2], p[3]];
    Some(match model {
        "SIMPLE_PINHOLE" => (simple(), Distortion::NONE),
        "PINHOLE" => (full(), Distortion::NONE),
        "SIMPLE_RADIAL" => (simple(), perspective([p[3], 0.0, 0.0, 0.0, 0.0, 0.0], [0.0; 2])),
        "RADIAL" => (simple(), perspective([p[3], p[4], 0.0, 0.0, 0.0, 0.0], [0.0; 2])),
        "OPENCV" => (full(), perspective([p[4], p[5], 0.0, 0.0, 0.0, 0.0], [p[6], p[7]])),
        // k1 k2 p1 p2 k3 k4 k5 k6
        "FULL_OPENCV" => (full(), perspective([p[4], p[5], p[8], p[9], p[10], p[11]], [p[6], p[7]])),
        "OPENCV_FISHEYE" => (full(), fisheye([p[4], p[5], p[6], p[7], 0.0, 0.0])),
        "SIMPLE_RADIAL_FISHEYE" => (simple(), fisheye([p[3], 0.0, 0.0, 0.0, 0.0, 0.0])),
        "RADIAL_FISHEYE" => (simple(), fisheye([p[3], p[4], 0.0, 0.0, 0.0, 0.0])),
        _ => return None,
    })
}

/// Number of parameters of each COLMAP camera model (colmap/src/colmap/sensor/models.h), by
/// binary model id.
pub(super) const MODELS: [(&str, usize); 11] = [
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
];

fn param_count(model: &str) -> Option<usize> {
    MODELS.iter().find(|(m, _)| *m == model).map(|(_, n)| *n)
}

/// A known model with the right number of parameters (any model is parsed; `pinhole` decides
/// what is usable).
pub(super) fn check_params(cam: &CameraModel, path: &Path, at: &str) -> Result<()> {
    let names: Vec<&str> = MODELS.iter().map(|(m, _)| *m).collect();
    match param_count(&cam.model) {
        None => {
            Err(Error::dataset(path, format!("{at}: unknown camera model {} (known: {})", cam.model, names.join(", "))))
        }
        Some(n) if n != cam.params.len() => {
            Err(Error::dataset(path, format!("{at}: {} needs {n} parameters, got {}", cam.model, cam.params.len())))
        }
        Some(_) => Ok(()),
    }
}
