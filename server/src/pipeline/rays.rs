//! Target rays through pixel centres (docs/bundle.md): pixel (u, v) is centred at image
//! coordinates (u, v); origin = camera centre in world space, direction =
//! R_c2w · [(u − cx)/fx, (v − cy)/fy, 1] (not normalised: the renderer's sample parameter t is the
//! target camera's z-depth). Rays are ordered row by row (v outer, u inner).

use crate::camera::Camera;

#[derive(Debug, Clone, PartialEq)]
pub struct Rays {
    /// (N, 3) world-space origins.
    pub origins: Vec<f32>,
    /// (N, 3) world-space directions.
    pub directions: Vec<f32>,
}

impl Rays {
    pub fn len(&self) -> usize {
        self.origins.len() / 3
    }

    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }
}

/// Computed in f64 and rounded once to f32.
pub fn generate(camera: &Camera) -> Rays {
    let c2w = camera.c2w();
    let (w, h) = (camera.width as usize, camera.height as usize);
    let origin = [c2w[0][3] as f32, c2w[1][3] as f32, c2w[2][3] as f32];
    let mut origins = Vec::with_capacity(w * h * 3);
    let mut directions = Vec::with_capacity(w * h * 3);
    for v in 0..h {
        let y = (v as f64 - camera.cy()) / camera.fy();
        for u in 0..w {
            let x = (u as f64 - camera.cx()) / camera.fx();
            for row in &c2w[..3] {
                directions.push((row[0] * x + row[1] * y + row[2]) as f32);
            }
            origins.extend_from_slice(&origin);
        }
    }
    Rays { origins, directions }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn principal_point_ray_is_the_optical_axis() {
        // Camera at world (0, 0, -2) looking down +z (identity rotation, OpenCV).
        let cam = Camera {
            width: 5,
            height: 3,
            k: [[10.0, 0.0, 2.0], [0.0, 20.0, 1.0], [0.0, 0.0, 1.0]],
            w2c: [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0]],
        };
        let rays = generate(&cam);
        assert_eq!(rays.len(), 15);
        let centre = 5 + 2; // v = 1, u = 2
        assert_eq!(&rays.directions[centre * 3..centre * 3 + 3], &[0.0, 0.0, 1.0]);
        assert_eq!(&rays.origins[centre * 3..centre * 3 + 3], &[0.0, 0.0, -2.0]);
        // u = 0, v = 0: x = -0.2, y = -0.05
        assert_eq!(&rays.directions[..3], &[-0.2, -0.05, 1.0]);
    }
}
