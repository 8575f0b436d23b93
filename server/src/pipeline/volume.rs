//! Stage 2: cost volume + 3D U-Net G2 -> encoding volume in the reference (first) view's frustum.

use crate::backend::{BackendError, Tensor, Ticket};
use crate::bundle::{GraphKind, ModelConfig};
use crate::camera::{mul4, Camera, Mat4};

/// `diag(1/4, 1/4, 1, 1) · [[K, 0], [0, 1]] · w2c` per view: projection onto the feature grid.
pub fn feature_projection(camera: &Camera) -> Mat4 {
    let k = camera.k;
    let k4 = [
        [k[0][0] / 4.0, k[0][1] / 4.0, k[0][2] / 4.0, 0.0],
        [k[1][0] / 4.0, k[1][1] / 4.0, k[1][2] / 4.0, 0.0],
        [k[2][0], k[2][1], k[2][2], 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    mul4(&k4, &camera.w2c)
}

pub fn projections(cameras: &[Camera]) -> Tensor {
    let data = cameras.iter().flat_map(|c| feature_projection(c).into_iter().flatten().map(|x| x as f32)).collect();
    Tensor::new(vec![cameras.len(), 4, 4], data)
}

/// `linspace(near, far, D)`, computed like torch.linspace (from both ends towards the middle).
pub fn depth_planes(near: f64, far: f64, d: usize) -> Tensor {
    let step = (far - near) / (d - 1) as f64;
    let half = d / 2;
    let data = (0..d)
        .map(|i| if i < half { near + step * i as f64 } else { far - step * (d - 1 - i) as f64 } as f32)
        .collect();
    Tensor::new(vec![d], data)
}

/// features (V, C, h, w) + images + cameras -> volume (1, Cv, D, h + 2·pad, w + 2·pad).
pub async fn run(
    ticket: &Ticket,
    config: &ModelConfig,
    features: &Tensor,
    images: &Tensor,
    cameras: &[Camera],
    near: f64,
    far: f64,
) -> Result<Tensor, BackendError> {
    let (h, w) = (features.shape[2], features.shape[3]);
    let inputs = vec![
        ("features".to_string(), features.clone()),
        ("images".to_string(), images.clone()),
        ("projections".to_string(), projections(cameras)),
        ("depth_planes".to_string(), depth_planes(near, far, config.depth_planes)),
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

    #[test]
    fn linspace_hits_both_ends() {
        let t = depth_planes(2.0, 6.0, 5);
        assert_eq!(*t.data, vec![2.0, 3.0, 4.0, 5.0, 6.0]);
        let t = depth_planes(2.125, 4.525, 128);
        assert_eq!(t.data[0], 2.125);
        assert_eq!(t.data[127], 4.525);
    }

    #[test]
    fn projection_scales_intrinsics() {
        let cam = Camera {
            width: 8,
            height: 8,
            k: [[100.0, 0.0, 40.0], [0.0, 80.0, 20.0], [0.0, 0.0, 1.0]],
            w2c: [[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]],
        };
        let p = feature_projection(&cam);
        assert_eq!(p[0], [25.0, 0.0, 10.0, 25.0 + 30.0]);
        assert_eq!(p[1], [0.0, 20.0, 5.0, 40.0 + 15.0]);
        assert_eq!(p[2], [0.0, 0.0, 1.0, 3.0]);
        assert_eq!(p[3], [0.0, 0.0, 0.0, 1.0]);
    }
}
