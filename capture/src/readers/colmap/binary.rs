//! The binary model as COLMAP writes it (colmap/src/colmap/scene/reconstruction_io.cc):
//! little-endian, counts as u64, ids as u32, names NUL-terminated.

use std::path::Path;

use nalgebra::Point3;

use super::lens::{check_params, MODELS};
use super::records::{pose, CameraModel, ImageRecord, Points};
use crate::error::{Error, Result};
use crate::files::Files;

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
            Error::dataset(self.path, format!("truncated binary model (record count {n} at offset {})", self.at - 8))
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
        let w2c = pose(q, t).ok_or_else(|| Error::dataset(path, format!("image {name}: zero or non-finite pose")))?;
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
