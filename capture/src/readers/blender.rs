//! NeRF-synthetic ("Blender") scenes: `transforms_{train,val,test}.json` (or one given file).
//!
//! Convention (`exporter/scnerf_export/data/dataparsers/blender.py::BlenderParser`, MVSNeRF's):
//! fx = fy = 0.5 W / tan(0.5 camera_angle_x) (fy from camera_angle_y when given), cx = W/2,
//! cy = H/2 with W, H read from each image, no half-pixel shift; `transform_matrix` is
//! camera-to-world in OpenGL axes; near/far 2/6; RGBA composited on white. Frames without an image
//! file are skipped (one warning). View names are the image stems ("r_6"), or "split/stem" for all
//! views when two splits share a stem.

use std::path::{Path, PathBuf};

use super::{
    cameras_of, json_f64, json_matrix4, read_json, resolve_image, skipped_warning, Capture, CapturedView, DepthSource,
    Format, ReadOptions,
};
use crate::camera::{w2c_from_opengl_c2w, Camera, Intrinsics, Pose};
use crate::depth_range;
use crate::error::{Error, Result};
use crate::files::Files;

const NEAR_FAR: (f64, f64) = (2.0, 6.0);

struct Entry {
    split: String,
    stem: String,
    image: PathBuf,
    w2c: Pose,
    angle_x: f64,
    angle_y: Option<f64>,
}

pub fn load(fs: &dyn Files, path: &Path, opts: ReadOptions) -> Result<Capture> {
    let files = transforms_files(fs, path)?;
    let mut entries = Vec::new();
    let (mut listed, mut skipped) = (0, 0);
    for file in &files {
        let (data, frames) = frames_of(fs, file)?;
        listed += frames.len();
        skipped += frames.len() - read_entries(fs, file, &data, &frames, &mut entries)?;
    }
    if entries.is_empty() {
        return Err(Error::dataset(path, "none of the frames listed in the transforms files has an image file"));
    }
    let names = unique_names(&entries, path)?;
    let mut views = Vec::with_capacity(entries.len());
    for (name, e) in names.into_iter().zip(entries) {
        let (w, h) = fs.image_size(&e.image)?;
        let fx = 0.5 * f64::from(w) / (0.5 * e.angle_x).tan();
        let fy = e.angle_y.map_or(fx, |ay| 0.5 * f64::from(h) / (0.5 * ay).tan());
        let intrinsics = Intrinsics { fx, fy, cx: f64::from(w) / 2.0, cy: f64::from(h) / 2.0 };
        views.push(CapturedView {
            name,
            image_path: e.image,
            camera: Camera { width: w, height: h, intrinsics, w2c: e.w2c },
            lens: None,
        });
    }
    let file_names: Vec<String> = files.iter().map(|f| f.display().to_string()).collect();
    let warnings = skipped_warning(&file_names.join(", "), skipped, listed).into_iter().collect();
    let (near, far, depth_source) = depth_range::resolve(
        (opts.near, opts.far),
        (Some(NEAR_FAR.0), Some(NEAR_FAR.1), DepthSource::Dataset),
        &cameras_of(&views),
        path,
    )?;
    Ok(Capture { depth_source, format: Format::Blender, views, near, far, background: [1.0; 3], warnings })
}

/// transforms_{train,val,test}.json in that order, else transforms.json, else the file given.
fn transforms_files(fs: &dyn Files, path: &Path) -> Result<Vec<PathBuf>> {
    if fs.is_file(path) {
        return Ok(vec![path.to_path_buf()]);
    }
    if !fs.is_dir(path) {
        return Err(Error::dataset(path, "Blender scene not found"));
    }
    let splits: Vec<PathBuf> = ["train", "val", "test"]
        .iter()
        .map(|s| path.join(format!("transforms_{s}.json")))
        .filter(|p| fs.is_file(p))
        .collect();
    if !splits.is_empty() {
        return Ok(splits);
    }
    let single = path.join("transforms.json");
    if fs.is_file(&single) {
        return Ok(vec![single]);
    }
    Err(Error::dataset(path, "no transforms_{train,val,test}.json or transforms.json"))
}

/// The file's JSON object and its `frames` list.
pub(super) fn frames_of(fs: &dyn Files, file: &Path) -> Result<(serde_json::Value, Vec<serde_json::Value>)> {
    let mut data = read_json(fs, file)?;
    let frames = match data.get_mut("frames").map(serde_json::Value::take) {
        Some(serde_json::Value::Array(frames)) => frames,
        _ => return Err(Error::dataset(file, "not a transforms.json (needs a 'frames' list)")),
    };
    Ok((data, frames))
}

/// Appends the frames of one file that have an image; returns how many it appended.
fn read_entries(
    fs: &dyn Files,
    file: &Path,
    data: &serde_json::Value,
    frames: &[serde_json::Value],
    entries: &mut Vec<Entry>,
) -> Result<usize> {
    let angle_x = match data.get("camera_angle_x") {
        Some(v) => json_f64(v, file, "camera_angle_x")?,
        None => {
            return Err(Error::dataset(file, "no 'camera_angle_x' (for fl_x/fl_y/cx/cy files use --format nerfstudio)"))
        }
    };
    if !(angle_x > 0.0 && angle_x < std::f64::consts::PI) {
        return Err(Error::dataset(file, format!("camera_angle_x {angle_x} is not an angle in (0, pi)")));
    }
    let angle_y = data.get("camera_angle_y").map(|v| json_f64(v, file, "camera_angle_y")).transpose()?;
    let split = file
        .file_name()
        .and_then(|n| n.to_str())
        .and_then(|n| n.strip_prefix("transforms_"))
        .and_then(|n| n.strip_suffix(".json"))
        .unwrap_or("")
        .to_string();
    let base = file.parent().unwrap_or(Path::new("."));
    let before = entries.len();
    for (i, frame) in frames.iter().enumerate() {
        let file_path = frame_file_path(frame, file, i)?;
        let Some(image) = resolve_image(fs, base, file_path) else { continue };
        let matrix = json_matrix4(&frame["transform_matrix"], file, &format!("frames[{i}].transform_matrix"))?;
        let w2c = w2c_from_opengl_c2w(&matrix).ok_or_else(|| {
            Error::dataset(file, format!("frames[{i}].transform_matrix is not a rigid camera-to-world transform"))
        })?;
        let stem = image.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        entries.push(Entry { split: split.clone(), stem, image, w2c, angle_x, angle_y });
    }
    Ok(entries.len() - before)
}

pub(super) fn frame_file_path<'a>(frame: &'a serde_json::Value, file: &Path, i: usize) -> Result<&'a str> {
    frame
        .get("file_path")
        .and_then(|p| p.as_str())
        .ok_or_else(|| Error::dataset(file, format!("frames[{i}] has no 'file_path'")))
}

/// Stems when unique, else "split/stem" for every view (`blender.py::_unique_names`).
fn unique_names(entries: &[Entry], path: &Path) -> Result<Vec<String>> {
    let stems: Vec<String> = entries.iter().map(|e| e.stem.clone()).collect();
    if all_unique(&stems) {
        return Ok(stems);
    }
    let full: Vec<String> = entries
        .iter()
        .map(|e| if e.split.is_empty() { e.stem.clone() } else { format!("{}/{}", e.split, e.stem) })
        .collect();
    if !all_unique(&full) {
        return Err(Error::dataset(path, "two frames name the same image: duplicate view names"));
    }
    Ok(full)
}

pub(super) fn all_unique(names: &[String]) -> bool {
    let set: std::collections::HashSet<&String> = names.iter().collect();
    set.len() == names.len()
}
