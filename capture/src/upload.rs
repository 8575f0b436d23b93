//! What is sent of a view: its camera fitted to the server's source limit ([`fit_to_limit`]) and
//! its image as that camera sees it ([`image_bytes`]). The `scnerf` client (render, view, eval)
//! and the server's `POST /v1/captures` (the viewer's drop, the Python client) both go through
//! these, so a capture is undistorted and resized one way. The files on disk are never changed.

use std::borrow::Cow;
use std::io::Cursor;
use std::path::Path;

use image::{DynamicImage, ImageFormat, Rgba};

use crate::error::{Error, Result};
use crate::images;
use crate::readers::{Capture, CapturedView};

/// Shrinks every view of more than `max_pixels` pixels to fit ([`fitted_size`]; cameras scaled
/// with pixel centres at integers); [`image_bytes`] then resamples the images. What was done, in
/// one line ([`fit_note`]), if anything.
pub fn fit_to_limit(capture: &mut Capture, max_pixels: u64) -> Option<String> {
    let mut resized = Vec::new();
    for view in &mut capture.views {
        let camera = &mut view.camera;
        if let Some((w, h)) = fitted_size(camera.width, camera.height, max_pixels) {
            resized.push(((camera.width, camera.height), (w, h)));
            *camera = camera.resized(w, h);
        }
    }
    let &(from, to) = resized.first()?;
    Some(fit_note(resized.len(), from, to, max_pixels))
}

/// The size an image of `width` x `height` is resized to when it has more than `max_pixels`
/// pixels: the aspect kept, each side scaled by sqrt(max_pixels / pixels) and rounded down (at
/// least 1); `None` when it fits as it is.
pub fn fitted_size(width: u32, height: u32, max_pixels: u64) -> Option<(u32, u32)> {
    let pixels = u64::from(width) * u64::from(height);
    if pixels <= max_pixels {
        return None;
    }
    let scale = (max_pixels as f64 / pixels as f64).sqrt();
    let (w, h) = ((f64::from(width) * scale) as u32, (f64::from(height) * scale) as u32);
    Some((w.max(1), h.max(1)))
}

/// The one line said of `count` images resized to fit (the first of them `from` -> `to`): by the
/// `scnerf` client, `POST /v1/captures` and the plan of what a client sends of a capture.
pub fn fit_note(count: usize, from: (u32, u32), to: (u32, u32), max_pixels: u64) -> String {
    format!(
        "{count} images of {}x{} exceed the server's limit of {max_pixels} pixels per source view: resizing them to \
         {}x{}",
        from.0, from.1, to.0, to.1
    )
}

/// Most pixels of a photo that is decoded to be undistorted or resized (a 48-megapixel phone
/// photo has 48 million): a header claiming more is refused before anything is allocated.
pub const MAX_DECODED_PIXELS: u64 = 1 << 26;

/// The photo's size when the image of `view` must be made from it (undistorted or resized);
/// `None` when the photo is that image, or its header cannot be read (the server refuses it).
fn to_resample(view: &CapturedView, bytes: &[u8]) -> Option<(u32, u32)> {
    let header = images::read_header(Cursor::new(bytes)).ok()?;
    let size = (header.width, header.height);
    (view.lens.is_some() || size != (view.camera.width, view.camera.height)).then_some(size)
}

/// Most bytes decoding a photo of `width` x `height` takes ([`images::decode`]): 16-bit RGBA,
/// and the decoder's buffers beside the pixels.
fn decode_bytes(width: u32, height: u32) -> u64 {
    u64::from(width) * u64::from(height) * 8 + images::HEADER_BYTES as u64
}

/// The memory [`image_bytes`] takes for `view`'s photo at most (the decoded photo, an 8-bit
/// RGBA copy and the undistorted image; a resized image is smaller): 0 when the photo is sent
/// as it is.
pub fn resample_bytes(view: &CapturedView, bytes: &[u8]) -> u64 {
    to_resample(view, bytes).map_or(0, |(w, h)| decode_bytes(w, h) + u64::from(w) * u64::from(h) * 8)
}

/// The image of `view` as its camera sees it, from the photo's `bytes`: the bytes as they are
/// when the photo is that image already; else decoded, undistorted ([`CapturedView::lens`]; the
/// pixels no photo pixel reaches take `background`), resized to the camera's size, and encoded
/// again (JPEG stays JPEG, at quality 95; anything else PNG).
pub fn image_bytes<'a>(view: &CapturedView, bytes: &'a [u8], background: [f64; 3]) -> Result<Cow<'a, [u8]>> {
    let Some((width, height)) = to_resample(view, bytes) else { return Ok(Cow::Borrowed(bytes)) };
    let path = &view.image_path;
    if u64::from(width) * u64::from(height) > MAX_DECODED_PIXELS {
        return Err(Error::dataset(
            path,
            format!("image of {width}x{height} has more than {MAX_DECODED_PIXELS} pixels, too many to resample"),
        ));
    }
    let bad = |e: images::ImageError| Error::dataset(path, format!("cannot decode the image: {e}"));
    let jpeg = image::guess_format(bytes).ok() == Some(ImageFormat::Jpeg);
    let mut image = images::decode(bytes).map_err(bad)?;
    if let Some(lens) = &view.lens {
        let fill = background.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8);
        let undistorted = lens.undistort_image(&image.to_rgba8(), Rgba([fill[0], fill[1], fill[2], 255]));
        image = DynamicImage::ImageRgba8(undistorted);
    }
    let camera = &view.camera;
    if (image.width(), image.height()) != (camera.width, camera.height) {
        image = image.resize_exact(camera.width, camera.height, image::imageops::FilterType::Triangle);
    }
    encode(&image, jpeg, path).map(Cow::Owned)
}

fn encode(image: &DynamicImage, jpeg: bool, path: &Path) -> Result<Vec<u8>> {
    let bad = |e: image::ImageError| Error::dataset(path, format!("cannot encode the resampled image: {e}"));
    let mut out = Cursor::new(Vec::new());
    if jpeg {
        let encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95);
        image.to_rgb8().write_with_encoder(encoder).map_err(bad)?;
    } else {
        image.write_to(&mut out, ImageFormat::Png).map_err(bad)?;
    }
    Ok(out.into_inner())
}
