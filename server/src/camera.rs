//! Cameras: conversion of the accepted conventions (OpenCV/OpenGL axes, world-to-camera or
//! camera-to-world poses, {fx,fy,cx,cy} or a 3x3 K) to the canonical OpenCV world-to-camera form
//! of docs/bundle.md, with the validation that makes the math well defined.

use serde::{Deserialize, Serialize};

use crate::error::ApiError;

pub type Mat3 = [[f64; 3]; 3];
pub type Mat4 = [[f64; 4]; 4];

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseKind {
    WorldToCamera,
    CameraToWorld,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Axes {
    /// x right, y down, z forward (the canonical form).
    Opencv,
    /// x right, y up, z backward (Blender, NeRF synthetic, nerfstudio).
    Opengl,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Intrinsics {
    Focal { fx: f64, fy: f64, cx: f64, cy: f64 },
    Matrix(Mat3),
}

#[derive(Debug, Clone, PartialEq)]
pub struct Pose {
    pub matrix: Mat4,
    pub kind: PoseKind,
    pub axes: Axes,
}

/// A camera as the client described it.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraSpec {
    pub width: u32,
    pub height: u32,
    pub intrinsics: Intrinsics,
    pub pose: Pose,
}

/// Canonical camera: OpenCV axes, world-to-camera, pixel (u, v) centred at image coordinates (u, v).
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub k: Mat3,
    pub w2c: Mat4,
}

impl Camera {
    pub fn fx(&self) -> f64 {
        self.k[0][0]
    }
    pub fn fy(&self) -> f64 {
        self.k[1][1]
    }
    pub fn cx(&self) -> f64 {
        self.k[0][2]
    }
    pub fn cy(&self) -> f64 {
        self.k[1][2]
    }

    /// Camera-to-world transform (inverse of `w2c`).
    pub fn c2w(&self) -> Mat4 {
        // Validation guarantees an invertible pose.
        invert4(&self.w2c).unwrap_or(self.w2c)
    }
}

/// Largest deviation of R·Rᵀ from the identity that is still accepted as a rotation. Poses come
/// from JSON files that often hold float32-rounded numbers; 1e-3 accepts those and rejects
/// scaled or sheared matrices.
pub const ROTATION_TOLERANCE: f64 = 1e-3;

/// Bounds that keep a camera renderable: the graphs compute rays, sample points and projections
/// in float32, where 1e-300 is 0 and 1e300 is infinite, and such cameras rendered blank views.
/// Focal lengths are relative to the image's larger side (fields of view from 0.06 to 179.8
/// degrees); the principal point may lie off the image (crops), by up to 1000 image sizes.
pub const FOCAL_PER_SIZE: std::ops::RangeInclusive<f64> = 1e-3..=1e3;
pub const MAX_PRINCIPAL_OFFSET_PER_SIZE: f64 = 1e3;
/// Largest camera translation, near and far plane in world units; smallest near plane.
pub const MAX_WORLD_EXTENT: f64 = 1e6;
pub const MIN_NEAR: f64 = 1e-6;

/// OpenGL camera axes -> OpenCV camera axes: flip y and z.
const GL_TO_CV: Mat4 = [[1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];

impl CameraSpec {
    /// Validates and converts to the canonical form. `field` names this camera in errors
    /// (e.g. `sources[1].camera`).
    pub fn canonicalize(&self, field: &str) -> Result<Camera, ApiError> {
        if self.width == 0 || self.height == 0 {
            return Err(ApiError::invalid(format!("{field}.width"), "width and height must be > 0"));
        }
        let k = self.intrinsic_matrix(field)?;
        let w2c = self.world_to_camera(field)?;
        Ok(Camera { width: self.width, height: self.height, k, w2c })
    }

    fn intrinsic_matrix(&self, field: &str) -> Result<Mat3, ApiError> {
        let at = format!("{field}.intrinsics");
        let k = match self.intrinsics {
            Intrinsics::Focal { fx, fy, cx, cy } => [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]],
            Intrinsics::Matrix(k) => k,
        };
        if k.iter().flatten().any(|v| !v.is_finite()) {
            return Err(ApiError::invalid(at, "intrinsics must be finite numbers"));
        }
        if k[2] != [0.0, 0.0, 1.0] || k[1][0] != 0.0 {
            return Err(ApiError::invalid(at, "K must have the form [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"));
        }
        if k[0][1] != 0.0 {
            return Err(ApiError::invalid(at, "skewed intrinsics (K[0][1] != 0) are not supported"));
        }
        if k[0][0] <= 0.0 || k[1][1] <= 0.0 {
            return Err(ApiError::invalid(at, "focal lengths fx and fy must be > 0"));
        }
        let size = f64::from(self.width.max(self.height));
        let (lo, hi) = (FOCAL_PER_SIZE.start() * size, FOCAL_PER_SIZE.end() * size);
        if !(FOCAL_PER_SIZE.contains(&(k[0][0] / size)) && FOCAL_PER_SIZE.contains(&(k[1][1] / size))) {
            return Err(ApiError::invalid(
                at,
                format!("focal lengths fx and fy must be within [{lo:e}, {hi:e}] pixels for a {size}-pixel image"),
            ));
        }
        let max_offset = MAX_PRINCIPAL_OFFSET_PER_SIZE * size;
        let offsets = [k[0][2] - f64::from(self.width) / 2.0, k[1][2] - f64::from(self.height) / 2.0];
        if offsets.iter().any(|o| o.abs() > max_offset) {
            return Err(ApiError::invalid(
                at,
                format!("the principal point cx, cy must lie within {max_offset:e} pixels of the image centre"),
            ));
        }
        Ok(k)
    }

    fn world_to_camera(&self, field: &str) -> Result<Mat4, ApiError> {
        let at = format!("{field}.pose.matrix");
        let m = &self.pose.matrix;
        if m.iter().flatten().any(|v| !v.is_finite()) {
            return Err(ApiError::invalid(at, "pose matrix must hold finite numbers"));
        }
        let last = m[3];
        if (last[0].abs() + last[1].abs() + last[2].abs() + (last[3] - 1.0).abs()) > 1e-6 {
            return Err(ApiError::invalid(at, "the last row of the pose matrix must be [0, 0, 0, 1]"));
        }
        check_rotation(m).map_err(|msg| ApiError::invalid(at.clone(), msg))?;
        if m[..3].iter().any(|row| row[3].abs() > MAX_WORLD_EXTENT) {
            return Err(ApiError::invalid(at, format!("the translation must be within {MAX_WORLD_EXTENT:e} units")));
        }
        // Bring the pose to world-to-camera in its own axes, then change the camera axes.
        let w2c_axes = match self.pose.kind {
            PoseKind::WorldToCamera => *m,
            PoseKind::CameraToWorld => {
                invert4(m).ok_or_else(|| ApiError::invalid(at.clone(), "pose matrix is singular"))?
            }
        };
        Ok(match self.pose.axes {
            Axes::Opencv => w2c_axes,
            Axes::Opengl => mul4(&GL_TO_CV, &w2c_axes),
        })
    }
}

/// The upper-left 3x3 block must be a proper rotation (orthonormal, det +1).
fn check_rotation(m: &Mat4) -> Result<(), String> {
    let mut worst: f64 = 0.0;
    for i in 0..3 {
        for j in 0..3 {
            let dot: f64 = (0..3).map(|c| m[i][c] * m[j][c]).sum();
            let ident = if i == j { 1.0 } else { 0.0 };
            worst = worst.max((dot - ident).abs());
        }
    }
    if worst > ROTATION_TOLERANCE {
        return Err(format!(
            "the rotation part of the pose is not orthonormal (max |R·Rᵀ - I| = {worst:.3e} > {ROTATION_TOLERANCE:e})"
        ));
    }
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    if det < 0.0 {
        return Err("the rotation part of the pose is a reflection (determinant -1)".into());
    }
    Ok(())
}

pub fn mul4(a: &Mat4, b: &Mat4) -> Mat4 {
    let mut out = [[0.0; 4]; 4];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..4).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    out
}

/// General 4x4 inverse (Gauss-Jordan, partial pivoting), in f64 like numpy.linalg.inv.
pub fn invert4(m: &Mat4) -> Option<Mat4> {
    let mut a = *m;
    let mut inv = [[0.0; 4]; 4];
    for (i, row) in inv.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for col in 0..4 {
        let pivot = (col..4).max_by(|&x, &y| a[x][col].abs().total_cmp(&a[y][col].abs()))?;
        if a[pivot][col].abs() < 1e-12 {
            return None;
        }
        a.swap(col, pivot);
        inv.swap(col, pivot);
        let p = a[col][col];
        for j in 0..4 {
            a[col][j] /= p;
            inv[col][j] /= p;
        }
        for r in 0..4 {
            if r != col {
                let f = a[r][col];
                if f != 0.0 {
                    for j in 0..4 {
                        a[r][j] -= f * a[col][j];
                        inv[r][j] -= f * inv[col][j];
                    }
                }
            }
        }
    }
    Some(inv)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rot_y(theta: f64) -> Mat3 {
        let (s, c) = theta.sin_cos();
        [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    }

    fn pose(r: Mat3, t: [f64; 3]) -> Mat4 {
        [
            [r[0][0], r[0][1], r[0][2], t[0]],
            [r[1][0], r[1][1], r[1][2], t[1]],
            [r[2][0], r[2][1], r[2][2], t[2]],
            [0.0, 0.0, 0.0, 1.0],
        ]
    }

    fn spec(matrix: Mat4, kind: PoseKind, axes: Axes) -> CameraSpec {
        CameraSpec {
            width: 64,
            height: 48,
            intrinsics: Intrinsics::Focal { fx: 50.0, fy: 50.0, cx: 32.0, cy: 24.0 },
            pose: Pose { matrix, kind, axes },
        }
    }

    fn close(a: &Mat4, b: &Mat4) -> bool {
        a.iter().flatten().zip(b.iter().flatten()).all(|(x, y)| (x - y).abs() < 1e-12)
    }

    #[test]
    fn all_conventions_agree() {
        let w2c_cv = pose(rot_y(0.3), [0.1, -0.2, 4.0]);
        let c2w_cv = invert4(&w2c_cv).unwrap();
        let c2w_gl = mul4(&c2w_cv, &GL_TO_CV); // GL_TO_CV is its own inverse
        let w2c_gl = invert4(&c2w_gl).unwrap();
        for (m, kind, axes) in [
            (w2c_cv, PoseKind::WorldToCamera, Axes::Opencv),
            (c2w_cv, PoseKind::CameraToWorld, Axes::Opencv),
            (c2w_gl, PoseKind::CameraToWorld, Axes::Opengl),
            (w2c_gl, PoseKind::WorldToCamera, Axes::Opengl),
        ] {
            let cam = spec(m, kind, axes).canonicalize("target").unwrap();
            assert!(close(&cam.w2c, &w2c_cv), "{kind:?} {axes:?}: {:?}", cam.w2c);
        }
    }

    #[test]
    fn opengl_camera_looks_down_minus_z() {
        // A Blender camera at (0,0,4) looking at the origin: OpenCV z (forward) must be world -z.
        let c2w_gl = pose([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.0, 0.0, 4.0]);
        let cam = spec(c2w_gl, PoseKind::CameraToWorld, Axes::Opengl).canonicalize("t").unwrap();
        let c2w = cam.c2w();
        assert_eq!([c2w[0][2], c2w[1][2], c2w[2][2]], [0.0, 0.0, -1.0]);
        assert_eq!([c2w[0][3], c2w[1][3], c2w[2][3]], [0.0, 0.0, 4.0]);
    }

    #[test]
    fn k_matrix_equals_focal_form() {
        let mut s = spec(pose(rot_y(0.0), [0.0; 3]), PoseKind::WorldToCamera, Axes::Opencv);
        let a = s.canonicalize("t").unwrap();
        s.intrinsics = Intrinsics::Matrix([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]]);
        assert_eq!(s.canonicalize("t").unwrap(), a);
    }

    fn invalid_field(s: &CameraSpec) -> (String, String) {
        match s.canonicalize("sources[1].camera").unwrap_err() {
            ApiError::Invalid { field, message } => (field, message),
            e => panic!("unexpected {e:?}"),
        }
    }

    #[test]
    fn rejects_bad_cameras_naming_the_field() {
        let good = spec(pose(rot_y(0.2), [0.0, 0.0, 3.0]), PoseKind::WorldToCamera, Axes::Opencv);

        let mut s = good.clone();
        s.pose.matrix[0][3] = f64::NAN;
        assert_eq!(invalid_field(&s).0, "sources[1].camera.pose.matrix");

        let mut s = good.clone();
        s.pose.matrix[0][0] *= 2.0; // scaled axis
        assert!(invalid_field(&s).1.contains("orthonormal"));

        let mut s = good.clone();
        s.pose.matrix = [[0.0; 4], [0.0; 4], [0.0; 4], [0.0, 0.0, 0.0, 1.0]]; // singular
        assert!(invalid_field(&s).1.contains("orthonormal"));

        let mut s = good.clone();
        s.pose.matrix[0] = [-1.0, 0.0, 0.0, 0.0];
        s.pose.matrix[1] = [0.0, 1.0, 0.0, 0.0];
        s.pose.matrix[2] = [0.0, 0.0, 1.0, 0.0]; // reflection
        assert!(invalid_field(&s).1.contains("reflection"));

        let mut s = good.clone();
        s.pose.matrix[3] = [0.0, 0.0, 1.0, 1.0];
        assert!(invalid_field(&s).1.contains("last row"));

        let mut s = good.clone();
        s.intrinsics = Intrinsics::Focal { fx: -1.0, fy: 50.0, cx: 0.0, cy: 0.0 };
        assert_eq!(
            invalid_field(&s),
            ("sources[1].camera.intrinsics".into(), "focal lengths fx and fy must be > 0".into())
        );

        let mut s = good.clone();
        s.intrinsics = Intrinsics::Focal { fx: f64::INFINITY, fy: 50.0, cx: 0.0, cy: 0.0 };
        assert!(invalid_field(&s).1.contains("finite"));

        let mut s = good.clone();
        s.intrinsics = Intrinsics::Matrix([[50.0, 1.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]]);
        assert!(invalid_field(&s).1.contains("skew"));

        let mut s = good.clone();
        s.intrinsics = Intrinsics::Matrix([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 1.0, 1.0]]);
        assert!(invalid_field(&s).1.contains("form"));

        // Finite but beyond what float32 rendering can use.
        for (fx, cx) in [(1e-300, 32.0), (1e300, 32.0), (50.0, 1e300), (50.0, -1e9)] {
            let mut s = good.clone();
            s.intrinsics = Intrinsics::Focal { fx, fy: 50.0, cx, cy: 24.0 };
            assert_eq!(invalid_field(&s).0, "sources[1].camera.intrinsics", "fx {fx}, cx {cx}");
        }
        let mut s = good.clone();
        s.pose.matrix[1][3] = 1e300;
        assert!(invalid_field(&s).1.contains("translation"));

        let mut s = good;
        s.width = 0;
        assert_eq!(invalid_field(&s).0, "sources[1].camera.width");
    }

    #[test]
    fn inverse_roundtrip() {
        let m = pose(rot_y(1.1), [1.0, 2.0, 3.0]);
        let i = invert4(&m).unwrap();
        let id = mul4(&m, &i);
        for (r, row) in id.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                assert!((v - if r == c { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        assert!(invert4(&[[0.0; 4]; 4]).is_none());
    }
}
