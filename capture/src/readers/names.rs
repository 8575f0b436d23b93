//! File names in captures: which are images, the set folders, how frames name their images, and
//! the natural order of names.

use std::cmp::Ordering;
use std::path::{Path, PathBuf};

use crate::error::Result;
use crate::files::Files;

/// Extensions of the images the readers use, in any case (`IMG_0001.JPG`, `a.Png`): the Python
/// loaders' (`exporter/scnerf_export/data/scene.py::IMAGE_EXTENSIONS`) and the server decodes.
pub const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// Whether `path` names an image the readers use (by its extension).
pub fn has_image_extension(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| IMAGE_EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)))
}

/// The image files of a folder, sorted by name: files with an image extension whose name does not
/// start with `.` (`._IMG_0001.JPG` is macOS's metadata). The LLFF reader's images and an image
/// set's first image; `llff.py::_list_images` and the Python client's `captures.is_image_name`,
/// held together by tests/fixtures/rules/image_files.json.
pub fn list_images(fs: &dyn Files, dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = fs
        .list(dir)?
        .into_iter()
        .filter(|p| fs.is_file(p) && has_image_extension(p))
        .filter(|p| !p.file_name().is_some_and(|n| n.to_string_lossy().starts_with('.')))
        .collect();
    files.sort();
    Ok(files)
}

/// The folder of the set `factor` under a capture's root: `images` for 1, `images_N` otherwise.
pub fn folder_name(factor: u32) -> String {
    if factor <= 1 {
        "images".to_string()
    } else {
        format!("images_{factor}")
    }
}

/// The image a transforms.json `file_path` refers to: the path itself, else with one of the image
/// extensions appended (Blender files omit it). `data/dataparsers/transforms.py::_resolve_image`.
pub(super) fn resolve_image(fs: &dyn Files, base: &Path, file_path: &str) -> Option<PathBuf> {
    let p = base.join(file_path);
    if fs.is_file(&p) {
        return Some(p);
    }
    if has_image_extension(&p) {
        return None;
    }
    let lower = IMAGE_EXTENSIONS.iter().map(|ext| ext.to_string());
    let upper = IMAGE_EXTENSIONS.iter().map(|ext| ext.to_ascii_uppercase());
    lower.chain(upper).map(|ext| PathBuf::from(format!("{}.{ext}", p.display()))).find(|q| fs.is_file(q))
}

/// One warning for all frames whose image is missing, instead of one per frame.
pub(super) fn skipped_warning(files: &str, skipped: usize, listed: usize) -> Option<String> {
    (skipped > 0).then(|| format!("{files}: {skipped} of {listed} frames have no image file; skipped"))
}

/// `path` without its extension, as Python's `os.path.splitext(path)[0]`.
pub(super) fn without_extension(path: &str) -> String {
    Path::new(path).with_extension("").to_string_lossy().into_owned()
}

/// Python's `Path(path).name`: the last component.
pub(super) fn base_name(path: &str) -> String {
    Path::new(path).file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()
}

/// Natural order ("img2" before "img10"), `data/scene.py::natural_key`: runs of digits compare by
/// value, everything else by code point.
pub fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (ka, kb) = (natural_key(a), natural_key(b));
    for (x, y) in ka.iter().zip(&kb) {
        let ord = match (x, y) {
            (Chunk::Number(x), Chunk::Number(y)) => {
                let (x, y) = (x.trim_start_matches('0'), y.trim_start_matches('0'));
                x.len().cmp(&y.len()).then_with(|| x.cmp(y))
            }
            (Chunk::Text(x), Chunk::Text(y)) => x.cmp(y),
            // never: both keys start with text and alternate, so kinds always line up
            _ => Ordering::Equal,
        };
        if ord != Ordering::Equal {
            return ord;
        }
    }
    ka.len().cmp(&kb.len())
}

enum Chunk<'a> {
    Text(&'a str),
    Number(&'a str),
}

/// Python's `re.split(r"(\d+)", s)`: text, digits, text, ... (the first and last text possibly
/// empty).
fn natural_key(s: &str) -> Vec<Chunk<'_>> {
    let mut out = Vec::new();
    let mut start = 0;
    let bytes = s.as_bytes();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i].is_ascii_digit() {
            let j = i + bytes[i..].iter().take_while(|b| b.is_ascii_digit()).count();
            out.push(Chunk::Text(&s[start..i]));
            out.push(Chunk::Number(&s[i..j]));
            start = j;
            i = j;
        } else {
            i += 1;
        }
    }
    out.push(Chunk::Text(&s[start..]));
    out
}
