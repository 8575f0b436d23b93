//! Lens distortion as COLMAP, nerfstudio and instant-ngp write it, and the pinhole camera a
//! distorted view is resampled to. No well-kept pure-Rust crate covers these models (opencv-rust
//! binds the C++ library), so this is OpenCV's own arithmetic, checked against OpenCV's
//! `undistortPoints` and `initUndistortRectifyMap` (`tests/undistort.rs`, fixture written by
//! `tests/fixtures/undistort/make_fixture.py`).
//!
//! Models, on normalised image coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy), r² = x² + y²:
//! - perspective (COLMAP SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV; nerfstudio OPENCV):
//!   OpenCV's rational model, x' = x (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
//!   + 2 p1 x y + p2 (r² + 2 x²), and y' likewise;
//! - fisheye (COLMAP OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE; nerfstudio
//!   OPENCV_FISHEYE): OpenCV's `cv::fisheye`, θ = atan r, θ' = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ +
//!   k4 θ⁸), (x', y') = (θ' / r) (x, y).

use std::path::Path;

use image::{Rgba, RgbaImage};

use crate::camera::{Camera, Intrinsics};
use crate::error::{Error, Result};

/// A lens's distortion: the coefficients of one of the two models (unused ones zero).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Distortion {
    pub fisheye: bool,
    /// Perspective: k1..k6 of the rational model; fisheye: k1..k4 (k5, k6 zero).
    pub k: [f64; 6],
    /// Tangential p1, p2 (perspective only).
    pub p: [f64; 2],
}

/// Which pinhole camera a distorted view is resampled to (OpenCV's `getOptimalNewCameraMatrix`
/// with alpha 0 or 1); `largest_rectangle`, `all_pixels` in the server's query.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Fit {
    /// The largest rectangle of valid pixels: nothing is filled, the edges are cropped. The
    /// default: the filled corners of `AllPixels` cost far more than the cropped edges (the
    /// network renders the filled colour well beyond them; docs/client.md, "Lens distortion").
    #[default]
    LargestRectangle,
    /// Every pixel of the photo stays in the image; the corners that no pixel reaches are
    /// filled with the capture's background.
    AllPixels,
}

/// A view whose photo is distorted: the photo's camera and the pinhole camera of the same size
/// it is resampled to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lens {
    pub distortion: Distortion,
    /// Of the photo on disk, at its size.
    pub distorted: Intrinsics,
    /// The undistorted image's, at the photo's size.
    pub pinhole: Intrinsics,
    pub width: u32,
    pub height: u32,
}

impl std::fmt::Display for Distortion {
    /// The coefficients that are not zero: `fisheye k1=0.05, k2=-0.01` or `k1=0.058`.
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        let names = ["k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2"];
        let nonzero: Vec<String> = names
            .iter()
            .zip(self.k.iter().chain(&self.p))
            .filter(|(_, c)| **c != 0.0)
            .map(|(n, c)| format!("{n}={c}"))
            .collect();
        write!(f, "{}{}", if self.fisheye { "fisheye " } else { "" }, nonzero.join(", "))
    }
}

impl Distortion {
    /// No distortion: the pinhole model.
    pub const NONE: Distortion = Distortion { fisheye: false, k: [0.0; 6], p: [0.0; 2] };

    pub fn is_zero(&self) -> bool {
        self.k.iter().chain(&self.p).all(|c| *c == 0.0)
    }

    /// Distorted normalised coordinates of an undistorted point.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, k3, k4, k5, k6] = self.k;
        let r2 = x * x + y * y;
        if self.fisheye {
            let r = r2.sqrt();
            if r < 1e-12 {
                return (x, y);
            }
            let theta = r.atan();
            let t2 = theta * theta;
            let theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))));
            return (x * theta_d / r, y * theta_d / r);
        }
        let radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)));
        let [p1, p2] = self.p;
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// The undistorted point that distorts to (xd, yd), to 1e-12 (OpenCV's `undistortPoints`
    /// stops after a few fixed-point steps by default; with a tight criterion it agrees). `None`
    /// when there is none: the point is outside what the lens model maps.
    pub fn undistort(&self, xd: f64, yd: f64) -> Option<(f64, f64)> {
        if self.fisheye {
            self.undistort_fisheye(xd, yd)
        } else {
            self.undistort_perspective(xd, yd)
        }
    }

    /// Newton's method on [`Self::distort`] with a finite-difference Jacobian.
    fn undistort_perspective(&self, xd: f64, yd: f64) -> Option<(f64, f64)> {
        const H: f64 = 1e-7;
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let (fx, fy) = self.distort(x, y);
            let (ex, ey) = (fx - xd, fy - yd);
            if ex.abs().max(ey.abs()) < 1e-12 {
                return Some((x, y));
            }
            let (ax, ay) = self.distort(x + H, y);
            let (bx, by) = self.distort(x, y + H);
            let (j00, j10, j01, j11) = ((ax - fx) / H, (ay - fy) / H, (bx - fx) / H, (by - fy) / H);
            let det = j00 * j11 - j01 * j10;
            if !det.is_finite() || det.abs() < 1e-12 {
                return None;
            }
            x -= (j11 * ex - j01 * ey) / det;
            y -= (j00 * ey - j10 * ex) / det;
            if !(x.is_finite() && y.is_finite()) {
                return None;
            }
        }
        None
    }

    /// The fisheye model is radial: θ from θ' by Newton's method (as `cv::fisheye::undistortPoints`),
    /// then r = tan θ; `None` at or beyond 90 degrees from the axis.
    fn undistort_fisheye(&self, xd: f64, yd: f64) -> Option<(f64, f64)> {
        let theta_d = xd.hypot(yd);
        if theta_d < 1e-12 {
            return Some((xd, yd));
        }
        let [k1, k2, k3, k4, ..] = self.k;
        let mut theta = theta_d;
        for _ in 0..50 {
            let t2 = theta * theta;
            let f = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d;
            if f.abs() < 1e-12 {
                if !(0.0..std::f64::consts::FRAC_PI_2).contains(&theta) {
                    return None;
                }
                let scale = theta.tan() / theta_d;
                return Some((xd * scale, yd * scale));
            }
            let df = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)));
            if !df.is_finite() || df.abs() < 1e-12 {
                return None;
            }
            theta -= f / df;
        }
        None
    }
}

/// Points along the border of a `width` x `height` image (pixel centres 0..w-1, 0..h-1), per
/// side: left, right, top, bottom. OpenCV samples a 9 x 9 grid; a finer border also keeps the
/// pixels of a lens whose distortion is not monotonic between those samples.
const BORDER_SAMPLES: usize = 33;

/// The pinhole intrinsics, for an image of the same size, that [`Fit`] asks for: OpenCV's
/// `getOptimalNewCameraMatrix(K, D, size, alpha)` with alpha 1 (`AllPixels`) or 0
/// (`LargestRectangle`), on a finer border. `None` when a border point cannot be undistorted.
pub fn pinhole_for(
    distorted: &Intrinsics,
    distortion: &Distortion,
    width: u32,
    height: u32,
    fit: Fit,
) -> Option<Intrinsics> {
    let (w, h) = (f64::from(width) - 1.0, f64::from(height) - 1.0);
    let side = |u0: f64, v0: f64, u1: f64, v1: f64| -> Option<Vec<(f64, f64)>> {
        (0..BORDER_SAMPLES)
            .map(|i| {
                let t = i as f64 / (BORDER_SAMPLES - 1) as f64;
                let (u, v) = (u0 + (u1 - u0) * t, v0 + (v1 - v0) * t);
                distortion.undistort((u - distorted.cx) / distorted.fx, (v - distorted.cy) / distorted.fy)
            })
            .collect()
    };
    let (left, right) = (side(0.0, 0.0, 0.0, h)?, side(w, 0.0, w, h)?);
    let (top, bottom) = (side(0.0, 0.0, w, 0.0)?, side(0.0, h, w, h)?);
    let xs = |s: &[(f64, f64)]| s.iter().map(|p| p.0).collect::<Vec<_>>();
    let ys = |s: &[(f64, f64)]| s.iter().map(|p| p.1).collect::<Vec<_>>();
    let (x0, x1, y0, y1) = match fit {
        Fit::AllPixels => {
            let all: Vec<(f64, f64)> = [&left, &right, &top, &bottom].into_iter().flatten().copied().collect();
            (min(&xs(&all)), max(&xs(&all)), min(&ys(&all)), max(&ys(&all)))
        }
        Fit::LargestRectangle => (max(&xs(&left)), min(&xs(&right)), max(&ys(&top)), min(&ys(&bottom))),
    };
    if !(x1 > x0 && y1 > y0) {
        return None;
    }
    let (fx, fy) = (w / (x1 - x0), h / (y1 - y0));
    Some(Intrinsics { fx, fy, cx: -fx * x0, cy: -fy * y0 })
}

fn min(v: &[f64]) -> f64 {
    v.iter().copied().fold(f64::INFINITY, f64::min)
}

fn max(v: &[f64]) -> f64 {
    v.iter().copied().fold(f64::NEG_INFINITY, f64::max)
}

impl Lens {
    /// Where in the photo the centre of pixel (u, v) of the undistorted image comes from
    /// (`initUndistortRectifyMap` with R = I and the new camera `pinhole`).
    pub fn source_of(&self, u: f64, v: f64) -> (f64, f64) {
        let (p, d) = (&self.pinhole, &self.distorted);
        let (x, y) = self.distortion.distort((u - p.cx) / p.fx, (v - p.cy) / p.fy);
        (d.fx * x + d.cx, d.fy * y + d.cy)
    }

    /// The undistorted image of `photo` (of the lens's size): each pixel sampled bilinearly at
    /// [`Lens::source_of`]; pixels that fall outside the photo take `fill`.
    pub fn undistort_image(&self, photo: &RgbaImage, fill: Rgba<u8>) -> RgbaImage {
        RgbaImage::from_fn(self.width, self.height, |u, v| {
            let (x, y) = self.source_of(f64::from(u), f64::from(v));
            bilinear(photo, x, y).unwrap_or(fill)
        })
    }
}

/// The photo at (x, y) (pixel centres at integers), from its four nearest pixels; `None` outside
/// the pixel centres' hull widened by half a pixel, whose edge pixels are repeated.
fn bilinear(photo: &RgbaImage, x: f64, y: f64) -> Option<Rgba<u8>> {
    let (w, h) = (f64::from(photo.width()), f64::from(photo.height()));
    if !(x >= -0.5 && y >= -0.5 && x <= w - 0.5 && y <= h - 0.5) {
        return None;
    }
    let (x, y) = (x.clamp(0.0, w - 1.0), y.clamp(0.0, h - 1.0));
    let (x0, y0) = (x.floor(), y.floor());
    let (tx, ty) = (x - x0, y - y0);
    let (x0, y0) = (x0 as u32, y0 as u32);
    let (x1, y1) = ((x0 + 1).min(photo.width() - 1), (y0 + 1).min(photo.height() - 1));
    let at = |px: u32, py: u32, c: usize| f64::from(photo.get_pixel(px, py)[c]);
    let mut out = [0u8; 4];
    for (c, o) in out.iter_mut().enumerate() {
        let top = at(x0, y0, c) * (1.0 - tx) + at(x1, y0, c) * tx;
        let bottom = at(x0, y1, c) * (1.0 - tx) + at(x1, y1, c) * tx;
        *o = (top * (1.0 - ty) + bottom * ty).round() as u8;
    }
    Some(Rgba(out))
}

/// A view's camera and lens from its photo's camera (at the photo's size) and the lens's
/// distortion: no distortion, the camera as it is; with `ignore` (`--ignore-distortion`), the same with a
/// warning (the Python loaders' `ignore_distortion` too); else the pinhole camera `fit` gives
/// that the photo is undistorted to when sent. `what` names the camera in messages.
pub fn lens_of(
    photo: Camera,
    distortion: Distortion,
    ignore: bool,
    fit: Fit,
    what: &str,
    file: &Path,
    warnings: &mut Vec<String>,
) -> Result<(Camera, Option<Lens>)> {
    if distortion.is_zero() {
        return Ok((photo, None));
    }
    if ignore {
        let warning = format!("{}: lens distortion ignored (images used as pinhole)", file.display());
        if !warnings.contains(&warning) {
            warnings.push(warning);
        }
        return Ok((photo, None));
    }
    let (width, height) = (photo.width, photo.height);
    let pinhole = pinhole_for(&photo.intrinsics, &distortion, width, height, fit).ok_or_else(|| {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn undistort_inverts_distort_for_both_models() {
        let perspective = Distortion { fisheye: false, k: [-0.2, 0.05, 0.01, 0.0, 0.0, 0.0], p: [1e-3, -2e-3] };
        let fisheye = Distortion { fisheye: true, k: [0.1, -0.02, 0.0, 0.0, 0.0, 0.0], p: [0.0; 2] };
        for d in [perspective, fisheye] {
            for (x, y) in [(0.0, 0.0), (0.3, -0.2), (-0.5, 0.4), (0.6, 0.6)] {
                let (xd, yd) = d.distort(x, y);
                let (ux, uy) = d.undistort(xd, yd).unwrap();
                assert!((ux - x).abs() < 1e-10 && (uy - y).abs() < 1e-10, "{d:?} at ({x}, {y}): ({ux}, {uy})");
            }
        }
    }

    #[test]
    fn no_distortion_keeps_the_camera_and_the_image() {
        let k = Intrinsics { fx: 50.0, fy: 50.0, cx: 15.5, cy: 11.5 };
        let none = Distortion::NONE;
        let pinhole = pinhole_for(&k, &none, 32, 24, Fit::AllPixels).unwrap();
        assert!((pinhole.fx - 50.0).abs() < 1e-9 && (pinhole.cx - 15.5).abs() < 1e-9, "{pinhole:?}");
        let lens = Lens { distortion: none, distorted: k, pinhole: k, width: 32, height: 24 };
        let photo = RgbaImage::from_fn(32, 24, |x, y| Rgba([x as u8 * 8, y as u8 * 10, 7, 255]));
        assert_eq!(lens.undistort_image(&photo, Rgba([0, 0, 0, 255])), photo);
    }
}
