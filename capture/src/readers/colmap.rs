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

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use nalgebra::{Point3, Quaternion, Translation3, UnitQuaternion};

use super::{
    cameras_of, folder_name, natural_cmp, without_extension, Capture, CapturedView, DepthSource, Format, ReadOptions,
};
use crate::camera::{Camera, Intrinsics, Pose};
use crate::depth_range;
use crate::error::{Error, Result};
use crate::files::Files;
use crate::percentile;
use crate::undistort::lens_of;
use crate::undistort::Distortion;

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

struct CameraModel {
    model: String,
    width: u64,
    height: u64,
    params: Vec<f64>,
}

struct ImageRecord {
    id: i64,
    name: String,
    w2c: Pose,
    camera_id: i64,
}

/// Point positions and, per point, the ids of the images that observe it.
struct Points {
    xyz: Vec<Point3<f64>>,
    tracks: Vec<Vec<i64>>,
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

/// Intrinsics (shifted to integer pixel centres), declared size and lens distortion of a camera.
fn pinhole(cam: &CameraModel, id: i64, file: &Path) -> Result<(Intrinsics, (u32, u32), Distortion)> {
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
const MODELS: [(&str, usize); 11] = [
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

fn pose(q: [f64; 4], t: [f64; 3]) -> Option<Pose> {
    let q = Quaternion::new(q[0], q[1], q[2], q[3]);
    let n = q.norm();
    if !(n.is_finite() && n >= 1e-12 && t.iter().all(|v| v.is_finite())) {
        return None;
    }
    let rotation = UnitQuaternion::from_quaternion(q).to_rotation_matrix();
    Some(Pose::from_parts(Translation3::new(t[0], t[1], t[2]), rotation))
}

/// Most depths (a point's z in one image) ranked for the depth range: 32 MiB of them, more than
/// a 64 MiB points3D file of real tracks gives. A point without a track counts in every image,
/// so a file of them could ask for points x images.
pub const MAX_DEPTHS: usize = 1 << 22;

/// near = 0.9 x the 1st, far = 1.1 x the 99th percentile of the positive z-depths of each point
/// in the images that observe it (in every image for a point without a track);
/// `colmap.py::_points_near_far`. Images whose file is missing still count.
fn points_near_far(points: &Points, images: &[ImageRecord], file: &Path) -> Result<Option<(f64, f64)>> {
    // Python keeps the last record of a repeated image id
    let poses: HashMap<i64, &Pose> = images.iter().map(|i| (i.id, &i.w2c)).collect();
    let mut observed: HashMap<i64, Vec<usize>> = HashMap::new();
    let mut untracked = Vec::new();
    for (k, track) in points.tracks.iter().enumerate() {
        if track.is_empty() {
            untracked.push(k);
        }
        for id in track {
            observed.entry(*id).or_default().push(k);
        }
    }
    let observations: usize = poses.keys().map(|id| observed.get(id).map_or(0, Vec::len)).sum();
    let depth_count = untracked.len().checked_mul(poses.len()).and_then(|n| n.checked_add(observations));
    if depth_count.is_none_or(|n| n > MAX_DEPTHS) {
        return Err(Error::dataset(
            file,
            format!(
                "{} points ({} without a track, seen from all {} images) give more than {MAX_DEPTHS} depths to \
                 rank for near/far: pass --near and --far",
                points.xyz.len(),
                untracked.len(),
                poses.len()
            ),
        ));
    }
    let mut depths = Vec::new();
    for (id, w2c) in &poses {
        let own = observed.get(id).map(Vec::as_slice).unwrap_or_default();
        for &k in own.iter().chain(&untracked) {
            let z = (*w2c * points.xyz[k]).z;
            if z > 1e-9 {
                depths.push(z);
            }
        }
    }
    if depths.is_empty() {
        return Ok(None);
    }
    depths.sort_by(f64::total_cmp);
    Ok(Some((0.9 * percentile(&depths, 1.0), 1.1 * percentile(&depths, 99.0))))
}

mod text {
    use super::*;

    /// The line quoted in an error, cut short (a malformed line may be the whole file).
    fn malformed(path: &Path, line: usize, what: &str, text: &str) -> Error {
        let shown: String = text.chars().take(80).collect();
        let cut = if shown.len() < text.len() { "..." } else { "" };
        Error::dataset(path, format!("line {line}: malformed {what} line: {shown:?}{cut}"))
    }

    /// The lines with their 1-based numbers, blank lines and comments left out.
    fn records(text: &str) -> impl Iterator<Item = (usize, &str)> {
        text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())).filter(|(_, s)| !s.is_empty() && !s.starts_with('#'))
    }

    /// The next `N` tokens as numbers.
    fn numbers<'a, T: std::str::FromStr, const N: usize>(tokens: &mut impl Iterator<Item = &'a str>) -> Option<[T; N]> {
        let mut out = Vec::with_capacity(N);
        for _ in 0..N {
            out.push(tokens.next()?.parse().ok()?);
        }
        out.try_into().ok()
    }

    /// The most parameters of any model (`MODELS`): a longer line is malformed without being
    /// read further.
    const MAX_PARAMS: usize = 12;

    pub(super) fn cameras(fs: &dyn Files, path: &Path) -> Result<Vec<(i64, CameraModel)>> {
        let mut out = Vec::new();
        for (n, s) in records(&fs.read_text(path)?) {
            let parse = || -> Option<(i64, CameraModel)> {
                let mut t = s.split_whitespace();
                let id = t.next()?.parse().ok()?;
                let model = t.next()?.to_uppercase();
                let [width, height] = numbers(&mut t)?;
                let params = t.by_ref().take(MAX_PARAMS).map(|x| x.parse().ok()).collect::<Option<Vec<f64>>>()?;
                t.next().is_none().then_some((id, CameraModel { model, width, height, params }))
            };
            let (id, cam) = parse().ok_or_else(|| malformed(path, n, "camera", s))?;
            check_params(&cam, path, &format!("line {n}"))?;
            out.push((id, cam));
        }
        if out.is_empty() {
            return Err(Error::dataset(path, "no cameras"));
        }
        Ok(out)
    }

    /// Every image takes two lines; the second (its 2D points) may be empty, so records are read
    /// in pairs instead of filtering blank lines.
    pub(super) fn images(fs: &dyn Files, path: &Path) -> Result<Vec<ImageRecord>> {
        let text = fs.read_text(path)?;
        let mut lines = text.lines().enumerate();
        let mut out = Vec::new();
        while let Some((i, line)) = lines.next() {
            let s = line.trim();
            if s.is_empty() || s.starts_with('#') {
                continue;
            }
            // id, qw qx qy qz tx ty tz, camera id, name
            let parse = || -> Option<(i64, [f64; 7], i64, String)> {
                let mut t = s.split_whitespace();
                let id = t.next()?.parse().ok()?;
                let qt = numbers(&mut t)?;
                let camera_id = t.next()?.parse().ok()?;
                // Python: " ".join(elems[9:])
                let name = t
                    .fold(String::new(), |name, token| if name.is_empty() { token.into() } else { name + " " + token });
                (!name.is_empty()).then_some((id, qt, camera_id, name))
            };
            let (id, [qw, qx, qy, qz, tx, ty, tz], camera_id, name) =
                parse().ok_or_else(|| malformed(path, i + 1, "image", s))?;
            let w2c = pose([qw, qx, qy, qz], [tx, ty, tz])
                .ok_or_else(|| Error::dataset(path, format!("line {}: zero or non-finite pose", i + 1)))?;
            out.push(ImageRecord { id, name, w2c, camera_id });
            lines.next(); // its 2D points
        }
        if out.is_empty() {
            return Err(Error::dataset(path, "no images"));
        }
        Ok(out)
    }

    /// `POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)*`
    pub(super) fn points(fs: &dyn Files, path: &Path) -> Result<Points> {
        let mut points = Points { xyz: Vec::new(), tracks: Vec::new() };
        for (n, s) in records(&fs.read_text(path)?) {
            let parse = || -> Option<(Point3<f64>, Vec<i64>)> {
                let mut t = s.split_whitespace();
                let [x, y, z] = numbers::<f64, 3>(t.by_ref().skip(1).by_ref())?;
                let track = t.skip(4).step_by(2).map(|x| x.parse().ok()).collect::<Option<_>>()?;
                Some((Point3::new(x, y, z), track))
            };
            let (xyz, track) = parse().ok_or_else(|| malformed(path, n, "point", s))?;
            points.xyz.push(xyz);
            points.tracks.push(track);
        }
        Ok(points)
    }
}

/// A known model with the right number of parameters (any model is parsed; `pinhole` decides
/// what is usable).
fn check_params(cam: &CameraModel, path: &Path, at: &str) -> Result<()> {
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

/// The binary model as COLMAP writes it (colmap/src/colmap/scene/reconstruction_io.cc):
/// little-endian, counts as u64, ids as u32, names NUL-terminated.
mod binary {
    use super::*;

    struct Reader<'a> {
        path: &'a Path,
        bytes: std::borrow::Cow<'a, [u8]>,
        at: usize,
    }

    impl<'a> Reader<'a> {
        fn open(fs: &'a dyn Files, path: &'a Path) -> Result<Self> {
            Ok(Reader { path, bytes: fs.read(path)?, at: 0 })
        }

        fn take<const N: usize>(&mut self) -> Result<[u8; N]> {
            let end = self.at + N;
            let chunk = self.bytes.get(self.at..end).ok_or_else(|| {
                Error::dataset(self.path, format!("truncated binary model (wanted {N} bytes at offset {})", self.at))
            })?;
            self.at = end;
            Ok(chunk.try_into().expect("slice of length N"))
        }

        fn u64(&mut self) -> Result<u64> {
            self.take().map(u64::from_le_bytes)
        }

        fn u32(&mut self) -> Result<u32> {
            self.take().map(u32::from_le_bytes)
        }

        fn i32(&mut self) -> Result<i32> {
            self.take().map(i32::from_le_bytes)
        }

        fn f64(&mut self) -> Result<f64> {
            self.take().map(f64::from_le_bytes)
        }

        fn f64s<const N: usize>(&mut self) -> Result<[f64; N]> {
            let mut out = [0.0; N];
            for v in &mut out {
                *v = self.f64()?;
            }
            Ok(out)
        }

        /// A count of records, refused when the file cannot hold that many of `min_size` bytes.
        fn count(&mut self, min_size: usize) -> Result<usize> {
            let n = self.u64()?;
            let room = (self.bytes.len() - self.at) / min_size.max(1);
            usize::try_from(n).ok().filter(|n| *n <= room).ok_or_else(|| {
                Error::dataset(
                    self.path,
                    format!("truncated binary model (record count {n} at offset {})", self.at - 8),
                )
            })
        }

        fn name(&mut self) -> Result<String> {
            let rest = &self.bytes[self.at..];
            let len = rest
                .iter()
                .position(|b| *b == 0)
                .ok_or_else(|| Error::dataset(self.path, "truncated binary model (unterminated image name)"))?;
            let name = String::from_utf8_lossy(&rest[..len]).into_owned();
            self.at += len + 1;
            Ok(name)
        }

        fn skip(&mut self, n: usize, size: usize) -> Result<()> {
            let end = n.checked_mul(size).and_then(|b| b.checked_add(self.at)).filter(|e| *e <= self.bytes.len());
            self.at = end.ok_or_else(|| Error::dataset(self.path, "truncated binary model"))?;
            Ok(())
        }
    }

    pub(super) fn cameras(fs: &dyn Files, path: &Path) -> Result<Vec<(i64, CameraModel)>> {
        let mut r = Reader::open(fs, path)?;
        let n = r.count(24)?;
        let mut out = Vec::with_capacity(n);
        for k in 0..n {
            let id = i64::from(r.u32()?);
            let model_id = r.i32()?;
            let (model, count) = usize::try_from(model_id)
                .ok()
                .and_then(|m| MODELS.get(m))
                .ok_or_else(|| Error::dataset(path, format!("camera {id}: unknown camera model id {model_id}")))?;
            let (width, height) = (r.u64()?, r.u64()?);
            let params = (0..*count).map(|_| r.f64()).collect::<Result<Vec<_>>>()?;
            let cam = CameraModel { model: model.to_string(), width, height, params };
            check_params(&cam, path, &format!("camera record {k}"))?;
            out.push((id, cam));
        }
        if out.is_empty() {
            return Err(Error::dataset(path, "no cameras"));
        }
        Ok(out)
    }

    pub(super) fn images(fs: &dyn Files, path: &Path) -> Result<Vec<ImageRecord>> {
        let mut r = Reader::open(fs, path)?;
        let n = r.count(73)?;
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            let id = i64::from(r.u32()?);
            let (q, t) = (r.f64s::<4>()?, r.f64s::<3>()?);
            let camera_id = i64::from(r.u32()?);
            let name = r.name()?;
            let points2d = r.count(24)?;
            r.skip(points2d, 24)?; // x, y (f64) and point3D id (i64) each
            let w2c =
                pose(q, t).ok_or_else(|| Error::dataset(path, format!("image {name}: zero or non-finite pose")))?;
            out.push(ImageRecord { id, name, w2c, camera_id });
        }
        if out.is_empty() {
            return Err(Error::dataset(path, "no images"));
        }
        Ok(out)
    }

    pub(super) fn points(fs: &dyn Files, path: &Path) -> Result<Points> {
        let mut r = Reader::open(fs, path)?;
        let n = r.count(51)?;
        let mut points = Points { xyz: Vec::with_capacity(n), tracks: Vec::with_capacity(n) };
        for _ in 0..n {
            r.u64()?; // point id
            let xyz = r.f64s::<3>()?;
            r.take::<3>()?; // colour
            r.f64()?; // reprojection error
            let len = r.count(8)?;
            let track = (0..len)
                .map(|_| {
                    let image = r.u32()?;
                    r.u32()?; // index of the 2D point in that image
                    Ok(i64::from(image))
                })
                .collect::<Result<Vec<_>>>()?;
            points.xyz.push(Point3::from(xyz));
            points.tracks.push(track);
        }
        Ok(points)
    }
}
