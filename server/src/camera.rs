//! The canonical camera every stage after the request works with: OpenCV axes, world-to-camera,
//! the form of docs/bundle.md. A request's cameras become it in `request::cameras`.

use nalgebra::{Matrix3, Matrix4, SMatrix};
use ndarray::Array3;

/// Canonical camera: OpenCV axes, world-to-camera, pixel (u, v) centred at image coordinates (u, v).
#[derive(Debug, Clone, PartialEq)]
pub struct CanonicalCamera {
    pub width: u32,
    pub height: u32,
    pub k: Matrix3<f64>,
    pub w2c: Matrix4<f64>,
}

impl CanonicalCamera {
    pub fn fx(&self) -> f64 {
        self.k[(0, 0)]
    }
    pub fn fy(&self) -> f64 {
        self.k[(1, 1)]
    }
    pub fn cx(&self) -> f64 {
        self.k[(0, 2)]
    }
    pub fn cy(&self) -> f64 {
        self.k[(1, 2)]
    }

    /// Centre and optical axis, for choosing sources (the rule shared with the client).
    pub fn viewpoint(&self) -> scnerf_capture::camera::Viewpoint {
        scnerf_capture::camera::Viewpoint::of_w2c(&self.w2c)
    }

    /// Camera-to-world transform: the general inverse of `w2c` (as numpy.linalg.inv in the
    /// exporter), not the rigid one, since validation accepts rotations orthonormal to 1e-3.
    pub fn c2w(&self) -> Matrix4<f64> {
        // Validation guarantees an invertible pose.
        self.w2c.try_inverse().unwrap_or(self.w2c)
    }
}

/// Matrices stacked into a (V, N, N) float32 array, each row-major: the graphs' camera inputs.
pub fn stack_rows<const N: usize>(matrices: &[SMatrix<f64, N, N>]) -> Array3<f32> {
    Array3::from_shape_fn((matrices.len(), N, N), |(i, r, c)| matrices[i][(r, c)] as f32)
}
