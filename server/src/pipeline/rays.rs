//! Target rays through pixel centres (docs/bundle.md): pixel (u, v) is centred at image
//! coordinates (u, v); origin = camera centre in world space, direction =
//! R_c2w · [(u − cx)/fx, (v − cy)/fy, 1] (not normalised: the renderer's sample parameter t is the
//! target camera's z-depth). Rays are ordered row by row (v outer, u inner).

use ndarray::{ArcArray2, Array1, Array3, Axis};

use crate::camera::CanonicalCamera;

#[derive(Debug, Clone, PartialEq)]
pub struct Rays {
    /// (N, 3) world-space origins.
    pub origins: ArcArray2<f32>,
    /// (N, 3) world-space directions.
    pub directions: ArcArray2<f32>,
}

impl Rays {
    pub fn len(&self) -> usize {
        self.origins.nrows()
    }

    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }

    /// The rays of `rows`, in that order (the pixels one pass renders).
    pub fn select(&self, rows: &[usize]) -> Rays {
        Rays {
            origins: self.origins.select(Axis(0), rows).into_shared(),
            directions: self.directions.select(Axis(0), rows).into_shared(),
        }
    }
}

/// Computed in f64 and rounded once to f32.
pub fn generate(camera: &CanonicalCamera) -> Rays {
    let c2w = camera.c2w();
    let (w, h) = (camera.width as usize, camera.height as usize);
    let x = Array1::from_shape_fn(w, |u| (u as f64 - camera.cx()) / camera.fx());
    let y = Array1::from_shape_fn(h, |v| (v as f64 - camera.cy()) / camera.fy());
    let directions =
        Array3::from_shape_fn((h, w, 3), |(v, u, k)| (c2w[(k, 0)] * x[u] + c2w[(k, 1)] * y[v] + c2w[(k, 2)]) as f32);
    let origin = Array1::from_shape_fn(3, |k| c2w[(k, 3)] as f32);
    let origins = origin.broadcast((h * w, 3)).expect("(3,) broadcasts to (N, 3)").to_owned();
    let directions = directions.into_shape_with_order((h * w, 3)).expect("h·w·3 elements");
    Rays { origins: origins.into_shared(), directions: directions.into_shared() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scnerf_capture::wire::from_rows;

    #[test]
    fn principal_point_ray_is_the_optical_axis() {
        // CanonicalCamera at world (0, 0, -2) looking down +z (identity rotation, OpenCV).
        let cam = CanonicalCamera {
            width: 5,
            height: 3,
            k: from_rows(&[[10.0, 0.0, 2.0], [0.0, 20.0, 1.0], [0.0, 0.0, 1.0]]),
            w2c: from_rows(&[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0]]),
        };
        let rays = generate(&cam);
        assert_eq!(rays.len(), 15);
        let centre = 5 + 2; // v = 1, u = 2
        assert_eq!(rays.directions.row(centre).to_vec(), [0.0, 0.0, 1.0]);
        assert_eq!(rays.origins.row(centre).to_vec(), [0.0, 0.0, -2.0]);
        // u = 0, v = 0: x = -0.2, y = -0.05
        assert_eq!(rays.directions.row(0).to_vec(), [-0.2, -0.05, 1.0]);
    }
}
