//! Stage 0: the source images, decoded off the async runtime and stacked into one
//! (V, 3, H, W) tensor padded to the bundle's image multiple.

use crate::backend::Tensor;
use crate::error::ApiError;
use crate::image_io::{self, RgbF32};
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
) -> Result<Tensor, ApiError> {
    let sources = sources.to_vec();
    tokio::task::spawn_blocking(move || {
        let images =
            sources.iter().map(|s| decode_one(s, background, max_pixels)).collect::<Result<Vec<RgbF32>, ApiError>>()?;
        Ok(stack_padded(&images, multiple, background))
    })
    .await
    .map_err(|e| ApiError::Internal(format!("image decoding task failed: {e}")))?
}

fn decode_one(source: &ValidSource, background: [f32; 3], max_pixels: u64) -> Result<RgbF32, ApiError> {
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

/// Stacks same-size views into an NCHW tensor (V, 3, Hp, Wp), padded with `background` to
/// `padded_size`.
pub fn stack_padded(images: &[RgbF32], multiple: usize, background: [f32; 3]) -> Tensor {
    let (w, h) = (images[0].width as usize, images[0].height as usize);
    let (wp, hp) = padded_size(w, h, multiple);
    let plane = hp * wp;
    let mut data = Vec::with_capacity(images.len() * 3 * plane);
    for img in images {
        for (c, bg) in background.iter().enumerate() {
            let start = data.len();
            data.resize(start + plane, *bg);
            let dst = &mut data[start..];
            for y in 0..h {
                for x in 0..w {
                    dst[y * wp + x] = img.data[(y * w + x) * 3 + c];
                }
            }
        }
    }
    Tensor::new(vec![images.len(), 3, hp, wp], data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pads_with_background() {
        let img = RgbF32 { width: 1, height: 1, data: vec![0.1, 0.2, 0.3] };
        let t = stack_padded(&[img.clone(), img], 4, [1.0, 0.5, 0.0]);
        assert_eq!(t.shape, vec![2, 3, 4, 4]);
        assert_eq!(t.data[0], 0.1);
        assert_eq!(t.data[1], 1.0);
        assert_eq!(t.data[16], 0.2);
        assert_eq!(t.data[17], 0.5);
        assert_eq!(t.data[48], 0.1);
    }

    #[test]
    fn padded_sizes_round_up_each_side() {
        assert_eq!(padded_size(40, 32, 32), (64, 32));
        assert_eq!(padded_size(1, 65, 32), (32, 96));
    }
}
