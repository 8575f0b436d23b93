//! Cameras in the project's canonical form, in one place (docs/design.md, "HTTP API"; the reference
//! implementation is `exporter/scnerf_export/cameras.py`, which the Python parsers of
//! `exporter/scnerf_export/data/dataparsers/` convert to):
//!
//! * OpenCV axes: x right, y down, z forward;
//! * world-to-camera poses;
//! * intrinsics in which the centre of pixel (u, v) is at image coordinates (u, v). Formats whose
//!   first pixel centre is at (0.5, 0.5) (COLMAP, nerfstudio) are shifted by -0.5 when read.
//!
//! The conventions of the API's poses are here too ([`PoseKind`], [`Axes`], [`canonical_w2c`]):
//! the server decodes requests with them and the client reads camera files with them, so a pose
//! means one camera on both sides.
//!
//! Every reader converts its cameras to this form once; paths, the API and the metrics see
//! nothing else. The source-ranking rule ([`rank_sources`]) lives here too: the client's
//! evaluation and the server's choice of sources per target are this one function.

use nalgebra::{Matrix3, Matrix4, Point3, Rotation3, Translation3, Unit, Vector3};
use serde::{Deserialize, Serialize};

/// A rigid world-to-camera transform. Kept as a rotation *matrix* (not a quaternion) so that a
/// pose read from a file is carried bit for bit to the request.
pub type Pose = nalgebra::IsometryMatrix3<f64>;

/// Pinhole intrinsics (no skew: the server refuses it).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema), schema(as = Focal))]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
    pub fn k(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// The intrinsics of a matrix of that form; `None` for any other (skewed, projective).
    pub fn from_k(k: &Matrix3<f64>) -> Option<Intrinsics> {
        let pinhole = k[(0, 1)] == 0.0 && k[(1, 0)] == 0.0 && k.row(2) == nalgebra::RowVector3::new(0.0, 0.0, 1.0);
        pinhole.then(|| Intrinsics { fx: k[(0, 0)], fy: k[(1, 1)], cx: k[(0, 2)], cy: k[(1, 2)] })
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub intrinsics: Intrinsics,
    pub w2c: Pose,
}

/// Whether `cameras.py::invert_rigid` (the Python loaders' inverse) inverts a matrix by transposing
/// its rotation: `np.allclose(R Rᵀ, I, atol=1e-6)` and `np.allclose(last row, [0, 0, 0, 1])`, with
/// numpy's default rtol of 1e-5. Mirrored exactly so both sides give the same numbers.
fn python_treats_as_rigid(m: &Matrix4<f64>) -> bool {
    let allclose = |a: f64, b: f64| (a - b).abs() <= 1e-6 + 1e-5 * b.abs();
    let r = m.fixed_view::<3, 3>(0, 0);
    let rrt = r * r.transpose();
    let identity = Matrix3::<f64>::identity();
    rrt.iter().zip(identity.iter()).all(|(a, b)| allclose(*a, *b))
        && m.row(3).iter().zip([0.0, 0.0, 0.0, 1.0]).all(|(a, b)| allclose(*a, b))
}

/// Largest deviation of R·Rᵀ from the identity that is still accepted as a rotation, by the
/// server in requests and by the readers in files (refusing worse poses while reading names the
/// file instead of a request field). Poses come from JSON files that often hold float32-rounded
/// numbers; 1e-3 accepts those and rejects scaled or sheared matrices.
pub const ROTATION_TOLERANCE: f64 = 1e-3;

/// What an API pose matrix maps: world points to camera points, or the reverse.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseKind {
    WorldToCamera,
    CameraToWorld,
}

/// The camera axes an API pose is written in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Axes {
    /// x right, y down, z forward (the canonical form).
    Opencv,
    /// x right, y up, z backward (Blender, NeRF synthetic, nerfstudio).
    Opengl,
}

impl Camera {
    /// Camera centre in world coordinates.
    pub fn center(&self) -> Point3<f64> {
        self.w2c.inverse_transform_point(&Point3::origin())
    }

    /// Unit optical axis in world coordinates (the third row of the rotation).
    pub fn forward(&self) -> Vector3<f64> {
        self.w2c.rotation.matrix().row(2).transpose()
    }

    pub fn viewpoint(&self) -> Viewpoint {
        Viewpoint::of_w2c(&self.w2c.to_homogeneous())
    }

    /// The same view resampled to `width` x `height`: f' = f s, c' = (c + 0.5) s - 0.5, so that
    /// pixel centres stay at integers (`cameras.py::Camera.resized`).
    pub fn resized(&self, width: u32, height: u32) -> Camera {
        let sx = f64::from(width) / f64::from(self.width);
        let sy = f64::from(height) / f64::from(self.height);
        let i = self.intrinsics;
        Camera {
            width,
            height,
            intrinsics: Intrinsics {
                fx: i.fx * sx,
                fy: i.fy * sy,
                cx: (i.cx + 0.5) * sx - 0.5,
                cy: (i.cy + 0.5) * sy - 0.5,
            },
            w2c: self.w2c,
        }
    }

    pub fn k(&self) -> Matrix3<f64> {
        self.intrinsics.k()
    }
}

/// OpenGL camera axes (x right, y up, z back) to OpenCV's: flip y and z (its own inverse).
pub fn gl_to_cv() -> Matrix4<f64> {
    Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, -1.0, -1.0, 1.0))
}

/// max |R Rᵀ - I| of the upper-left 3x3 block: compared with [`ROTATION_TOLERANCE`].
pub fn orthonormality_error(m: &Matrix4<f64>) -> f64 {
    let r = m.fixed_view::<3, 3>(0, 0);
    (r * r.transpose() - Matrix3::identity()).amax()
}

/// A 4x4 matrix as a pose, unchanged; `None` unless its last row is [0, 0, 0, 1], its values are
/// finite and its rotation block is a proper rotation within the server's tolerance.
pub fn pose_from_matrix(m: &Matrix4<f64>) -> Option<Pose> {
    let last_row_ok = (m.row(3) - nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0)).amax() <= 1e-9;
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
    let usable = m.iter().all(|v| v.is_finite())
        && last_row_ok
        && orthonormality_error(m) <= ROTATION_TOLERANCE
        && r.determinant() > 0.0;
    usable.then(|| {
        Pose::from_parts(
            Translation3::from(m.fixed_view::<3, 1>(0, 3).into_owned()),
            Rotation3::from_matrix_unchecked(r),
        )
    })
}

/// Inverse of a rigid 4x4 [R|t]: the transpose when R is orthonormal (by Python's test), else a
/// general inverse (`cameras.py::invert_rigid`).
fn invert_rigid(m: &Matrix4<f64>) -> Option<Matrix4<f64>> {
    if python_treats_as_rigid(m) {
        pose_from_matrix(m).map(|p| p.inverse().to_homogeneous())
    } else {
        m.try_inverse()
    }
}

/// Camera-to-world in OpenGL axes (nerfstudio, Blender) -> canonical world-to-camera.
pub fn w2c_from_opengl_c2w(c2w: &Matrix4<f64>) -> Option<Pose> {
    invert_rigid(&(c2w * gl_to_cv())).as_ref().and_then(pose_from_matrix)
}

/// Camera-to-world in OpenCV axes (LLFF after its column swap) -> world-to-camera.
pub fn w2c_from_c2w(c2w: &Matrix4<f64>) -> Option<Pose> {
    invert_rigid(c2w).as_ref().and_then(pose_from_matrix)
}

/// A pose in any of the API's conventions -> canonical world-to-camera, as the server decodes
/// requests: a camera-to-world matrix is inverted by the general inverse (numpy.linalg.inv's role
/// in `cameras.py::canonical_w2c`), not the rigid one, since a rotation is accepted when
/// orthonormal to [`ROTATION_TOLERANCE`]; the axes are changed on the camera side. `None` when a
/// camera-to-world matrix is singular. The matrix is not validated: callers check it first.
pub fn canonical_w2c(matrix: &Matrix4<f64>, kind: PoseKind, axes: Axes) -> Option<Matrix4<f64>> {
    let w2c_in_own_axes = match kind {
        PoseKind::WorldToCamera => *matrix,
        PoseKind::CameraToWorld => matrix.try_inverse()?,
    };
    Some(match axes {
        Axes::Opencv => w2c_in_own_axes,
        Axes::Opengl => gl_to_cv() * w2c_in_own_axes,
    })
}

/// [`canonical_w2c`] of a matrix that is a rigid transform (by [`pose_from_matrix`]) before and
/// after: the client's reading of camera files, giving the camera the server would compute.
pub fn w2c_from_api(matrix: &Matrix4<f64>, kind: PoseKind, axes: Axes) -> Option<Pose> {
    pose_from_matrix(matrix)?;
    pose_from_matrix(&canonical_w2c(matrix, kind, axes)?)
}

/// World-to-camera of a camera at `eye` looking at `target`, with `up` pointing up in the image
/// (`cameras.py::look_at`: x = forward x up, y = forward x right).
pub fn look_at(eye: &Point3<f64>, target: &Point3<f64>, up: &Vector3<f64>) -> Pose {
    // face_towards maps z to the direction and y towards the given vector: OpenCV's y is down.
    let rotation = Rotation3::face_towards(&(target - eye), &-up);
    Pose::from_parts(Translation3::from(eye.coords), rotation).inverse()
}

/// Unit vector, or `None` for a zero or non-finite one.
pub fn unit(v: Vector3<f64>) -> Option<Vector3<f64>> {
    Unit::try_new(v, 1e-12).map(Unit::into_inner)
}

/// Where the optical axes of a set of cameras meet: the point nearest to every axis (least
/// squares), and how far the axes spread.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Convergence {
    pub point: Point3<f64>,
    /// The smallest over the largest eigenvalue of the least-squares system: about the mean
    /// squared angle between the axes (0 when they are parallel).
    pub spread: f64,
}

/// The point the cameras look at, and the spread of their axes; `None` when the axes are
/// (nearly) parallel, spreading by less than about 6 degrees (`spread` <= 0.01), or when most
/// cameras have the point behind them.
pub fn convergence<'a>(cameras: impl IntoIterator<Item = &'a Camera>) -> Option<Convergence> {
    let cameras: Vec<&Camera> = cameras.into_iter().collect();
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for c in &cameras {
        let d = c.forward();
        let p = Matrix3::identity() - d * d.transpose();
        a += p;
        b += p * c.center().coords;
    }
    let eigen = a.symmetric_eigen();
    let spread = eigen.eigenvalues.min() / eigen.eigenvalues.max();
    if spread.is_nan() || spread <= 0.01 {
        return None;
    }
    let point = Point3::from(a.lu().solve(&b)?);
    let in_front = cameras.iter().filter(|c| (point - c.center()).dot(&c.forward()) > 0.0).count();
    (in_front * 2 > cameras.len()).then_some(Convergence { point, spread })
}

/// Where a camera is and which way it looks: all that source ranking needs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Viewpoint {
    pub centre: Point3<f64>,
    /// The optical axis (+z of the camera) in world coordinates.
    pub forward: Vector3<f64>,
}

impl Viewpoint {
    /// Of a world-to-camera matrix [R | t] (OpenCV axes), as `cameras.py::Camera` computes them:
    /// centre = -Rᵀ t, forward = the third row of R.
    pub fn of_w2c(w2c: &Matrix4<f64>) -> Viewpoint {
        let r = w2c.fixed_view::<3, 3>(0, 0);
        let t = w2c.fixed_view::<3, 1>(0, 3);
        Viewpoint { centre: Point3::from(-(r.transpose() * t)), forward: r.row(2).transpose() }
    }
}

/// Source ranking, MVSNeRF's rule (`cameras.py::rank_sources`): candidates by the distance of
/// their centre to the target's, nearest first, ties to the lower index; a candidate whose
/// optical axis makes 90 degrees or more with the target's (dot of the forward axes <= 0) sees
/// the other side and is left out. The first becomes the volume's reference view.
pub fn rank_sources(target: &Viewpoint, candidates: &[Viewpoint]) -> Vec<usize> {
    let mut ranked: Vec<(f64, usize)> = candidates
        .iter()
        .enumerate()
        .filter(|(_, c)| c.forward.dot(&target.forward) > 0.0)
        .map(|(i, c)| ((c.centre - target.centre).norm(), i))
        .collect();
    ranked.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    ranked.into_iter().map(|(_, i)| i).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera_at(eye: [f64; 3], target: [f64; 3]) -> Camera {
        Camera {
            width: 8,
            height: 6,
            intrinsics: Intrinsics { fx: 10.0, fy: 10.0, cx: 4.0, cy: 3.0 },
            w2c: look_at(&Point3::from(eye), &Point3::from(target), &Vector3::z()),
        }
    }

    #[test]
    fn look_at_matches_the_python_convention() {
        let c = camera_at([4.0, 0.0, 1.0], [0.0, 0.0, 1.0]);
        assert!((c.center() - Point3::new(4.0, 0.0, 1.0)).norm() < 1e-12);
        assert!((c.forward() - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-12);
        // x = forward x up, y (down) = forward x right
        let r = c.w2c.rotation.matrix();
        assert!((r.row(0).transpose() - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12);
        assert!((r.row(1).transpose() - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
    }

    #[test]
    fn opengl_round_trip() {
        let c = camera_at([1.0, 2.0, 3.0], [0.0, 0.5, 0.0]);
        let c2w_gl = c.w2c.inverse().to_homogeneous() * gl_to_cv();
        let back = w2c_from_opengl_c2w(&c2w_gl).unwrap();
        assert!((back.to_homogeneous() - c.w2c.to_homogeneous()).amax() < 1e-12);
        let api = w2c_from_api(&c2w_gl, PoseKind::CameraToWorld, Axes::Opengl).unwrap();
        assert!((api.to_homogeneous() - c.w2c.to_homogeneous()).amax() < 1e-12);
    }

    /// A pose matrix as the API receives it.
    type ApiPose = (Matrix4<f64>, PoseKind, Axes);

    /// One camera written in the API's four conventions, as a user would write it, and its
    /// canonical world-to-camera.
    fn one_camera_in_every_convention() -> (Matrix4<f64>, Vec<ApiPose>) {
        let w2c_cv = camera_at([1.0, 2.0, 3.0], [0.0, 0.5, 0.0]).w2c.to_homogeneous();
        let c2w_cv = w2c_cv.try_inverse().unwrap();
        let c2w_gl = c2w_cv * gl_to_cv();
        let w2c_gl = c2w_gl.try_inverse().unwrap();
        let written = vec![
            (w2c_cv, PoseKind::WorldToCamera, Axes::Opencv),
            (c2w_cv, PoseKind::CameraToWorld, Axes::Opencv),
            (c2w_gl, PoseKind::CameraToWorld, Axes::Opengl),
            (w2c_gl, PoseKind::WorldToCamera, Axes::Opengl),
        ];
        (w2c_cv, written)
    }

    #[test]
    fn every_api_convention_gives_the_canonical_pose() {
        let (w2c_cv, written) = one_camera_in_every_convention();
        for (m, kind, axes) in written {
            let w2c = canonical_w2c(&m, kind, axes).unwrap();
            assert!((w2c - w2c_cv).amax() < 1e-12, "{kind:?} {axes:?}: {w2c}");
        }
    }

    #[test]
    fn client_and_server_conversions_give_the_same_numbers() {
        let (_, written) = one_camera_in_every_convention();
        for (m, kind, axes) in written {
            let server = canonical_w2c(&m, kind, axes).unwrap();
            let client = w2c_from_api(&m, kind, axes).unwrap();
            assert_eq!(client.to_homogeneous().fixed_rows::<3>(0), server.fixed_rows::<3>(0), "{kind:?} {axes:?}");
        }
    }

    #[test]
    fn a_singular_camera_to_world_has_no_canonical_pose() {
        let singular = Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, 0.0, 1.0, 1.0));
        assert!(canonical_w2c(&singular, PoseKind::CameraToWorld, Axes::Opengl).is_none());
        assert!(w2c_from_api(&singular, PoseKind::CameraToWorld, Axes::Opencv).is_none());
    }

    #[test]
    fn resize_keeps_pixel_centres_at_integers() {
        let c = camera_at([1.0, 0.0, 0.0], [0.0, 0.0, 0.0]).resized(4, 3);
        assert_eq!(c.intrinsics, Intrinsics { fx: 5.0, fy: 5.0, cx: 1.75, cy: 1.25 });
    }

    #[test]
    fn intrinsics_are_the_pinhole_matrices() {
        let i = Intrinsics { fx: 8.0, fy: 9.0, cx: 4.0, cy: 3.5 };
        assert_eq!(Intrinsics::from_k(&i.k()), Some(i));
        let mut skewed = i.k();
        skewed[(0, 1)] = 0.5;
        assert_eq!(Intrinsics::from_k(&skewed), None);
        let mut projective = i.k();
        projective[(2, 0)] = 0.1;
        assert_eq!(Intrinsics::from_k(&projective), None);
    }

    #[test]
    fn non_rotations_are_refused() {
        let mut m = Matrix4::identity();
        m[(0, 0)] = 1.01;
        assert!(pose_from_matrix(&m).is_none());
        m[(0, 0)] = -1.0; // a reflection
        assert!(pose_from_matrix(&m).is_none());
    }

    #[test]
    fn ranking_is_by_distance_then_index_and_skips_opposite_views() {
        let target = camera_at([4.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        let a = camera_at([1.0, 4.0, 0.0], [0.0, 0.0, 0.0]);
        let b = camera_at([1.0, -4.0, 0.0], [0.0, 0.0, 0.0]); // as far as a: after it
        let near = camera_at([4.0, 1.0, 0.0], [0.0, 0.0, 0.0]);
        let behind = camera_at([-4.0, 0.0, 0.0], [0.0, 0.0, 0.0]); // faces the target
        let side = camera_at([0.0, 4.0, 0.0], [0.0, 0.0, 0.0]); // exactly 90 degrees: left out
        let candidates: Vec<Viewpoint> = [a, b, near, behind, side].iter().map(Camera::viewpoint).collect();
        assert_eq!(rank_sources(&target.viewpoint(), &candidates), vec![2, 0, 1]);
    }
}
