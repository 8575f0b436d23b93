//! Stage 0: the source images, decoded off the async runtime and stacked into one
//! (V, 3, H, W) tensor padded to the bundle's image multiple.

use ndarray::{s, Array3, Array4, Axis};

use crate::error::ApiError;
use crate::image_io;
use crate::request::ValidSource;

/// The size a `width` x `height` source is padded to: each side rounded up to `multiple`. The
/// padding goes right and bottom, which leaves the intrinsics unchanged.
pub fn padded_size(width: usize, height: usize, multiple: usize) -> (usize, usize) {
    (width.div_ceil(multiple) * multiple, height.div_ceil(multiple) * multiple)
}

/// Decodes the sources' images (PNG/JPEG, transparency composited on `background`) and stacks
/// them padded to `multiple`.
pub async fn decode(
    sources: &[ValidSource],
    background: [f32; 3],
    max_pixels: u64,
    multiple: usize,
) -> Result<Array4<f32>, ApiError> {
    let sources = sources.to_vec();
    tokio::task::spawn_blocking(move || {
        let images = sources.iter().map(|s| decode_one(s, background, max_pixels)).collect::<Result<Vec<_>, _>>()?;
        Ok(stack_padded(&images, multiple, background))
    })
    .await
    .map_err(|e| ApiError::Internal(format!("image decoding task failed: {e}")))?
}

fn decode_one(source: &ValidSource, background: [f32; 3], max_pixels: u64) -> Result<Array3<f32>, ApiError> {
    let (cam, field) = (&source.camera, source.image_field.as_str());
    // The header alone tells the size: a mismatch is refused before anything is decoded.
    let (_, width, height) = image_io::probe(&source.image, field)?;
    if (width, height) != (cam.width, cam.height) {
        return Err(ApiError::invalid(
            field.to_string(),
            format!("image is {width}x{height} but its camera says {}x{}", cam.width, cam.height),
        ));
    }
    image_io::decode_source(&source.image, field, background, max_pixels)
}

/// Stacks same-size (H, W, 3) views into one NCHW array (V, 3, Hp, Wp), padded with
/// `background` to `padded_size`.
pub fn stack_padded(images: &[Array3<f32>], multiple: usize, background: [f32; 3]) -> Array4<f32> {
    let (h, w, _) = images[0].dim();
    let (wp, hp) = padded_size(w, h, multiple);
    let mut stacked = Array4::zeros((images.len(), 3, hp, wp));
    for (c, bg) in background.into_iter().enumerate() {
        stacked.index_axis_mut(Axis(1), c).fill(bg);
    }
    for (mut view, image) in stacked.outer_iter_mut().zip(images) {
        view.slice_mut(s![.., ..h, ..w]).assign(&image.view().permuted_axes([2, 0, 1]));
    }
    stacked
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pads_with_background() {
        let img = ndarray::arr3(&[[[0.1, 0.2, 0.3]]]);
        let t = stack_padded(&[img.clone(), img], 4, [1.0, 0.5, 0.0]);
        assert_eq!(t.shape(), &[2, 3, 4, 4]);
        let flat = t.as_slice().unwrap();
        assert_eq!(flat[0], 0.1);
        assert_eq!(flat[1], 1.0);
        assert_eq!(flat[16], 0.2);
        assert_eq!(flat[17], 0.5);
        assert_eq!(flat[48], 0.1);
    }

    #[test]
    fn padded_sizes_round_up_each_side() {
        assert_eq!(padded_size(40, 32, 32), (64, 32));
        assert_eq!(padded_size(1, 65, 32), (32, 96));
    }
}
