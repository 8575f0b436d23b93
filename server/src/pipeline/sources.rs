//! Stage 0: the source images, decoded off the async runtime and stacked into one
//! (V, 3, H, W) tensor padded to the bundle's image multiple.

use ndarray::{s, Array3, Array4, ArrayViewMut3, Axis};

use crate::blocking;
use crate::error::ApiError;
use crate::image_io;
use crate::request::ValidSource;

/// The size a `width` x `height` source is padded to: each side rounded up to `multiple`. The
/// padding goes right and bottom, which leaves the intrinsics unchanged.
pub fn padded_size(width: usize, height: usize, multiple: usize) -> (usize, usize) {
    (width.div_ceil(multiple) * multiple, height.div_ceil(multiple) * multiple)
}

/// Decodes the sources' images (PNG/JPEG, transparency composited on `background`) into one
/// stack padded to `multiple`, one image at a time: what a request holds is the stack and the
/// image being decoded (`estimate::decode_bytes`). Stops between images when the request is gone.
pub async fn decode(
    sources: &[ValidSource],
    background: [f32; 3],
    max_pixels: u64,
    multiple: usize,
) -> Result<Array4<f32>, ApiError> {
    let sources = sources.to_vec();
    blocking::run(move |cancel| {
        let first = &sources.first().ok_or_else(|| ApiError::invalid("sources", "no source views"))?.camera;
        let mut stacked =
            padded_stack(sources.len(), first.width as usize, first.height as usize, multiple, background);
        for (view, source) in stacked.outer_iter_mut().zip(&sources) {
            cancel.check()?;
            put(view, &decode_one(source, background, max_pixels)?);
        }
        Ok(stacked)
    })
    .await
}

/// `count` views of `width` x `height` padded to `padded_size`, filled with `background`.
fn padded_stack(count: usize, width: usize, height: usize, multiple: usize, background: [f32; 3]) -> Array4<f32> {
    let (wp, hp) = padded_size(width, height, multiple);
    let mut stacked = Array4::zeros((count, 3, hp, wp));
    for (c, bg) in background.into_iter().enumerate() {
        stacked.index_axis_mut(Axis(1), c).fill(bg);
    }
    stacked
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

/// An (H, W, 3) image into the top left of its padded (3, Hp, Wp) place in the stack.
fn put(mut view: ArrayViewMut3<f32>, image: &Array3<f32>) {
    let (h, w, _) = image.dim();
    view.slice_mut(s![.., ..h, ..w]).assign(&image.view().permuted_axes([2, 0, 1]));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pads_with_background() {
        let img = ndarray::arr3(&[[[0.1, 0.2, 0.3]]]);
        let mut t = padded_stack(2, 1, 1, 4, [1.0, 0.5, 0.0]);
        for view in t.outer_iter_mut() {
            put(view, &img);
        }
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
