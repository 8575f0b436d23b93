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
pub mod llff;
pub mod nerfstudio;

use std::cmp::Ordering;
use std::path::{Path, PathBuf};

use crate::camera::Camera;
pub use crate::depth_range::DepthSource;
use crate::error::{Error, Result};
use crate::files::{Disk, Files};
use crate::undistort::{pinhole_for, Distortion, Fit, Lens};

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
    if fs.is_file(path) {
        // a transforms file given directly
        return match path.extension().and_then(|e| e.to_str()) {
            Some("json") if is_blender_json(fs, path)? => Ok(Format::Blender),
            Some("json") => Ok(Format::Nerfstudio),
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
        if is_blender_json(fs, &path.join("transforms.json"))? {
            Format::Blender
        } else {
            Format::Nerfstudio
        }
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
    Ok(format)
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

/// Extensions the Python loaders accept (`exporter/scnerf_export/data/scene.py::IMAGE_EXTENSIONS`)
/// and the server decodes.
pub const IMAGE_EXTENSIONS: [&str; 6] = ["png", "jpg", "jpeg", "PNG", "JPG", "JPEG"];

/// Whether `path` names an image the readers use (by its extension).
pub fn has_image_extension(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| IMAGE_EXTENSIONS.contains(&e))
}

/// A JSON file (a transforms file, a camera path), refused with a message naming it when it is not
/// JSON, repeats a key within an object, or holds more than [`MAX_JSON_VALUES`] values. The
/// checks run over the text before the document is built: `serde_json::Value` takes 16-32 times
/// the text's size for arrays of small numbers, and its maps keep the last of duplicate keys.
pub fn read_json(fs: &dyn Files, path: &Path) -> Result<serde_json::Value> {
    let text = fs.read_text(path)?;
    json_check::check(&text).map_err(|e| Error::dataset(path, format!("invalid JSON: {e}")))?;
    serde_json::from_str(&text).map_err(|e| Error::dataset(path, format!("invalid JSON: {e}")))
}

/// Most values (numbers, strings, arrays, objects...) a JSON file of a capture may hold: a
/// transforms file of 10,000 frames holds about 300,000.
pub const MAX_JSON_VALUES: usize = 1 << 19;

mod json_check {
    use std::collections::HashSet;
    use std::fmt;
    use std::hash::{BuildHasher, RandomState};

    use serde::de::{DeserializeSeed, Deserializer, MapAccess, SeqAccess, Visitor};

    use super::MAX_JSON_VALUES;

    /// Walks the document without building it: counts its values and, per object, the hashes
    /// of its keys (8 bytes a key, whatever its length).
    pub(super) fn check(text: &str) -> Result<(), serde_json::Error> {
        let mut de = serde_json::Deserializer::from_str(text);
        let mut walk = Walk { values: 0, keys: RandomState::new() };
        (&mut walk).deserialize(&mut de)?;
        de.end()
    }

    struct Walk {
        values: usize,
        keys: RandomState,
    }

    impl Walk {
        fn count<E: serde::de::Error>(&mut self) -> Result<(), E> {
            self.values += 1;
            if self.values > MAX_JSON_VALUES {
                return Err(E::custom(format_args!("more than {MAX_JSON_VALUES} values")));
            }
            Ok(())
        }
    }

    impl<'de> DeserializeSeed<'de> for &mut Walk {
        type Value = ();

        fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
            d.deserialize_any(self)
        }
    }

    /// Reads a key (without copying it when the text holds it unescaped) into the hashes of the
    /// keys of its object, refusing one seen before.
    struct KeySeed<'a> {
        hasher: &'a RandomState,
        seen: &'a mut HashSet<u64>,
    }

    impl<'de> DeserializeSeed<'de> for KeySeed<'_> {
        type Value = ();

        fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
            d.deserialize_str(self)
        }
    }

    impl<'de> Visitor<'de> for KeySeed<'_> {
        type Value = ();

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("a key")
        }

        fn visit_str<E: serde::de::Error>(self, key: &str) -> Result<(), E> {
            if !self.seen.insert(self.hasher.hash_one(key)) {
                let shown: String = key.chars().take(64).collect();
                return Err(E::custom(format_args!("key {shown:?} appears twice in one object")));
            }
            Ok(())
        }
    }

    impl<'de> Visitor<'de> for &mut Walk {
        type Value = ();

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("any JSON value")
        }

        fn visit_bool<E: serde::de::Error>(self, _: bool) -> Result<(), E> {
            self.count()
        }

        fn visit_i64<E: serde::de::Error>(self, _: i64) -> Result<(), E> {
            self.count()
        }

        fn visit_u64<E: serde::de::Error>(self, _: u64) -> Result<(), E> {
            self.count()
        }

        fn visit_f64<E: serde::de::Error>(self, _: f64) -> Result<(), E> {
            self.count()
        }

        fn visit_str<E: serde::de::Error>(self, _: &str) -> Result<(), E> {
            self.count()
        }

        fn visit_unit<E: serde::de::Error>(self) -> Result<(), E> {
            self.count()
        }

        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
            self.count()?;
            while seq.next_element_seed(&mut *self)?.is_some() {}
            Ok(())
        }

        fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
            self.count()?;
            let (hasher, mut seen) = (self.keys.clone(), HashSet::new());
            while map.next_key_seed(KeySeed { hasher: &hasher, seen: &mut seen })?.is_some() {
                map.next_value_seed(&mut *self)?;
            }
            Ok(())
        }
    }
}

/// `near`/`far`: each from the command line if given, else from the dataset, else both from the
/// views' poses ([`crate::depth_range::from_poses`]); checked as the Python loaders do
/// (`data/scene.py::check_near_far`). `from_data` is the dataset's, with where it comes from.
fn depth_range(
    opts: ReadOptions,
    from_data: (Option<f64>, Option<f64>, DepthSource),
    views: &[CapturedView],
    source: &Path,
) -> Result<(f64, f64, DepthSource)> {
    let (data_near, data_far, data_source) = from_data;
    let (near, far, from) = match (opts.near.or(data_near), opts.far.or(data_far)) {
        (Some(near), Some(far)) => {
            let from = if opts.near.is_some() && opts.far.is_some() { DepthSource::Flags } else { data_source };
            (near, far, from)
        }
        (near, far) => {
            let cameras: Vec<&Camera> = views.iter().map(|v| &v.camera).collect();
            let (pose_near, pose_far) = crate::depth_range::from_poses(&cameras).ok_or_else(|| {
                Error::dataset(
                    source,
                    "no near/far in the dataset (COLMAP: from points3D; nerfstudio: near/far keys), and the \
                     poses do not give one (the cameras look at no common point in front of them): pass --near \
                     and --far",
                )
            })?;
            (near.unwrap_or(pose_near), far.unwrap_or(pose_far), DepthSource::Poses)
        }
    };
    if !(near.is_finite() && far.is_finite() && 0.0 <= near && near < far) {
        return Err(Error::dataset(source, format!("invalid near/far {near}/{far}: need 0 <= near < far")));
    }
    Ok((near, far, from))
}

/// The image a transforms.json `file_path` refers to: the path itself, else with one of the image
/// extensions appended (Blender files omit it). `data/dataparsers/transforms.py::_resolve_image`.
fn resolve_image(fs: &dyn Files, base: &Path, file_path: &str) -> Option<PathBuf> {
    let p = base.join(file_path);
    if fs.is_file(&p) {
        return Some(p);
    }
    if has_image_extension(&p) {
        return None;
    }
    IMAGE_EXTENSIONS.iter().map(|ext| PathBuf::from(format!("{}.{ext}", p.display()))).find(|q| fs.is_file(q))
}

/// A view's camera and lens from its photo's camera (at the photo's size) and the lens's
/// distortion: no distortion, the camera as it is; with `--ignore-distortion`, the same with a
/// warning (what the Python loaders do); else the pinhole camera of [`ReadOptions::undistort`]
/// that the photo is undistorted to when sent. `what` names the camera in messages.
fn lens_of(
    opts: ReadOptions,
    photo: Camera,
    distortion: Distortion,
    what: &str,
    file: &Path,
    warnings: &mut Vec<String>,
) -> Result<(Camera, Option<Lens>)> {
    if distortion.is_zero() {
        return Ok((photo, None));
    }
    if opts.ignore_distortion {
        let warning = format!("{}: lens distortion ignored (images used as pinhole)", file.display());
        if !warnings.contains(&warning) {
            warnings.push(warning);
        }
        return Ok((photo, None));
    }
    let (width, height) = (photo.width, photo.height);
    let pinhole = pinhole_for(&photo.intrinsics, &distortion, width, height, opts.undistort).ok_or_else(|| {
        Error::dataset(
            file,
            format!(
                "{what}: its lens distortion ({distortion}) cannot be inverted over the whole image: check the \
                 coefficients, or pass --ignore-distortion to use the images as pinhole"
            ),
        )
    })?;
    let lens = Lens { distortion, distorted: photo.intrinsics, pinhole, width, height };
    Ok((Camera { intrinsics: pinhole, ..photo }, Some(lens)))
}

/// One warning for all frames whose image is missing, instead of one per frame.
fn skipped_warning(files: &str, skipped: usize, listed: usize) -> Option<String> {
    (skipped > 0).then(|| format!("{files}: {skipped} of {listed} frames have no image file; skipped"))
}

/// `path` without its extension, as Python's `os.path.splitext(path)[0]`.
fn without_extension(path: &str) -> String {
    Path::new(path).with_extension("").to_string_lossy().into_owned()
}

/// Python's `Path(path).name`: the last component.
fn base_name(path: &str) -> String {
    Path::new(path).file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()
}

/// Natural order ("img2" before "img10"), `data/scene.py::natural_key`: runs of digits compare by
/// value, everything else by code point.
pub fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (ka, kb) = (natural_key(a), natural_key(b));
    for (x, y) in ka.iter().zip(&kb) {
        let ord = match (x, y) {
            (Chunk::Number(x), Chunk::Number(y)) => {
                let (x, y) = (x.trim_start_matches('0'), y.trim_start_matches('0'));
                x.len().cmp(&y.len()).then_with(|| x.cmp(y))
            }
            (Chunk::Text(x), Chunk::Text(y)) => x.cmp(y),
            // never: both keys start with text and alternate, so kinds always line up
            _ => Ordering::Equal,
        };
        if ord != Ordering::Equal {
            return ord;
        }
    }
    ka.len().cmp(&kb.len())
}

enum Chunk<'a> {
    Text(&'a str),
    Number(&'a str),
}

/// Python's `re.split(r"(\d+)", s)`: text, digits, text, ... (the first and last text possibly
/// empty).
fn natural_key(s: &str) -> Vec<Chunk<'_>> {
    let mut out = Vec::new();
    let mut start = 0;
    let bytes = s.as_bytes();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i].is_ascii_digit() {
            let j = i + bytes[i..].iter().take_while(|b| b.is_ascii_digit()).count();
            out.push(Chunk::Text(&s[start..i]));
            out.push(Chunk::Number(&s[i..j]));
            start = j;
            i = j;
        } else {
            i += 1;
        }
    }
    out.push(Chunk::Text(&s[start..]));
    out
}

/// A JSON number, or an error naming the file and the field.
fn json_f64(value: &serde_json::Value, path: &Path, field: &str) -> Result<f64> {
    value.as_f64().ok_or_else(|| Error::dataset(path, format!("{field} is not a number: {value}")))
}

/// A 4x4 (or 3x4, completed with [0 0 0 1]) row-major matrix from JSON.
fn json_matrix4(value: &serde_json::Value, path: &Path, field: &str) -> Result<nalgebra::Matrix4<f64>> {
    let bad = || Error::dataset(path, format!("{field} must be a finite 4x4 (or 3x4) matrix"));
    let rows = value.as_array().ok_or_else(bad)?;
    if rows.len() != 3 && rows.len() != 4 {
        return Err(bad());
    }
    let mut m = nalgebra::Matrix4::identity();
    for (r, row) in rows.iter().enumerate() {
        let row = row.as_array().filter(|row| row.len() == 4).ok_or_else(bad)?;
        for (c, v) in row.iter().enumerate() {
            m[(r, c)] = v.as_f64().filter(|v| v.is_finite()).ok_or_else(bad)?;
        }
    }
    Ok(m)
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
