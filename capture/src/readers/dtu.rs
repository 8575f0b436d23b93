//! DTU scans in MVSNeRF's layout: `Cameras/train/000000NN_cam.txt` (or `Cameras/`) and
//! `Rectified/scanS_train/rect_{NN+1:03}_3_r5000.png` (lighting 3, 640x512).
//!
//! Convention (`exporter/scnerf_export/data/dataparsers/dtu.py::DtuParser`): MVSNet cam.txt,
//! world-to-camera in millimetres and intrinsics at 1/4 of 640x512; the first two rows of K are
//! multiplied by 4 (MVSNeRF's convention: no half-pixel shift) and the world is scaled by 1/200.
//! near = smallest depth_min / 200, far = largest (depth_min + 192 depth_interval) / 200
//! (2.125 / 4.525 for the usual "425 2.5"). Views are named by their number ("25"); cameras
//! without an image are skipped (one warning).

use std::path::{Path, PathBuf};

use nalgebra::Matrix4;

use super::{cameras_of, Capture, CapturedView, DepthSource, Format, ReadOptions};
use crate::camera::{pose_from_matrix, Camera, Intrinsics};
use crate::depth_range;
use crate::error::{Error, Result};
use crate::files::Files;

/// MVSNeRF's world scale: millimetres x 1/200.
const SCALE: f64 = 1.0 / 200.0;
/// depth_max = depth_min + depth_interval x 192 (MVSNet / MVSNeRF).
const NUM_DEPTHS: f64 = 192.0;
const SIZE: (u32, u32) = (640, 512);

pub fn load(fs: &dyn Files, path: &Path, opts: ReadOptions) -> Result<Capture> {
    if !fs.is_dir(path) {
        return Err(Error::dataset(path, "DTU scene folder not found"));
    }
    let train = path.join("Cameras/train");
    let cam_dir = if fs.is_dir(&train) { train } else { path.join("Cameras") };
    let cam_files = camera_files(fs, &cam_dir)?;
    let image_dir = image_dir(fs, path)?;
    let (mut views, mut nears, mut fars, mut skipped) = (Vec::new(), Vec::new(), Vec::new(), 0);
    for (id, file) in &cam_files {
        let image_path = image_dir.join(format!("rect_{:03}_3_r5000.png", u64::from(*id) + 1));
        if !fs.is_file(&image_path) {
            skipped += 1;
            continue;
        }
        let cam = parse_cam(fs, file)?;
        nears.push(cam.depth_min * SCALE);
        fars.push((cam.depth_min + cam.depth_interval * NUM_DEPTHS) * SCALE);
        if fs.image_size(&image_path)? != SIZE {
            return Err(Error::dataset(&image_path, "expected a 640x512 image (MVSNeRF's DTU)"));
        }
        let camera = Camera { width: SIZE.0, height: SIZE.1, intrinsics: cam.intrinsics, w2c: cam.w2c };
        views.push(CapturedView { name: id.to_string(), image_path, camera, lens: None });
    }
    if views.is_empty() {
        return Err(Error::dataset(path, "no DTU view has both a camera and an image"));
    }
    let warnings = (skipped > 0)
        .then(|| format!("{}: {skipped} of {} cameras have no image; skipped", cam_dir.display(), cam_files.len()))
        .into_iter()
        .collect();
    let near = nears.iter().copied().fold(f64::INFINITY, f64::min);
    let far = fars.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let (near, far, depth_source) = depth_range::resolve(
        (opts.near, opts.far),
        (Some(near), Some(far), DepthSource::Dataset),
        &cameras_of(&views),
        path,
    )?;
    Ok(Capture { depth_source, format: Format::Dtu, views, near, far, background: [0.0; 3], warnings })
}

/// `NNNNNNNN_cam.txt` files with their view numbers, sorted by file name.
fn camera_files(fs: &dyn Files, dir: &Path) -> Result<Vec<(u32, PathBuf)>> {
    let mut files = fs.list(dir)?;
    files.sort();
    let numbered: Vec<(u32, PathBuf)> = files
        .into_iter()
        .filter_map(|p| {
            let name = p.file_name()?.to_str()?;
            let digits = name.strip_suffix("_cam.txt")?;
            let all_digits = !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit());
            Some((digits.parse().ok().filter(|_| all_digits)?, p))
        })
        .collect();
    if numbered.is_empty() {
        return Err(Error::dataset(dir, "no MVSNet camera files (*_cam.txt)"));
    }
    Ok(numbered)
}

/// `Rectified/scanS_train` or `Rectified/scanS` for a folder named like `scanS`, else the one
/// sub-folder of `Rectified`, else `Rectified` itself when it holds the images.
fn image_dir(fs: &dyn Files, root: &Path) -> Result<PathBuf> {
    let rect = root.join("Rectified");
    let mut candidates: Vec<PathBuf> = fs.list(&rect)?.into_iter().filter(|p| fs.is_dir(p)).collect();
    candidates.sort();
    if let Some(scan) = scan_number(root) {
        let preferred: Vec<PathBuf> = candidates
            .iter()
            .filter(|p| {
                p.file_name()
                    .is_some_and(|n| n == format!("scan{scan}_train").as_str() || n == format!("scan{scan}").as_str())
            })
            .cloned()
            .collect();
        if !preferred.is_empty() {
            candidates = preferred;
        }
    }
    match candidates.as_slice() {
        [one] => Ok(one.clone()),
        [] if has_rect_images(fs, &rect) => Ok(rect),
        _ => Err(Error::dataset(&rect, format!("cannot tell which folder holds the images: {candidates:?}"))),
    }
}

fn has_rect_images(fs: &dyn Files, dir: &Path) -> bool {
    fs.list(dir).is_ok_and(|entries| {
        entries.iter().filter_map(|p| p.file_name()).any(|n| {
            let name = n.to_string_lossy();
            name.starts_with("rect_") && name.ends_with(".png")
        })
    })
}

/// The digits after the first "scan" in the folder name (Python's `re.search(r"scan(\d+)")`).
fn scan_number(root: &Path) -> Option<String> {
    let name = root.file_name()?.to_str()?;
    name.match_indices("scan").find_map(|(i, _)| {
        let digits: String = name[i + 4..].chars().take_while(char::is_ascii_digit).collect();
        (!digits.is_empty()).then_some(digits)
    })
}

struct DtuCamera {
    intrinsics: Intrinsics,
    w2c: crate::camera::Pose,
    depth_min: f64,
    depth_interval: f64,
}

/// MVSNet cam.txt: "extrinsic" then 16 numbers, "intrinsic" then 9 numbers, then depth_min and
/// depth_interval; scaled to MVSNeRF's units.
fn parse_cam(fs: &dyn Files, path: &Path) -> Result<DtuCamera> {
    let text = fs.read_text(path)?;
    // ASCII only: the indices found in `low` must be those of `text`.
    let low = text.to_ascii_lowercase();
    let (i_ext, i_int) = match (low.find("extrinsic"), low.find("intrinsic")) {
        (Some(e), Some(i)) if e < i => (e, i),
        _ => return Err(Error::dataset(path, "not an MVSNet cam.txt (needs 'extrinsic' then 'intrinsic' sections)")),
    };
    // At most `max` numbers: 16 then 11 are all a camera has (a longer section is refused or
    // its tail ignored, as before, without being read into memory).
    let numbers = |s: &str, max: usize| -> Result<Vec<f64>> {
        s.split_whitespace()
            .take(max)
            .map(|t| {
                t.parse().map_err(|_| {
                    let shown: String = t.chars().take(32).collect();
                    Error::dataset(path, format!("malformed number in cam.txt: {shown:?}"))
                })
            })
            .collect()
    };
    let ext = numbers(&text[i_ext + "extrinsic".len()..i_int], 17)?;
    let rest = numbers(&text[i_int + "intrinsic".len()..], 11)?;
    if ext.len() != 16 {
        let found = if ext.len() > 16 { "more".to_string() } else { ext.len().to_string() };
        return Err(Error::dataset(path, format!("extrinsic must have 16 numbers, found {found}")));
    }
    if rest.len() < 11 {
        return Err(Error::dataset(
            path,
            format!("need 9 intrinsic numbers then 'depth_min depth_interval', found {} numbers", rest.len()),
        ));
    }
    let k = &rest[..9];
    if k[1] != 0.0 || k[3] != 0.0 || k[6..9] != [0.0, 0.0, 1.0] || !(k[0] > 0.0 && k[4] > 0.0) {
        return Err(Error::dataset(path, "intrinsic must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0"));
    }
    let (depth_min, depth_interval) = (rest[9], rest[10]);
    // The far depth finite as well (so both numbers are): an infinite one would be refused later,
    // away from the file that holds it.
    let far = depth_min + depth_interval * NUM_DEPTHS;
    if !(depth_min > 0.0 && depth_interval > 0.0 && far.is_finite()) {
        return Err(Error::dataset(path, format!("invalid depth range {depth_min} {depth_interval}")));
    }
    let mut w2c = Matrix4::from_row_slice(&ext);
    for r in 0..3 {
        w2c[(r, 3)] *= SCALE;
    }
    let w2c = pose_from_matrix(&w2c)
        .ok_or_else(|| Error::dataset(path, "extrinsic is not a finite rigid world-to-camera transform"))?;
    let intrinsics = Intrinsics { fx: k[0] * 4.0, fy: k[4] * 4.0, cx: k[2] * 4.0, cy: k[5] * 4.0 };
    Ok(DtuCamera { intrinsics, w2c, depth_min, depth_interval })
}
