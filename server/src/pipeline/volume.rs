//! Stage 2: cost volume + 3D U-Net G2 -> encoding volume in the reference (first) view's frustum.

use nalgebra::{Matrix4, Vector4};
use ndarray::{ArcArray4, ArcArray5, Array1, Array3};

use crate::backend::{BackendError, Ticket};
use crate::bundle::{GraphKind, ModelConfig};
use crate::camera::{stack_rows, Camera};

/// `diag(1/4, 1/4, 1, 1) · [[K, 0], [0, 1]] · w2c` per view: projection onto the feature grid.
pub fn feature_projection(camera: &Camera) -> Matrix4<f64> {
    Matrix4::from_diagonal(&Vector4::new(0.25, 0.25, 1.0, 1.0)) * camera.k.to_homogeneous() * camera.w2c
}

/// (V, 4, 4) feature-grid projections.
pub fn projections(cameras: &[Camera]) -> Array3<f32> {
    stack_rows(&cameras.iter().map(feature_projection).collect::<Vec<_>>())
}

/// `linspace(near, far, D)`, computed like torch.linspace (from both ends towards the middle).
pub fn depth_planes(near: f64, far: f64, d: usize) -> Array1<f32> {
    let step = (far - near) / (d - 1) as f64;
    let half = d / 2;
    Array1::from_shape_fn(d, |i| if i < half { near + step * i as f64 } else { far - step * (d - 1 - i) as f64 } as f32)
}

/// features (V, C, h, w) + images + cameras -> volume (1, Cv, D, h + 2·pad, w + 2·pad).
pub async fn run(
    ticket: &Ticket,
    config: &ModelConfig,
    features: &ArcArray4<f32>,
    images: &ArcArray4<f32>,
    cameras: &[Camera],
    near: f64,
    far: f64,
) -> Result<ArcArray5<f32>, BackendError> {
    let (_, _, h, w) = features.dim();
    let inputs = vec![
        ("features".to_string(), features.clone().into_dyn()),
        ("images".to_string(), images.clone().into_dyn()),
        ("projections".to_string(), projections(cameras).into_shared().into_dyn()),
        ("depth_planes".to_string(), depth_planes(near, far, config.depth_planes).into_shared().into_dyn()),
    ];
    let mut out = ticket.run(GraphKind::Volume, super::pixel_units(images), inputs).await?;
    let shape = [
        Some(1),
        Some(config.volume_channels),
        Some(config.depth_planes),
        Some(h + 2 * config.pad),
        Some(w + 2 * config.pad),
    ];
    out.take("volume", &shape)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::from_rows;

    #[test]
    fn linspace_hits_both_ends() {
        let t = depth_planes(2.0, 6.0, 5);
        assert_eq!(t.to_vec(), vec![2.0, 3.0, 4.0, 5.0, 6.0]);
        let t = depth_planes(2.125, 4.525, 128);
        assert_eq!(t[0], 2.125);
        assert_eq!(t[127], 4.525);
    }

    #[test]
    fn projection_scales_intrinsics() {
        let cam = Camera {
            width: 8,
            height: 8,
            k: from_rows(&[[100.0, 0.0, 40.0], [0.0, 80.0, 20.0], [0.0, 0.0, 1.0]]),
            w2c: from_rows(&[[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]),
        };
        let p = projections(&[cam]);
        assert_eq!(p.slice(ndarray::s![0, 0, ..]).to_vec(), [25.0, 0.0, 10.0, 25.0 + 30.0]);
        assert_eq!(p.slice(ndarray::s![0, 1, ..]).to_vec(), [0.0, 20.0, 5.0, 40.0 + 15.0]);
        assert_eq!(p.slice(ndarray::s![0, 2, ..]).to_vec(), [0.0, 0.0, 1.0, 3.0]);
        assert_eq!(p.slice(ndarray::s![0, 3, ..]).to_vec(), [0.0, 0.0, 0.0, 1.0]);
    }
}
