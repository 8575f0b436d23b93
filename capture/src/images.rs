//! Reading the photos of a capture or a request: PNG and JPEG, their header alone (format and
//! size) or the whole image, the same way in the client and the server.
//!
//! Both are built for bytes from anyone:
//! - a header read allocates at most [`HEADER_BYTES`]: a PNG's colour profile (iCCP) and text
//!   chunks (tEXt, zTXt, iTXt), which can inflate to gigabytes from a few bytes, are skipped
//!   unread (nothing here uses them), as are unknown chunks, whatever their count;
//! - decoding is strict: a truncated or corrupt JPEG is an error, as a PNG is, instead of an
//!   image with its missing rows filled grey;
//! - the EXIF orientation (a JPEG's APP1, a PNG's eXIf) is applied, as image viewers do: a phone
//!   photo tagged "rotate 90" is its rotated self, and its header's size is the rotated size.

use std::io::{BufRead, Cursor, Seek};

use image::metadata::Orientation;
use image::{DynamicImage, ImageBuffer, ImageFormat, Pixel};
use zune_core::bytestream::{ZByteReaderTrait, ZCursor};
use zune_core::colorspace::ColorSpace;
use zune_core::options::DecoderOptions;

/// The most a header read allocates: a PNG's chunks before its image data that are kept (the
/// eXIf chunk, the palette), or, when decoding, its line buffers. Real metadata is kilobytes.
pub const HEADER_BYTES: usize = 4 << 20;

/// Why an image cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// Not PNG or JPEG.
    #[error("{0}")]
    Unsupported(String),
    /// A PNG or JPEG that cannot be read: truncated, corrupt, or metadata past [`HEADER_BYTES`].
    #[error("{0}")]
    Malformed(String),
    /// The file could not be read (on disk).
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// An image's format and its size as displayed (its EXIF orientation applied).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    pub format: ImageFormat,
    pub width: u32,
    pub height: u32,
    orientation: Orientation,
}

impl Header {
    fn new(format: ImageFormat, (width, height): (u32, u32), orientation: Orientation) -> Header {
        let swaps = matches!(
            orientation,
            Orientation::Rotate90 | Orientation::Rotate270 | Orientation::Rotate90FlipH | Orientation::Rotate270FlipH
        );
        let (width, height) = if swaps { (height, width) } else { (width, height) };
        Header { format, width, height, orientation }
    }
}

/// The header of the image `reader` starts with.
pub fn read_header<R: BufRead + Seek>(mut reader: R) -> Result<Header, ImageError> {
    match format(reader.fill_buf()?)? {
        ImageFormat::Png => {
            let decoder = png_decoder(reader).read_info().map_err(png_error)?;
            let info = decoder.info();
            Ok(Header::new(ImageFormat::Png, info.size(), png_orientation(info)))
        }
        _ => {
            let mut decoder = jpeg_decoder(reader);
            decoder.decode_headers().map_err(jpeg_error)?;
            jpeg_header(&decoder)
        }
    }
}

/// Decodes a whole image, oriented as [`Header`] says, into 8 or 16 bits per channel as stored.
pub fn decode(bytes: &[u8]) -> Result<DynamicImage, ImageError> {
    let (mut image, orientation) = match format(bytes)? {
        ImageFormat::Png => decode_png(bytes)?,
        _ => decode_jpeg(bytes)?,
    };
    image.apply_orientation(orientation);
    Ok(image)
}

fn format(start: &[u8]) -> Result<ImageFormat, ImageError> {
    match image::guess_format(start) {
        Ok(f @ (ImageFormat::Png | ImageFormat::Jpeg)) => Ok(f),
        Ok(other) => Err(ImageError::Unsupported(format!("image format {other:?} is not supported (PNG or JPEG)"))),
        Err(_) if start.is_empty() => Err(ImageError::Malformed("the image is empty".into())),
        Err(_) => Err(ImageError::Unsupported("unrecognised image data (PNG or JPEG expected)".into())),
    }
}

fn png_decoder<R: BufRead + Seek>(reader: R) -> png::Decoder<R> {
    let mut decoder = png::Decoder::new_with_limits(reader, png::Limits { bytes: HEADER_BYTES });
    decoder.set_ignore_iccp_chunk(true);
    decoder.set_ignore_text_chunk(true);
    decoder
}

fn png_orientation(info: &png::Info) -> Orientation {
    info.exif_metadata.as_deref().and_then(Orientation::from_exif_chunk).unwrap_or(Orientation::NoTransforms)
}

fn png_error(e: png::DecodingError) -> ImageError {
    match e {
        png::DecodingError::IoError(e) if e.kind() != std::io::ErrorKind::UnexpectedEof => ImageError::Io(e),
        png::DecodingError::LimitsExceeded => {
            ImageError::Malformed(format!("the PNG's chunks before its image data exceed {HEADER_BYTES} bytes"))
        }
        other => ImageError::Malformed(format!("invalid PNG: {other}")),
    }
}

/// A PNG as stored (palettes and low bit depths expanded to 8 bits, 16 bits kept).
fn decode_png(bytes: &[u8]) -> Result<(DynamicImage, Orientation), ImageError> {
    let mut decoder = png_decoder(Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(png_error)?;
    let orientation = png_orientation(reader.info());
    let size = reader.output_buffer_size().ok_or_else(|| ImageError::Malformed("the PNG is too large".into()))?;
    let mut buffer = vec![0; size];
    let frame = reader.next_frame(&mut buffer).map_err(png_error)?;
    buffer.truncate(frame.buffer_size());
    let (w, h) = (frame.width, frame.height);
    use png::{BitDepth, ColorType};
    let image = match (frame.color_type, frame.bit_depth) {
        (ColorType::Grayscale, BitDepth::Eight) => DynamicImage::ImageLuma8(sized(w, h, buffer)?),
        (ColorType::GrayscaleAlpha, BitDepth::Eight) => DynamicImage::ImageLumaA8(sized(w, h, buffer)?),
        (ColorType::Rgb, BitDepth::Eight) => DynamicImage::ImageRgb8(sized(w, h, buffer)?),
        (ColorType::Rgba, BitDepth::Eight) => DynamicImage::ImageRgba8(sized(w, h, buffer)?),
        (color, BitDepth::Sixteen) => {
            let wide: Vec<u16> = buffer.chunks_exact(2).map(|b| u16::from_be_bytes([b[0], b[1]])).collect();
            match color {
                ColorType::Grayscale => DynamicImage::ImageLuma16(sized(w, h, wide)?),
                ColorType::GrayscaleAlpha => DynamicImage::ImageLumaA16(sized(w, h, wide)?),
                ColorType::Rgb => DynamicImage::ImageRgb16(sized(w, h, wide)?),
                _ => DynamicImage::ImageRgba16(sized(w, h, wide)?),
            }
        }
        (color, depth) => {
            return Err(ImageError::Malformed(format!("unexpected PNG output {color:?} at {depth:?} bits")));
        }
    };
    Ok((image, orientation))
}

fn jpeg_decoder<T: ZByteReaderTrait>(reader: T) -> zune_jpeg::JpegDecoder<T> {
    // Sizes are the caller's to limit (it knows its pixel limit); JPEG's own limit is 65535.
    let options = DecoderOptions::default().set_strict_mode(true).set_max_width(65535).set_max_height(65535);
    zune_jpeg::JpegDecoder::new_with_options(reader, options)
}

fn jpeg_header<T: ZByteReaderTrait>(decoder: &zune_jpeg::JpegDecoder<T>) -> Result<Header, ImageError> {
    let (w, h) = decoder.dimensions().ok_or_else(|| ImageError::Malformed("invalid JPEG: no size".into()))?;
    let orientation =
        decoder.exif().and_then(|exif| Orientation::from_exif_chunk(exif)).unwrap_or(Orientation::NoTransforms);
    // At most 65535 per side (the decoder's limits above).
    Ok(Header::new(ImageFormat::Jpeg, (w as u32, h as u32), orientation))
}

fn jpeg_error(e: zune_jpeg::errors::DecodeErrors) -> ImageError {
    ImageError::Malformed(format!("invalid JPEG: {e}"))
}

/// A JPEG as 8-bit RGB, or gray when it is gray.
fn decode_jpeg(bytes: &[u8]) -> Result<(DynamicImage, Orientation), ImageError> {
    let mut decoder = jpeg_decoder(ZCursor::new(bytes));
    decoder.decode_headers().map_err(jpeg_error)?;
    let header = jpeg_header(&decoder)?;
    let gray = decoder.input_colorspace() == Some(ColorSpace::Luma);
    let out = if gray { ColorSpace::Luma } else { ColorSpace::RGB };
    decoder.set_options(decoder.options().jpeg_set_out_colorspace(out));
    let pixels = decoder.decode().map_err(jpeg_error)?;
    let (w, h) = decoder.dimensions().map(|(w, h)| (w as u32, h as u32)).unwrap_or_default();
    let image = match gray {
        true => DynamicImage::ImageLuma8(sized(w, h, pixels)?),
        false => DynamicImage::ImageRgb8(sized(w, h, pixels)?),
    };
    Ok((image, header.orientation))
}

/// Decoded samples as a `w` x `h` image of pixels `P`.
fn sized<P: Pixel>(w: u32, h: u32, samples: Vec<P::Subpixel>) -> Result<ImageBuffer<P, Vec<P::Subpixel>>, ImageError> {
    ImageBuffer::from_raw(w, h, samples)
        .ok_or_else(|| ImageError::Malformed("the decoded image data does not match the image's size".into()))
}
