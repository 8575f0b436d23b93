//! Stage 1: the 2D encoder G1, all source views in one run (its batch norm uses the statistics of
//! the V views together, as the public checkpoint was evaluated).

use ndarray::ArcArray4;

use super::pixel_units;
use crate::backend::{BackendError, Ticket};
use crate::bundle::{GraphKind, ModelConfig};

/// images (V, 3, H, W) in [0, 1] -> features (V, C, H/4, W/4).
pub async fn run(
    ticket: &Ticket,
    config: &ModelConfig,
    images: &ArcArray4<f32>,
) -> Result<ArcArray4<f32>, BackendError> {
    let (v, _, h, w) = images.dim();
    let inputs = vec![("images".into(), images.clone().into_dyn())];
    let mut out = ticket.run(GraphKind::Encoder, pixel_units(images), inputs).await?;
    out.take("features", &[Some(v), Some(config.feature_channels), Some(h / 4), Some(w / 4)])
}
