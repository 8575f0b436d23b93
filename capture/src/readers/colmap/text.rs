//! The text model: `cameras.txt`, `images.txt`, `points3D.txt`.

use std::path::Path;

use nalgebra::Point3;

use super::lens::check_params;
use super::records::{pose, CameraModel, ImageRecord, Points};
use crate::error::{Error, Result};
use crate::files::Files;

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
            let name =
                t.fold(String::new(), |name, token| if name.is_empty() { token.into() } else { name + " " + token });
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
