//! LLFF: `poses_bounds.npy` (N x 17) and `images/` (file names sorted, one per row).
//!
//! Convention (`exporter/scnerf_export/data/dataparsers/llff.py::LlffParser`): each row is a 3x5
//! matrix [R | t | hwf] then the view's near and far bounds. R is camera-to-world with columns in
//! LLFF's [down, right, back] axes, so OpenCV's [right, down, forward] = [col1, col0, -col2]. hwf
//! is the full-resolution height, width and focal: f = focal W_image / W_hwf, and the principal
//! point is the image centre (W/2, H/2), as in LLFF's and MVSNeRF's code. The world stays in LLFF's
//! units (no NeRF bd_factor rescale). near = smallest near bound, far = largest far bound. hwf
//! describes the full-size images: a downscaled set (`images_N`, `--downscale N`) gets f scaled by
//! its width, f W_N / W_hwf, which is LLFF's f / N for sizes that divide exactly.

use std::path::Path;

use nalgebra::{Matrix4, Vector3};

use super::{cameras_of, folder_name, list_images, Capture, CapturedView, DepthSource, Format, ReadOptions};
use crate::camera::{w2c_from_c2w, Camera, Intrinsics};
use crate::depth_range;
use crate::error::{Error, Result};
use crate::files::Files;

pub fn load(fs: &dyn Files, path: &Path, opts: ReadOptions) -> Result<Capture> {
    let npy = path.join("poses_bounds.npy");
    let rows = read_rows(fs, &npy)?;
    let folder = path.join(folder_name(opts.downscale.unwrap_or(1)));
    let images = list_images(fs, &folder)?;
    if images.len() != rows.len() {
        return Err(Error::dataset(
            &npy,
            format!("{} poses but {} images in {}", rows.len(), images.len(), folder.display()),
        ));
    }
    let mut views = Vec::with_capacity(rows.len());
    for (i, (row, image)) in rows.iter().zip(images).enumerate() {
        let at = |r: usize, c: usize| row[r * 5 + c];
        let (h0, w0, focal) = (at(0, 4), at(1, 4), at(2, 4));
        if w0 <= 0.0 || h0 <= 0.0 || focal <= 0.0 {
            return Err(Error::dataset(&npy, format!("row {i} has an invalid hwf ({h0}, {w0}, {focal})")));
        }
        let column = |c: usize| Vector3::new(at(0, c), at(1, c), at(2, c));
        let mut c2w = Matrix4::identity();
        c2w.fixed_view_mut::<3, 1>(0, 0).copy_from(&column(1));
        c2w.fixed_view_mut::<3, 1>(0, 1).copy_from(&column(0));
        c2w.fixed_view_mut::<3, 1>(0, 2).copy_from(&-column(2));
        c2w.fixed_view_mut::<3, 1>(0, 3).copy_from(&column(3));
        let w2c = w2c_from_c2w(&c2w)
            .ok_or_else(|| Error::dataset(&npy, format!("row {i}: the pose is not a rigid transform")))?;
        let (w, h) = fs.image_size(&image)?;
        let f = focal * f64::from(w) / w0;
        let intrinsics = Intrinsics { fx: f, fy: f, cx: f64::from(w) / 2.0, cy: f64::from(h) / 2.0 };
        let name = image.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        views.push(CapturedView {
            name,
            image_path: image,
            camera: Camera { width: w, height: h, intrinsics, w2c },
            lens: None,
        });
    }
    let near = rows.iter().map(|r| r[15]).fold(f64::INFINITY, f64::min);
    let far = rows.iter().map(|r| r[16]).fold(f64::NEG_INFINITY, f64::max);
    let (near, far, depth_source) = depth_range::resolve(
        (opts.near, opts.far),
        (Some(near), Some(far), DepthSource::Dataset),
        &cameras_of(&views),
        &npy,
    )?;
    Ok(Capture { depth_source, format: Format::Llff, views, near, far, background: [0.0; 3], warnings: Vec::new() })
}

/// The N rows of 17 finite numbers (float64 or float32, either byte or memory order).
fn read_rows(fs: &dyn Files, npy: &Path) -> Result<Vec<[f64; 17]>> {
    let bytes = fs.read(npy)?;
    let bad = |what: String| Error::dataset(npy, what);
    // The shape is checked against the file's size before npyz reads the header: it multiplies
    // the declared dimensions unchecked, and sizes its buffer from them.
    let (shape, data_bytes) =
        declared_shape(&bytes).ok_or_else(|| bad("not a .npy file (no readable header)".into()))?;
    if shape.len() != 2 || shape[1] != 17 || shape[0] == 0 {
        return Err(bad(format!("expected an N x 17 array, got shape {shape:?}")));
    }
    // float32 is the smallest accepted element.
    if shape[0].checked_mul(17 * 4).is_none_or(|needed| needed > data_bytes) {
        return Err(bad(format!(
            "the header declares {} rows, more than the file's {data_bytes} bytes hold",
            shape[0]
        )));
    }
    let file = npyz::NpyFile::new(&bytes[..]).map_err(|e| bad(format!("not a .npy file ({e})")))?;
    let order = file.order();
    let dtype = match file.dtype() {
        npyz::DType::Plain(ty) => ty.to_string(),
        other => other.descr(),
    };
    let values: Vec<f64> = match dtype.get(1..) {
        Some("f8") => file.into_vec::<f64>(),
        Some("f4") => file.into_vec::<f32>().map(|v| v.into_iter().map(f64::from).collect()),
        _ => return Err(bad(format!("expected float64 values, got dtype {dtype}"))),
    }
    .map_err(|e| bad(format!("cannot read the array ({e})")))?;
    if values.iter().any(|v| !v.is_finite()) {
        return Err(bad("non-finite values".into()));
    }
    let n = shape[0] as usize;
    let index = |i: usize, j: usize| match order {
        npyz::Order::C => i * 17 + j,
        npyz::Order::Fortran => j * n + i,
    };
    Ok((0..n).map(|i| std::array::from_fn(|j| values[index(i, j)])).collect())
}

/// The shape a .npy file's header declares and the bytes after the header (NEP 1: magic,
/// version, header length (2 bytes in version 1, 4 after), a Python dict with a `shape` tuple).
fn declared_shape(bytes: &[u8]) -> Option<(Vec<u64>, u64)> {
    let rest = bytes.strip_prefix(b"\x93NUMPY")?;
    let (len, header_at): (usize, usize) = match rest.first()? {
        1 => (usize::from(u16::from_le_bytes(rest.get(2..4)?.try_into().ok()?)), 4),
        _ => (usize::try_from(u32::from_le_bytes(rest.get(2..6)?.try_into().ok()?)).ok()?, 6),
    };
    let header = std::str::from_utf8(rest.get(header_at..header_at.checked_add(len)?)?).ok()?;
    let data_bytes = rest.len().checked_sub(header_at + len)? as u64;
    let after = &header[header.find("'shape'").or_else(|| header.find("\"shape\""))?..];
    let tuple = &after[after.find('(')? + 1..];
    let tuple = &tuple[..tuple.find(')')?];
    let shape =
        tuple.split(',').map(str::trim).filter(|d| !d.is_empty()).map(|d| d.parse().ok()).collect::<Option<_>>()?;
    Some((shape, data_bytes))
}
