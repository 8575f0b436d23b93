//! nerfstudio `transforms.json`: fl_x, fl_y, cx, cy, w, h at the top level and/or per frame,
//! `file_path` per frame, `transform_matrix` camera-to-world in OpenGL axes.
//!
//! Convention (`exporter/scnerf_export/data/dataparsers/nerfstudio.py::NerfstudioParser`):
//! nerfstudio puts the first pixel's centre at (0.5, 0.5), so cx, cy are shifted by -0.5; if the
//! image on disk has another size than w x h the intrinsics are rescaled to it (pixel centres kept
//! at integers). Lens distortion (k1..k4, p1, p2) is refused unless `--ignore-distortion`. near/far
//! from the flags, else the file's `near`/`far` (or `near_far`) keys. View names are the file
//! stems, or the file paths without extension when stems repeat. A downscaled set (`--downscale N`)
//! is nerfstudio's: `images_N/<file name>` beside the transforms file, the intrinsics scaled to its
//! images.

use std::path::{Path, PathBuf};

use serde_json::Value;

use super::blender::{all_unique, frame_file_path, frames_of};
use super::{
    base_name, cameras_of, folder_name, json_f64, json_matrix4, resolve_image, skipped_warning, without_extension,
    Capture, CapturedView, DepthSource, Format, ReadOptions,
};
use crate::camera::{w2c_from_opengl_c2w, Camera, Intrinsics};
use crate::depth_range;
use crate::error::{Error, Result};
use crate::files::Files;
use crate::undistort::lens_of;
use crate::undistort::Distortion;

const MODELS: [&str; 4] = ["OPENCV", "OPENCV_FISHEYE", "PINHOLE", "SIMPLE_PINHOLE"];

pub fn load(fs: &dyn Files, path: &Path, opts: ReadOptions) -> Result<Capture> {
    let file = if fs.is_dir(path) { path.join("transforms.json") } else { path.to_path_buf() };
    if !fs.is_file(&file) {
        return Err(Error::dataset(&file, "nerfstudio transforms.json not found"));
    }
    let (data, frames) = frames_of(fs, &file)?;
    let model = data.get("camera_model").and_then(Value::as_str).unwrap_or("OPENCV").to_uppercase();
    if !MODELS.contains(&model.as_str()) {
        return Err(Error::dataset(
            &file,
            format!("camera_model {model} is not supported (one of {})", MODELS.join(", ")),
        ));
    }
    let base = file.parent().unwrap_or(Path::new("."));
    let mut warnings = Vec::new();
    let mut entries = Vec::new(); // (path without extension, view)
    for (i, frame) in frames.iter().enumerate() {
        let file_path = frame_file_path(frame, &file, i)?;
        let Some(image) = frame_image(fs, base, file_path, opts.downscale) else { continue };
        let param = |key: &str| -> Result<f64> {
            let value = frame.get(key).or_else(|| data.get(key)).ok_or_else(|| {
                Error::dataset(&file, format!("frames[{i}] has no '{key}' (neither per frame nor at the top level)"))
            })?;
            json_f64(value, &file, &format!("frames[{i}].{key}"))
        };
        let fx = param("fl_x")?;
        let has_fy = frame.get("fl_y").is_some() || data.get("fl_y").is_some();
        let fy = if has_fy { param("fl_y")? } else { fx };
        let (cx, cy) = (param("cx")?, param("cy")?);
        // Python's int() of the declared size
        let (w, h) = (param("w")?.trunc(), param("h")?.trunc());
        if fx <= 0.0 || fy <= 0.0 || w <= 0.0 || h <= 0.0 || w > f64::from(u32::MAX) || h > f64::from(u32::MAX) {
            return Err(Error::dataset(&file, format!("frames[{i}] has a non-positive focal length or size")));
        }
        let coefficient = |key: &str| -> Result<f64> {
            if frame.get(key).is_some() || data.get(key).is_some() {
                param(key)
            } else {
                Ok(0.0)
            }
        };
        let distortion = distortion(&model, coefficient, &file, i)?;
        let matrix = json_matrix4(&frame["transform_matrix"], &file, &format!("frames[{i}].transform_matrix"))?;
        let w2c = w2c_from_opengl_c2w(&matrix).ok_or_else(|| {
            Error::dataset(&file, format!("frames[{i}].transform_matrix is not a rigid camera-to-world transform"))
        })?;
        let photo = Camera {
            width: w as u32,
            height: h as u32,
            intrinsics: Intrinsics { fx, fy, cx: cx - 0.5, cy: cy - 0.5 },
            w2c,
        };
        let (aw, ah) = fs.image_size(&image)?;
        let photo = if (aw, ah) == (photo.width, photo.height) { photo } else { photo.resized(aw, ah) };
        let (camera, lens) = lens_of(
            photo,
            distortion,
            opts.ignore_distortion,
            opts.undistort,
            &format!("frames[{i}]"),
            &file,
            &mut warnings,
        )?;
        let view = CapturedView { name: String::new(), image_path: image, camera, lens };
        entries.push((without_extension(file_path), view));
    }
    if entries.is_empty() {
        return Err(Error::dataset(&file, "none of the listed frames has an image file"));
    }
    let stems: Vec<String> = entries.iter().map(|(rel, _)| base_name(rel)).collect();
    let unique = all_unique(&stems);
    let views = entries
        .into_iter()
        .zip(stems)
        .map(|((rel, view), stem)| CapturedView { name: if unique { stem } else { rel }, ..view })
        .collect::<Vec<_>>();
    warnings.extend(skipped_warning(&file.display().to_string(), frames.len() - views.len(), frames.len()));
    let (near, far) = near_far(&data, &file)?;
    let (near, far, depth_source) =
        depth_range::resolve((opts.near, opts.far), (near, far, DepthSource::Dataset), &cameras_of(&views), &file)?;
    Ok(Capture { format: Format::Nerfstudio, views, near, far, depth_source, background: [0.0; 3], warnings })
}

/// A frame's distortion from its coefficients (per frame or at the top level, zero when absent)
/// by `camera_model`: OPENCV's k1, k2, k3, p1, p2 are OpenCV's; OPENCV_FISHEYE's k1..k4 are
/// OpenCV's fisheye ones. nerfstudio's k4 of OPENCV (a term in r⁸, not OpenCV's rational k4) and
/// p1, p2 of a fisheye are refused rather than dropped.
fn distortion(model: &str, coefficient: impl Fn(&str) -> Result<f64>, file: &Path, i: usize) -> Result<Distortion> {
    let [k1, k2, k3, k4, p1, p2] = ["k1", "k2", "k3", "k4", "p1", "p2"].map(&coefficient);
    let (k1, k2, k3, k4, p1, p2) = (k1?, k2?, k3?, k4?, p1?, p2?);
    let refuse = |key: &str, why: &str| Error::dataset(file, format!("frames[{i}].{key} is not zero: {why}"));
    if model == "OPENCV_FISHEYE" {
        if p1 != 0.0 || p2 != 0.0 {
            return Err(refuse(if p1 != 0.0 { "p1" } else { "p2" }, "OPENCV_FISHEYE has no tangential distortion"));
        }
        return Ok(Distortion { fisheye: true, k: [k1, k2, k3, k4, 0.0, 0.0], p: [0.0; 2] });
    }
    if k4 != 0.0 {
        return Err(refuse(
            "k4",
            "nerfstudio's k4 of OPENCV (a term in r^8) is not supported; undistort the images first",
        ));
    }
    Ok(Distortion { fisheye: false, k: [k1, k2, k3, 0.0, 0.0, 0.0], p: [p1, p2] })
}

/// The image of a frame: its `file_path`, or with `--downscale N` nerfstudio's downscaled copy,
/// the file of the same name in `images_N` (its dataparser's `_get_fname`).
fn frame_image(fs: &dyn Files, base: &Path, file_path: &str, downscale: Option<u32>) -> Option<PathBuf> {
    match downscale.filter(|&n| n > 1) {
        Some(n) => resolve_image(fs, &base.join(folder_name(n)), &base_name(file_path)),
        None => resolve_image(fs, base, file_path),
    }
}

/// `near`/`far` keys, each falling back to the matching element of `near_far`.
fn near_far(data: &Value, file: &Path) -> Result<(Option<f64>, Option<f64>)> {
    let pair = data.get("near_far").and_then(Value::as_array).filter(|a| a.len() == 2);
    let pick = |key: &str, idx: usize| -> Result<Option<f64>> {
        match data.get(key).or_else(|| pair.map(|p| &p[idx])) {
            Some(v) => json_f64(v, file, key).map(Some),
            None => Ok(None),
        }
    };
    Ok((pick("near", 0)?, pick("far", 1)?))
}
