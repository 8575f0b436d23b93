//! Image decoding and encoding. These are CPU-bound: callers run them on `spawn_blocking`.

use std::io::Cursor;

use image::{DynamicImage, ImageFormat};
use ndarray::{s, Array3, ArrayView1};
use scnerf_capture::images::{self, ImageError};

use crate::error::ApiError;

/// Reads only the header: format and size as displayed (`scnerf_capture::images`: bounded
/// memory whatever the file holds). Lets us refuse oversized images (decompression bombs) before
/// allocating anything.
pub fn probe(bytes: &[u8], field: &str) -> Result<(ImageFormat, u32, u32), ApiError> {
    let header = images::read_header(Cursor::new(bytes)).map_err(|e| image_error(e, field))?;
    Ok((header.format, header.width, header.height))
}

fn image_error(e: ImageError, field: &str) -> ApiError {
    match e {
        ImageError::Unsupported(message) => ApiError::UnsupportedMediaType { field: Some(field.to_string()), message },
        other => ApiError::malformed(field.to_string(), format!("cannot read image: {other}")),
    }
}

/// Decodes a PNG/JPEG source view to RGB in [0, 1], (H, W, 3), oriented as its EXIF says;
/// alpha is composited on `background` (`rgb·a + background·(1 − a)`), as the network never sees
/// transparency.
pub fn decode_source(
    bytes: &[u8],
    field: &str,
    background: [f32; 3],
    max_pixels: u64,
) -> Result<Array3<f32>, ApiError> {
    let (_, w, h) = probe(bytes, field)?;
    if u64::from(w) * u64::from(h) > max_pixels {
        return Err(ApiError::invalid(
            field.to_string(),
            format!("image of {w}x{h} exceeds the limit of {max_pixels} pixels"),
        ));
    }
    let image = images::decode(bytes).map_err(|e| image_error(e, field))?;
    Ok(to_rgb_on_background(image, background))
}

fn to_rgb_on_background(image: DynamicImage, background: [f32; 3]) -> Array3<f32> {
    let (w, h) = (image.width() as usize, image.height() as usize);
    // The decoder's buffers hold exactly h·w pixels of 3 or 4 channels.
    if !image.color().has_alpha() {
        return Array3::from_shape_vec((h, w, 3), image.into_rgb32f().into_raw()).expect("h·w RGB pixels");
    }
    let rgba = Array3::from_shape_vec((h, w, 4), image.into_rgba32f().into_raw()).expect("h·w RGBA pixels");
    let alpha = rgba.slice(s![.., .., 3..]);
    let background = ArrayView1::from(&background);
    &rgba.slice(s![.., .., ..3]) * &alpha + &(&background * &(1.0 - &alpha))
}

/// Encodes 8-bit RGB as PNG.
pub fn encode_png(width: u32, height: u32, rgb: &[u8]) -> Result<Vec<u8>, ApiError> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Adaptive)
        .write_image(rgb, width, height, image::ExtendedColorType::Rgb8)
        .map_err(|e| ApiError::Internal(format!("PNG encoding failed: {e}")))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png(img: DynamicImage) -> Vec<u8> {
        let mut out = Vec::new();
        img.write_to(&mut Cursor::new(&mut out), ImageFormat::Png).unwrap();
        out
    }

    #[test]
    fn alpha_is_composited_on_background() {
        let mut rgba = image::RgbaImage::new(2, 1);
        rgba.put_pixel(0, 0, image::Rgba([255, 0, 0, 255]));
        rgba.put_pixel(1, 0, image::Rgba([255, 0, 0, 0]));
        let img = decode_source(&png(DynamicImage::ImageRgba8(rgba)), "source_0", [0.0, 1.0, 0.5], 100).unwrap();
        assert_eq!(img, ndarray::arr3(&[[[1.0, 0.0, 0.0], [0.0, 1.0, 0.5]]]));
    }

    #[test]
    fn rgb_and_gray_decode() {
        let rgb = image::RgbImage::from_pixel(3, 2, image::Rgb([0, 51, 255]));
        let img = decode_source(&png(DynamicImage::ImageRgb8(rgb)), "s", [0.0; 3], 100).unwrap();
        assert_eq!(img.dim(), (2, 3, 3));
        assert_eq!(img.slice(s![0, 0, ..]), ndarray::aview1(&[0.0, 0.2, 1.0]));
        let gray = image::GrayImage::from_pixel(1, 1, image::Luma([255]));
        assert_eq!(
            decode_source(&png(DynamicImage::ImageLuma8(gray)), "s", [0.0; 3], 100).unwrap(),
            Array3::<f32>::ones((1, 1, 3))
        );
    }

    #[test]
    fn refuses_garbage_unknown_and_oversized() {
        assert!(matches!(decode_source(b"\x89PNG\r\n\x1a\nbroken", "source_1", [0.0; 3], 100),
            Err(ApiError::Malformed { field: Some(f), .. }) if f == "source_1"));
        assert!(matches!(
            decode_source(b"hello", "source_1", [0.0; 3], 100),
            Err(ApiError::UnsupportedMediaType { .. })
        ));
        let big = png(DynamicImage::ImageRgb8(image::RgbImage::new(20, 20)));
        assert!(matches!(decode_source(&big, "source_2", [0.0; 3], 399), Err(ApiError::Invalid { .. })));
    }

    #[test]
    fn png_roundtrip() {
        let bytes = encode_png(2, 1, &[1, 2, 3, 4, 5, 6]).unwrap();
        let back = image::load_from_memory(&bytes).unwrap().into_rgb8();
        assert_eq!(back.into_raw(), vec![1, 2, 3, 4, 5, 6]);
    }
}

#[cfg(test)]
mod bomb_tests {
    use super::*;

    #[test]
    fn a_huge_header_is_read_and_refused() {
        let bomb = crate::testing::png_header(100_000, 100_000);
        assert_eq!(probe(&bomb, "source_0").unwrap(), (ImageFormat::Png, 100_000, 100_000));
        let err = decode_source(&bomb, "source_0", [0.0; 3], 1024 * 1024).unwrap_err();
        assert!(matches!(&err, ApiError::Invalid { field, .. } if field == "source_0"), "{err:?}");
        assert!(err.to_string().contains("100000x100000"), "{err}");
    }

    #[test]
    fn a_tiny_valid_header_with_missing_data_is_malformed() {
        let truncated = crate::testing::png_header(1, 1);
        assert_eq!(probe(&truncated, "s").unwrap().1, 1);
        // The header is fine; the decoder then finds too little image data.
        let r = decode_source(&truncated, "s", [0.0; 3], 100);
        assert!(r.is_ok() || matches!(r, Err(ApiError::Malformed { .. })), "{r:?}");
    }
}
