//! A request's cameras (JSON `scnerf_capture::wire::WireCamera`, or protobuf) as a `CameraSpec`,
//! then converted from the accepted conventions (OpenCV/OpenGL axes, world-to-camera or
//! camera-to-world poses, {fx,fy,cx,cy} or a 3x3 K) to the canonical camera
//! (`crate::camera::CanonicalCamera`), with the validation that makes the math well defined. The
//! conventions themselves (axes, pose kinds, the conversion, the rotation tolerance) are
//! `scnerf_capture::camera`'s, shared with the client.

use nalgebra::{Matrix3, Matrix4, RowVector3, RowVector4};
use scnerf_capture::camera::{canonical_w2c, orthonormality_error, ROTATION_TOLERANCE};
pub use scnerf_capture::camera::{Axes, PoseKind};
use scnerf_capture::wire::{from_rows, WireCamera};

use crate::camera::CanonicalCamera;
use crate::error::ApiError;

#[derive(Debug, Clone, PartialEq)]
pub struct PoseSpec {
    pub matrix: Matrix4<f64>,
    pub kind: PoseKind,
    pub axes: Axes,
}

/// A camera as the client described it, whatever the wire form.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraSpec {
    pub width: u32,
    pub height: u32,
    /// The intrinsic matrix as given (`{fx, fy, cx, cy}` written as one), not yet checked.
    pub k: Matrix3<f64>,
    pub pose: PoseSpec,
}

/// Bounds that keep a camera renderable: the graphs compute rays, sample points and projections
/// in float32, where 1e-300 is 0 and 1e300 is infinite, and such cameras rendered blank views.
/// Focal lengths are relative to the image's larger side (fields of view from 0.06 to 179.8
/// degrees); the principal point may lie off the image (crops), by up to 1000 image sizes.
pub const FOCAL_PER_SIZE: std::ops::RangeInclusive<f64> = 1e-3..=1e3;
pub const MAX_PRINCIPAL_OFFSET_PER_SIZE: f64 = 1e3;
/// Largest camera translation, near and far plane in world units; smallest near plane.
pub const MAX_WORLD_EXTENT: f64 = 1e6;
pub const MIN_NEAR: f64 = 1e-6;

impl CameraSpec {
    /// The camera of a JSON document. `field` names it in errors (e.g. `sources[1].camera`):
    /// giving both `intrinsics` and `K`, or neither, is malformed.
    pub fn from_wire(c: &WireCamera, field: &str) -> Result<CameraSpec, ApiError> {
        let k =
            c.intrinsic_matrix().map_err(|e| ApiError::malformed(format!("{field}.{}", e.field()), e.to_string()))?;
        let pose = PoseSpec { matrix: from_rows(&c.pose.matrix), kind: c.pose.kind, axes: c.pose.axes };
        Ok(CameraSpec { width: c.width, height: c.height, k, pose })
    }

    /// Validates and converts to the canonical form. `field` names this camera in errors
    /// (e.g. `sources[1].camera`).
    pub fn canonicalize(&self, field: &str) -> Result<CanonicalCamera, ApiError> {
        if self.width == 0 || self.height == 0 {
            return Err(ApiError::invalid(format!("{field}.width"), "width and height must be > 0"));
        }
        let k = self.intrinsic_matrix(field)?;
        let w2c = self.world_to_camera(field)?;
        Ok(CanonicalCamera { width: self.width, height: self.height, k, w2c })
    }

    fn intrinsic_matrix(&self, field: &str) -> Result<Matrix3<f64>, ApiError> {
        let at = format!("{field}.intrinsics");
        let k = self.k;
        if !k.iter().all(|v| v.is_finite()) {
            return Err(ApiError::invalid(at, "intrinsics must be finite numbers"));
        }
        if k.row(2) != RowVector3::new(0.0, 0.0, 1.0) || k[(1, 0)] != 0.0 {
            return Err(ApiError::invalid(at, "K must have the form [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"));
        }
        if k[(0, 1)] != 0.0 {
            return Err(ApiError::invalid(at, "skewed intrinsics (K[0][1] != 0) are not supported"));
        }
        let (fx, fy) = (k[(0, 0)], k[(1, 1)]);
        if fx <= 0.0 || fy <= 0.0 {
            return Err(ApiError::invalid(at, "focal lengths fx and fy must be > 0"));
        }
        let size = f64::from(self.width.max(self.height));
        let (lo, hi) = (FOCAL_PER_SIZE.start() * size, FOCAL_PER_SIZE.end() * size);
        if !(FOCAL_PER_SIZE.contains(&(fx / size)) && FOCAL_PER_SIZE.contains(&(fy / size))) {
            return Err(ApiError::invalid(
                at,
                format!("focal lengths fx and fy must be within [{lo:e}, {hi:e}] pixels for a {size}-pixel image"),
            ));
        }
        let max_offset = MAX_PRINCIPAL_OFFSET_PER_SIZE * size;
        let offsets = [k[(0, 2)] - f64::from(self.width) / 2.0, k[(1, 2)] - f64::from(self.height) / 2.0];
        if offsets.iter().any(|o| o.abs() > max_offset) {
            return Err(ApiError::invalid(
                at,
                format!("the principal point cx, cy must lie within {max_offset:e} pixels of the image centre"),
            ));
        }
        Ok(k)
    }

    fn world_to_camera(&self, field: &str) -> Result<Matrix4<f64>, ApiError> {
        let at = format!("{field}.pose.matrix");
        let m = &self.pose.matrix;
        if !m.iter().all(|v| v.is_finite()) {
            return Err(ApiError::invalid(at, "pose matrix must hold finite numbers"));
        }
        if (m.row(3) - RowVector4::new(0.0, 0.0, 0.0, 1.0)).lp_norm(1) > 1e-6 {
            return Err(ApiError::invalid(at, "the last row of the pose matrix must be [0, 0, 0, 1]"));
        }
        check_rotation(m).map_err(|msg| ApiError::invalid(at.clone(), msg))?;
        if m.fixed_view::<3, 1>(0, 3).amax() > MAX_WORLD_EXTENT {
            return Err(ApiError::invalid(at, format!("the translation must be within {MAX_WORLD_EXTENT:e} units")));
        }
        canonical_w2c(m, self.pose.kind, self.pose.axes).ok_or_else(|| ApiError::invalid(at, "pose matrix is singular"))
    }
}

/// The rotation block of pose `m` must be a proper rotation (orthonormal, det +1).
fn check_rotation(m: &Matrix4<f64>) -> Result<(), String> {
    let worst = orthonormality_error(m);
    if worst > ROTATION_TOLERANCE {
        return Err(format!(
            "the rotation part of the pose is not orthonormal (max |R·Rᵀ - I| = {worst:.3e} > {ROTATION_TOLERANCE:e})"
        ));
    }
    if m.fixed_view::<3, 3>(0, 0).determinant() < 0.0 {
        return Err("the rotation part of the pose is a reflection (determinant -1)".into());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Point3, Vector3, Vector4};
    use scnerf_capture::camera::{gl_to_cv, look_at, Intrinsics};
    use scnerf_capture::wire::{WireIntrinsics, WirePose};

    /// A rigid transform: rotation about y by `theta`, then translation `t`.
    fn pose(theta: f64, t: [f64; 3]) -> Matrix4<f64> {
        Isometry3::new(Vector3::from(t), Vector3::y() * theta).to_homogeneous()
    }

    fn spec(matrix: Matrix4<f64>, kind: PoseKind, axes: Axes) -> CameraSpec {
        CameraSpec {
            width: 64,
            height: 48,
            k: Intrinsics { fx: 50.0, fy: 50.0, cx: 32.0, cy: 24.0 }.k(),
            pose: PoseSpec { matrix, kind, axes },
        }
    }

    #[test]
    fn all_conventions_agree() {
        let w2c_cv = pose(0.3, [0.1, -0.2, 4.0]);
        let c2w_cv = w2c_cv.try_inverse().unwrap();
        let c2w_gl = c2w_cv * gl_to_cv(); // gl_to_cv is its own inverse
        let w2c_gl = c2w_gl.try_inverse().unwrap();
        for (m, kind, axes) in [
            (w2c_cv, PoseKind::WorldToCamera, Axes::Opencv),
            (c2w_cv, PoseKind::CameraToWorld, Axes::Opencv),
            (c2w_gl, PoseKind::CameraToWorld, Axes::Opengl),
            (w2c_gl, PoseKind::WorldToCamera, Axes::Opengl),
        ] {
            let cam = spec(m, kind, axes).canonicalize("target").unwrap();
            assert!((cam.w2c - w2c_cv).amax() < 1e-12, "{kind:?} {axes:?}: {}", cam.w2c);
        }
    }

    #[test]
    fn opengl_camera_looks_down_minus_z() {
        // A Blender camera at (0,0,4) looking at the origin: OpenCV z (forward) must be world -z.
        let c2w_gl = pose(0.0, [0.0, 0.0, 4.0]);
        let cam = spec(c2w_gl, PoseKind::CameraToWorld, Axes::Opengl).canonicalize("t").unwrap();
        let c2w = cam.c2w();
        assert_eq!(c2w.fixed_view::<3, 1>(0, 2), Vector3::new(0.0, 0.0, -1.0));
        assert_eq!(c2w.fixed_view::<3, 1>(0, 3), Vector3::new(0.0, 0.0, 4.0));
    }

    #[test]
    fn a_canonical_camera_sent_as_json_reads_back_as_itself() {
        let c = scnerf_capture::camera::Camera {
            width: 64,
            height: 48,
            intrinsics: Intrinsics { fx: 50.5, fy: 51.0, cx: 31.5, cy: 23.5 },
            w2c: look_at(&Point3::new(0.3, -1.0, 4.0), &Point3::origin(), &Vector3::z()),
        };
        let sent: WireCamera = serde_json::from_str(&serde_json::to_string(&WireCamera::from(&c)).unwrap()).unwrap();
        let cam = CameraSpec::from_wire(&sent, "target").unwrap().canonicalize("target").unwrap();
        assert_eq!((cam.width, cam.height, cam.k), (64, 48, c.k()));
        // serde_json reads a number back to within an ulp (its exact parser is a feature left off).
        assert!((cam.w2c - c.w2c.to_homogeneous()).amax() < 1e-15, "{}", cam.w2c);
    }

    #[test]
    fn intrinsics_in_any_form_give_the_same_camera() {
        let pose = WirePose {
            matrix: [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]],
            kind: PoseKind::WorldToCamera,
            axes: Axes::Opencv,
        };
        let rows = [[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]];
        let focal = WireIntrinsics::Focal(Intrinsics { fx: 50.0, fy: 50.0, cx: 32.0, cy: 24.0 });
        let wire = |intrinsics, k| WireCamera { width: 64, height: 48, intrinsics, k, pose: pose.clone() };
        let a = CameraSpec::from_wire(&wire(Some(focal.clone()), None), "t").unwrap();
        assert_eq!(CameraSpec::from_wire(&wire(Some(WireIntrinsics::Matrix(rows)), None), "t").unwrap(), a);
        assert_eq!(CameraSpec::from_wire(&wire(None, Some(rows)), "t").unwrap(), a);

        let malformed = |w: WireCamera| match CameraSpec::from_wire(&w, "sources[2].camera").unwrap_err() {
            ApiError::Malformed { field, message } => (field, message),
            e => panic!("unexpected {e:?}"),
        };
        assert_eq!(
            malformed(wire(Some(focal), Some(rows))),
            (Some("sources[2].camera.K".into()), "give either intrinsics or K, not both".into())
        );
        assert_eq!(
            malformed(wire(None, None)),
            (Some("sources[2].camera.intrinsics".into()), "missing field `intrinsics` (or `K`)".into())
        );
    }

    fn invalid_field(s: &CameraSpec) -> (String, String) {
        match s.canonicalize("sources[1].camera").unwrap_err() {
            ApiError::Invalid { field, message } => (field, message),
            e => panic!("unexpected {e:?}"),
        }
    }

    #[test]
    fn rejects_bad_cameras_naming_the_field() {
        let good = spec(pose(0.2, [0.0, 0.0, 3.0]), PoseKind::WorldToCamera, Axes::Opencv);

        let mut s = good.clone();
        s.pose.matrix[(0, 3)] = f64::NAN;
        assert_eq!(invalid_field(&s).0, "sources[1].camera.pose.matrix");

        let mut s = good.clone();
        s.pose.matrix[(0, 0)] *= 2.0; // scaled axis
        assert!(invalid_field(&s).1.contains("orthonormal"));

        let mut s = good.clone();
        s.pose.matrix = Matrix4::from_diagonal(&Vector4::new(0.0, 0.0, 0.0, 1.0)); // singular
        assert!(invalid_field(&s).1.contains("orthonormal"));

        let mut s = good.clone();
        s.pose.matrix = Matrix4::from_diagonal(&Vector4::new(-1.0, 1.0, 1.0, 1.0)); // reflection
        assert!(invalid_field(&s).1.contains("reflection"));

        let mut s = good.clone();
        s.pose.matrix.set_row(3, &RowVector4::new(0.0, 0.0, 1.0, 1.0));
        assert!(invalid_field(&s).1.contains("last row"));

        let mut s = good.clone();
        s.k = Intrinsics { fx: -1.0, fy: 50.0, cx: 0.0, cy: 0.0 }.k();
        assert_eq!(
            invalid_field(&s),
            ("sources[1].camera.intrinsics".into(), "focal lengths fx and fy must be > 0".into())
        );

        let mut s = good.clone();
        s.k = Intrinsics { fx: f64::INFINITY, fy: 50.0, cx: 0.0, cy: 0.0 }.k();
        assert!(invalid_field(&s).1.contains("finite"));

        let mut s = good.clone();
        s.k = from_rows(&[[50.0, 1.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]]);
        assert!(invalid_field(&s).1.contains("skew"));

        let mut s = good.clone();
        s.k = from_rows(&[[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 1.0, 1.0]]);
        assert!(invalid_field(&s).1.contains("form"));

        // Finite but beyond what float32 rendering can use.
        for (fx, cx) in [(1e-300, 32.0), (1e300, 32.0), (50.0, 1e300), (50.0, -1e9)] {
            let mut s = good.clone();
            s.k = Intrinsics { fx, fy: 50.0, cx, cy: 24.0 }.k();
            assert_eq!(invalid_field(&s).0, "sources[1].camera.intrinsics", "fx {fx}, cx {cx}");
        }
        let mut s = good.clone();
        s.pose.matrix[(1, 3)] = 1e300;
        assert!(invalid_field(&s).1.contains("translation"));

        let mut s = good;
        s.width = 0;
        assert_eq!(invalid_field(&s).0, "sources[1].camera.width");
    }
}
