//! Hostile source images, decoded as a request's sources are (`image_io`): metadata bombs are
//! read in bounded memory, truncated JPEGs are refused like truncated PNGs, and the EXIF
//! orientation is applied. Memory is measured by this test binary's allocator, per thread (the
//! decode runs on the test's own thread), so tests running side by side do not see each other.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::io::Write;

use scnerf_server::error::ApiError;
use scnerf_server::image_io::{decode_source, probe};
use scnerf_server::testing::png_with_chunks;

struct Counting;

thread_local! {
    static LIVE: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
}

fn count(delta: isize) {
    // `try_with`: a thread being torn down has no counters left, and needs none.
    let _ = LIVE.try_with(|live| {
        live.set(live.get() + delta);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(live.get())));
    });
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count(layout.size() as isize);
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        count(-(layout.size() as isize));
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count(new_size as isize - layout.size() as isize);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// `f`'s result and the most this thread allocated while it ran, above what it held before.
fn peak_during<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let start = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(start));
    let out = f();
    (out, (PEAK.with(Cell::get) - start) as usize)
}

/// What decoding an 80x64 source may take whatever its metadata: the image as stored, its
/// float copies, and the decoders' buffers (`scnerf_capture::images::HEADER_BYTES` at most).
const BOUND: usize = 8 << 20;

/// A zlib stream that inflates to `n` zero bytes.
fn zlib_zeros(n: usize) -> Vec<u8> {
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
    let block = vec![0u8; 1 << 20];
    for _ in 0..n >> 20 {
        z.write_all(&block).unwrap();
    }
    z.finish().unwrap()
}

fn plain_png(width: u32, height: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(width, height, |x, y| image::Rgb([x as u8, y as u8, 7]));
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png).unwrap();
    out
}

/// `png` read and decoded as a source: its size, and the most either took.
fn read_as_source(png: &[u8]) -> ((u32, u32), usize) {
    let ((header, decoded), peak) = peak_during(|| {
        let (_, w, h) = probe(png, "source_0").unwrap();
        let decoded = decode_source(png, "source_0", [0.0; 3], 80 * 64).unwrap();
        ((w, h), decoded)
    });
    assert_eq!(decoded.dim(), (header.1 as usize, header.0 as usize, 3));
    assert_eq!(decoded[[5, 9, 0]], 9.0 / 255.0, "the pixels are the image's");
    (header, peak)
}

/// A colour profile that inflates to 64 MiB (the probe's was 1 GiB from 1 MB: 0.5 GB per image
/// through the image crate's reader).
#[test]
fn a_colour_profile_bomb_is_skipped_unread() {
    let profile = [b"bomb\0\0".as_slice(), &zlib_zeros(64 << 20)].concat();
    let png = png_with_chunks(&plain_png(80, 64), [(b"iCCP", profile.as_slice())]);
    let (size, peak) = read_as_source(&png);
    assert_eq!(size, (80, 64));
    assert!(peak < BOUND, "{peak} bytes");
}

#[test]
fn compressed_text_bombs_are_skipped_unread() {
    let inflated = zlib_zeros(64 << 20);
    let ztxt = [b"Comment\0\0".as_slice(), &inflated].concat();
    let itxt = [b"Comment\0\x01\0\0\0".as_slice(), &inflated].concat();
    let png = png_with_chunks(&plain_png(80, 64), [(b"zTXt", ztxt.as_slice()), (b"iTXt", itxt.as_slice())]);
    let (size, peak) = read_as_source(&png);
    assert_eq!(size, (80, 64));
    assert!(peak < BOUND, "{peak} bytes");
}

/// A million tiny text chunks: each would be kept (two strings apiece) if text were read; with
/// the text skipped, nothing is kept however many there are.
#[test]
fn a_million_tiny_chunks_are_read_in_bounded_memory() {
    let chunk: &[u8] = b"k\0text";
    let png = png_with_chunks(&plain_png(80, 64), std::iter::repeat_n((b"tEXt", chunk), 1_000_000));
    let (size, peak) = read_as_source(&png);
    assert_eq!(size, (80, 64));
    assert!(peak < BOUND, "{peak} bytes");
}

fn jpeg(img: &image::RgbImage, exif: Option<Vec<u8>>) -> Vec<u8> {
    use image::ImageEncoder;
    let mut out = Vec::new();
    let mut encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95);
    if let Some(exif) = exif {
        encoder.set_exif_metadata(exif).unwrap();
    }
    encoder.write_image(img.as_raw(), img.width(), img.height(), image::ExtendedColorType::Rgb8).unwrap();
    out
}

#[test]
fn truncated_jpegs_are_refused_like_truncated_pngs() {
    let img = image::RgbImage::from_fn(96, 64, |x, y| image::Rgb([(x * 2) as u8, (y * 3) as u8, 90]));
    let whole = jpeg(&img, None);
    assert_eq!(decode_source(&whole, "source_1", [0.0; 3], 96 * 64).unwrap().dim(), (64, 96, 3));
    for percent in [10, 50, 90, 99] {
        let cut = &whole[..whole.len() * percent / 100];
        let err = decode_source(cut, "source_1", [0.0; 3], 96 * 64).unwrap_err();
        assert!(matches!(&err, ApiError::Malformed { field: Some(f), .. } if f == "source_1"), "{percent}%: {err:?}");
    }
    let png = plain_png(80, 64);
    let err = decode_source(&png[..png.len() / 2], "source_2", [0.0; 3], 80 * 64).unwrap_err();
    assert!(matches!(&err, ApiError::Malformed { field: Some(f), .. } if f == "source_2"), "{err:?}");
}

/// A little-endian EXIF (TIFF) block with one tag: Orientation = `value`.
fn exif_orientation(value: u16) -> Vec<u8> {
    let mut exif = b"II*\0\x08\0\0\0\x01\0".to_vec(); // header, first IFD at 8, one entry
    exif.extend_from_slice(&[0x12, 0x01, 3, 0, 1, 0, 0, 0]); // tag 0x0112, SHORT, count 1
    exif.extend_from_slice(&value.to_le_bytes());
    exif.extend_from_slice(&[0, 0, 0, 0, 0, 0]); // padding, no next IFD
    exif
}

/// A phone photo stored 96 wide and 64 high and tagged "rotate 90 clockwise" (6) is decoded as
/// it is shown: 64 wide and 96 high, its stored left column now its top row.
#[test]
fn the_exif_orientation_is_applied() {
    let stored =
        image::RgbImage::from_fn(96, 64, |x, _| if x < 8 { image::Rgb([250, 0, 0]) } else { image::Rgb([0, 0, 250]) });
    let rotated = jpeg(&stored, Some(exif_orientation(6)));
    let (_, width, height) = probe(&rotated, "source_0").unwrap();
    assert_eq!((width, height), (64, 96));
    let img = decode_source(&rotated, "source_0", [0.0; 3], 96 * 64).unwrap();
    assert_eq!(img.dim(), (96, 64, 3));
    let red = |y: usize, x: usize| img[[y, x, 0]] > 0.8 && img[[y, x, 2]] < 0.2;
    assert!(red(2, 0) && red(2, 63), "the stored left column is the top rows");
    assert!(!red(40, 32) && !red(95, 0));
    // Untagged (or tagged 1), the same bytes are taken as stored.
    let plain = decode_source(&jpeg(&stored, Some(exif_orientation(1))), "source_0", [0.0; 3], 96 * 64).unwrap();
    assert_eq!(plain.dim(), (64, 96, 3));
}
