//! What a client sends of a capture folder to `POST /v1/captures`, decided from the folder's
//! listing: which files are capture files, which image set goes, and the size that each image
//! over the server's source limit is resized to first. The server answers it at `POST
//! /v1/captures/plan`, so the viewer and the Python client follow these rules instead of copies
//! of them. They are the readers' own, applied to file names: images by their extension in any
//! case ([`has_image_extension`]), the format by its files' names ([`detect_by_names`]), the sets
//! and the pick ([`crate::image_sets`]), the fit to the limit ([`fitted_size`]).
//!
//! The pick needs the size of each set's first image, and a resize the size of the images
//! resized: a plan is made with the size of the first image (in name order) of every folder
//! holding images, one header read per folder. A listing that lacks one of them gets
//! [`Outcome::SizesNeeded`], and the client asks again with those sizes. An image whose own size
//! is given is planned by it; any other by its folder's first.

use std::borrow::Cow;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Component, Path, PathBuf};

use crate::error::{Error, Result};
use crate::files::{Files, MemoryFiles};
use crate::image_sets::{first_image, image_sets, pick, Pick, Picked};
use crate::readers::{detect_by_names, has_image_extension, Format, IMAGE_EXTENSIONS};
use crate::upload::{fit_note, fitted_size};

/// Extensions of the camera and model files the readers parse, in any case: transforms JSON,
/// LLFF's `poses_bounds.npy`, COLMAP's text and binary models, DTU's camera text files.
pub const CAMERA_EXTENSIONS: [&str; 4] = ["json", "npy", "txt", "bin"];

/// Whether a path inside a capture is hidden: one of its names starts with `.` (`.DS_Store`,
/// `.thumbnails/a.png`). Hidden files are never capture files.
pub fn is_hidden(path: &Path) -> bool {
    path.components().any(|c| matches!(c, Component::Normal(name) if name.to_string_lossy().starts_with('.')))
}

/// Whether a capture needs the file at `path`: an image or a camera file, not hidden.
pub fn is_capture_file(path: &Path) -> bool {
    let camera = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| CAMERA_EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)));
    !is_hidden(path) && (camera || has_image_extension(path))
}

/// Why a listed file is not sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LeftOut {
    /// One of its names starts with `.`.
    Hidden,
    /// Neither an image nor a camera file.
    NotCaptureFile,
    /// In the folder of an image set other than the one picked.
    OtherImageSet,
}

/// An image resized before it is sent: from the size the plan takes it to have, to the size that
/// fits the limit. An image of another size is sent as it is (the server fits it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Resize {
    pub from: (u32, u32),
    pub to: (u32, u32),
}

/// A file to send: its index in the listing, and its resize if it is an image over the limit.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ToSend {
    pub index: usize,
    pub resize: Option<Resize>,
}

/// What to send of a capture.
#[derive(Debug, Clone)]
pub struct Plan {
    /// The format the names say; `None` for a single `transforms.json` (Blender or nerfstudio:
    /// its content tells, which `POST /v1/captures` reads).
    pub format: Option<Format>,
    /// In listing order.
    pub send: Vec<ToSend>,
    /// In listing order, by index.
    pub left_out: Vec<(usize, LeftOut)>,
    /// The image set sent, and every set of the capture; `None` when it keeps no sets.
    pub picked: Option<Picked>,
    /// What to tell the user, one line each.
    pub notes: Vec<String>,
}

/// A plan, or the images whose sizes it needs first (indices into the listing, in order).
#[derive(Debug, Clone)]
pub enum Outcome {
    SizesNeeded(Vec<usize>),
    Planned(Plan),
}

/// A listing the plan cannot be made of, naming what is wrong with it.
#[derive(Debug, thiserror::Error)]
pub enum PlanError {
    /// The listing's `index`th file.
    #[error("{message}")]
    File { index: usize, message: String },
    /// The `index`th size given.
    #[error("{message}")]
    Size { index: usize, message: String },
    /// The listing as a whole: empty, or of no format the readers know.
    #[error("{0}")]
    Listing(String),
    /// A downscale factor the capture has no set for ([`Error::UnknownImageSet`]).
    #[error("{0}")]
    Downscale(Error),
}

/// The plan for a folder whose files are `files` (paths relative to it, `/`-separated) with the
/// sizes (width, height as displayed) of some images, under `rule` and the source limit
/// `max_pixels`.
pub fn plan(files: &[&str], sizes: &[(&str, u32, u32)], rule: Pick, max_pixels: u64) -> Result<Outcome, PlanError> {
    if files.is_empty() {
        return Err(PlanError::Listing("no files: list every file of the capture folder".into()));
    }
    let listing = Listing::new(files)?;
    if listing.index.is_empty() {
        return Err(PlanError::Listing(format!(
            "none of the {} files is an image (.{}) or a camera file (.{})",
            files.len(),
            IMAGE_EXTENSIONS.join(" ."),
            CAMERA_EXTENSIONS.join(" .")
        )));
    }
    let sizes = listing.sizes(sizes)?;
    let root = Path::new("");
    let dataset = |e: Error| match e {
        Error::Dataset { path, message } if path.as_os_str().is_empty() => PlanError::Listing(message),
        other => PlanError::Listing(other.to_string()),
    };
    let format = detect_by_names(&listing, root).map_err(dataset)?;
    // The first image of every folder holding images: the sizes a plan is made with.
    let folders: BTreeSet<&Path> = listing.images().filter_map(|p| p.parent()).collect();
    let mut firsts = BTreeMap::new();
    let mut needed = Vec::new();
    for folder in folders {
        let Some(first) = first_image(&listing, folder).map_err(dataset)? else { continue };
        match sizes.get(&first) {
            Some(&size) => {
                firsts.insert(folder.to_path_buf(), size);
            }
            None => needed.push(listing.index[&first]),
        }
    }
    if !needed.is_empty() {
        needed.sort_unstable();
        return Ok(Outcome::SizesNeeded(needed));
    }
    // A single transforms.json keeps its images as nerfstudio does (Blender's own renders keep no
    // images_N/ beside images/).
    let listed = Listed { listing: &listing, sizes: &sizes };
    let sets = image_sets(&listed, root, format.unwrap_or(Format::Nerfstudio)).map_err(dataset)?;
    let picked = pick(&sets, rule).map_err(PlanError::Downscale)?;
    let others: Vec<&Path> = match &picked {
        Some(p) => p.sets.iter().filter(|s| s.factor != p.set.factor).map(|s| s.folder.as_path()).collect(),
        None => Vec::new(),
    };

    let mut send = Vec::new();
    let mut left_out = listing.left_out.clone();
    for (path, &index) in &listing.index {
        if others.iter().any(|folder| path.starts_with(folder)) {
            left_out.push((index, LeftOut::OtherImageSet));
            continue;
        }
        let size = match has_image_extension(path) {
            true => sizes.get(path).or_else(|| firsts.get(path.parent()?)).copied(),
            false => None,
        };
        let resize = size.and_then(|from| Some(Resize { from, to: fitted_size(from.0, from.1, max_pixels)? }));
        send.push(ToSend { index, resize });
    }
    send.sort_by_key(|s| s.index);
    left_out.sort_by_key(|&(i, _)| i);

    let mut notes: Vec<String> = picked.as_ref().and_then(|p| set_note(p, rule, max_pixels)).into_iter().collect();
    let resized: Vec<Resize> = send.iter().filter_map(|s| s.resize).collect();
    if let Some(first) = resized.first() {
        notes.push(fit_note(resized.len(), first.from, first.to, max_pixels));
    }
    let other: Vec<&str> =
        left_out.iter().filter(|(_, why)| *why == LeftOut::NotCaptureFile).map(|&(i, _)| files[i]).collect();
    if !other.is_empty() {
        let more = if other.len() > 3 { format!(" and {} more", other.len() - 3) } else { String::new() };
        notes.push(format!(
            "not sent: {}{more}, neither images (.{}) nor camera files (.{})",
            other[..other.len().min(3)].join(", "),
            IMAGE_EXTENSIONS.join(" ."),
            CAMERA_EXTENSIONS.join(" ."),
        ));
    }
    Ok(Outcome::Planned(Plan { format, send, left_out, picked, notes }))
}

/// What to say of the set picked: which of which, and why (`scnerf render` says the same).
fn set_note(picked: &Picked, rule: Pick, max_pixels: u64) -> Option<String> {
    let describe = picked.describe();
    match rule {
        Pick::Downscale(n) => Some(format!("image set: {describe} (downscale {n})")),
        Pick::Fit { .. } if picked.sets.len() < 2 => None,
        Pick::Fit { .. } if picked.fits => Some(format!(
            "image set: {describe}: the largest within the server's limit of {max_pixels} pixels per source view \
             (downscale N picks another)"
        )),
        Pick::Fit { .. } => Some(format!(
            "image set: {describe}: the smallest; none is within the server's limit of {max_pixels} pixels per \
             source view"
        )),
    }
}

/// A listing: its capture files (as files of no content, for the readers' rules about names) by
/// their normal paths, with their indices; what is left out of it at once.
struct Listing {
    files: MemoryFiles,
    index: BTreeMap<PathBuf, usize>,
    left_out: Vec<(usize, LeftOut)>,
    /// Every file's normal path, capture file or not, with its index.
    all: BTreeMap<PathBuf, usize>,
}

impl Listing {
    fn new(paths: &[&str]) -> Result<Listing, PlanError> {
        let mut listing =
            Listing { files: MemoryFiles::new(), index: BTreeMap::new(), left_out: Vec::new(), all: BTreeMap::new() };
        for (index, &path) in paths.iter().enumerate() {
            let message = |m: String| PlanError::File { index, message: m };
            let normal = MemoryFiles::normal_path(Path::new(path))
                .filter(|p| !p.as_os_str().is_empty())
                .ok_or_else(|| message(format!("{path:?} is not a relative path inside the capture folder")))?;
            if let Some(&before) = listing.all.get(&normal) {
                return Err(message(format!("{path:?} is listed twice (files[{before}] is the same file)")));
            }
            listing.all.insert(normal.clone(), index);
            if is_hidden(&normal) {
                listing.left_out.push((index, LeftOut::Hidden));
            } else if !is_capture_file(&normal) {
                listing.left_out.push((index, LeftOut::NotCaptureFile));
            } else {
                listing.files.insert(path, Vec::new());
                listing.index.insert(normal, index);
            }
        }
        Ok(listing)
    }

    /// The capture's images, by their normal paths.
    fn images(&self) -> impl Iterator<Item = &Path> {
        self.index.keys().map(PathBuf::as_path).filter(|p| has_image_extension(p))
    }

    /// The sizes given, by normal path: each of a listed image, given once, of at least 1x1.
    fn sizes(&self, sizes: &[(&str, u32, u32)]) -> Result<BTreeMap<PathBuf, (u32, u32)>, PlanError> {
        let mut out = BTreeMap::new();
        for (index, &(path, width, height)) in sizes.iter().enumerate() {
            let message = |m: String| PlanError::Size { index, message: m };
            let normal = MemoryFiles::normal_path(Path::new(path)).unwrap_or_default();
            if !self.all.contains_key(&normal) {
                return Err(message(format!("{path:?} is not in `files`")));
            }
            if !self.index.contains_key(&normal) || !has_image_extension(&normal) {
                return Err(message(format!(
                    "{path:?} is not an image of the capture (hidden, or not .png .jpg .jpeg)"
                )));
            }
            if width == 0 || height == 0 {
                return Err(message(format!("{path:?}: an image of {width}x{height} has no pixels")));
            }
            if out.insert(normal, (width, height)).is_some() {
                return Err(message(format!("{path:?}: its size is given twice")));
            }
        }
        Ok(out)
    }
}

/// The names of a listing, read as the readers read a folder. Only names and the sizes given are
/// there: reading a file is an error.
impl Files for Listing {
    fn is_file(&self, path: &Path) -> bool {
        self.files.is_file(path)
    }

    fn is_dir(&self, path: &Path) -> bool {
        self.files.is_dir(path)
    }

    fn read(&self, path: &Path) -> Result<Cow<'_, [u8]>> {
        Err(Error::dataset(path, "only the name of a listed file is known"))
    }

    fn list(&self, dir: &Path) -> Result<Vec<PathBuf>> {
        self.files.list(dir)
    }
}

/// A listing with the sizes given: [`image_sets`] reads each set's size from its first image.
struct Listed<'a> {
    listing: &'a Listing,
    sizes: &'a BTreeMap<PathBuf, (u32, u32)>,
}

impl Files for Listed<'_> {
    fn is_file(&self, path: &Path) -> bool {
        self.listing.is_file(path)
    }

    fn is_dir(&self, path: &Path) -> bool {
        self.listing.is_dir(path)
    }

    fn read(&self, path: &Path) -> Result<Cow<'_, [u8]>> {
        self.listing.read(path)
    }

    fn list(&self, dir: &Path) -> Result<Vec<PathBuf>> {
        self.listing.list(dir)
    }

    fn image_size(&self, path: &Path) -> Result<(u32, u32)> {
        let normal = MemoryFiles::normal_path(path).unwrap_or_default();
        self.sizes.get(&normal).copied().ok_or_else(|| Error::dataset(path, "the image's size is not given"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FIT: Pick = Pick::Fit { max_pixels: 1 << 20 };

    fn planned(files: &[&str], sizes: &[(&str, u32, u32)], rule: Pick) -> Plan {
        match plan(files, sizes, rule, 1 << 20).unwrap() {
            Outcome::Planned(p) => p,
            Outcome::SizesNeeded(n) => panic!("sizes needed: {n:?}"),
        }
    }

    fn sent<'a>(plan: &Plan, files: &[&'a str]) -> Vec<&'a str> {
        plan.send.iter().map(|s| files[s.index]).collect()
    }

    #[test]
    fn capture_files_are_images_and_camera_files_in_any_case_never_hidden() {
        for yes in ["a.png", "IMG.Png", "b.JPG", "c.jpeg", "sparse/0/cameras.BIN", "poses_bounds.npy", "t.Json"] {
            assert!(is_capture_file(Path::new(yes)), "{yes}");
        }
        for no in [".DS_Store", ".a.png", "images/.b.jpg", ".thumbs/c.png", "notes.md", "clip.mp4", "png"] {
            assert!(!is_capture_file(Path::new(no)), "{no}");
        }
    }

    #[test]
    fn a_listing_without_the_first_images_sizes_gets_asked_for_them() {
        let files = ["poses_bounds.npy", "images/b.JPG", "images/a.jpg", "images_4/a.png", "images_4/.x.png"];
        let needed = match plan(&files, &[], FIT, 1 << 20).unwrap() {
            Outcome::SizesNeeded(n) => n,
            Outcome::Planned(_) => panic!("planned without sizes"),
        };
        assert_eq!(needed, [2, 3], "the first image of each folder, hidden ones left out");
    }

    #[test]
    fn the_largest_set_that_fits_is_sent_and_the_others_left_out() {
        let files = ["poses_bounds.npy", "images/a.JPG", "images_4/a.Png", "images_8/a.png", ".DS_Store", "x.md"];
        let sizes = [("images/a.JPG", 4032, 3024), ("images_4/a.Png", 1008, 756), ("images_8/a.png", 504, 378)];
        let plan = planned(&files, &sizes, FIT);
        assert_eq!(plan.format, Some(Format::Llff));
        assert_eq!(sent(&plan, &files), ["poses_bounds.npy", "images_4/a.Png"]);
        assert!(plan.send.iter().all(|s| s.resize.is_none()));
        let why: Vec<(usize, LeftOut)> = plan.left_out.clone();
        assert_eq!(
            why,
            [
                (1, LeftOut::OtherImageSet),
                (3, LeftOut::OtherImageSet),
                (4, LeftOut::Hidden),
                (5, LeftOut::NotCaptureFile)
            ]
        );
        assert_eq!(plan.picked.as_ref().unwrap().set.factor, 4);
        assert!(plan.notes[0].starts_with("image set: images_4 (1008x756) of images (4032x3024)"), "{:?}", plan.notes);
        assert!(plan.notes[1].starts_with("not sent: x.md, neither images"), "{:?}", plan.notes);
        // downscale names the set
        let eight = planned(&files, &sizes, Pick::Downscale(8));
        assert_eq!(sent(&eight, &files), ["poses_bounds.npy", "images_8/a.png"]);
        assert!(matches!(plan_err(&files, &sizes, Pick::Downscale(2)), PlanError::Downscale(_)));
    }

    fn plan_err(files: &[&str], sizes: &[(&str, u32, u32)], rule: Pick) -> PlanError {
        plan(files, sizes, rule, 1 << 20).unwrap_err()
    }

    #[test]
    fn images_over_the_limit_are_resized_as_fit_to_limit_does() {
        // no set fits: the smallest, each image resized by its own size if given, else its folder's first
        let files = ["transforms.json", "images/0.jpg", "images/1.jpg", "images/2.jpg", "images_1/0.jpg"];
        let sizes = [("images/0.jpg", 2048, 1536), ("images/2.jpg", 1536, 2048), ("images_1/0.jpg", 800, 600)];
        let plan = planned(&files, &sizes, FIT);
        assert_eq!(plan.format, None, "transforms.json: nerfstudio or Blender");
        let resizes: Vec<Option<Resize>> = plan.send.iter().map(|s| s.resize).collect();
        let landscape = Resize { from: (2048, 1536), to: (1182, 886) };
        let portrait = Resize { from: (1536, 2048), to: (886, 1182) };
        assert_eq!(resizes, [None, Some(landscape), Some(landscape), Some(portrait), None]);
        assert_eq!(fitted_size(2048, 1536, 1 << 20), Some((1182, 886)));
        let sets = &plan.picked.as_ref().unwrap().sets;
        assert_eq!(sets.len(), 1, "images_1 is no set: {sets:?}");
        assert_eq!(
            plan.notes,
            ["3 images of 2048x1536 exceed the server's limit of 1048576 pixels per source view: resizing them to 1182x886"]
        );
    }

    #[test]
    fn bad_listings_name_the_entry() {
        let err = |files: &[&str], sizes: &[(&str, u32, u32)]| plan_err(files, sizes, FIT);
        assert!(matches!(err(&[], &[]), PlanError::Listing(_)));
        assert!(matches!(err(&["a.json", "../b.png"], &[]), PlanError::File { index: 1, .. }));
        assert!(matches!(err(&["a.json", "/etc/passwd"], &[]), PlanError::File { index: 1, .. }));
        assert!(matches!(err(&["a.json", "./a.json"], &[]), PlanError::File { index: 1, .. }));
        assert!(matches!(err(&["", "a.json"], &[]), PlanError::File { index: 0, .. }));
        let files = ["transforms.json", "images/a.png", ".b.png", "c.md"];
        assert!(matches!(err(&files, &[("images/z.png", 1, 1)]), PlanError::Size { index: 0, .. }));
        assert!(matches!(err(&files, &[("images/a.png", 1, 1), (".b.png", 1, 1)]), PlanError::Size { index: 1, .. }));
        assert!(matches!(err(&files, &[("transforms.json", 1, 1)]), PlanError::Size { index: 0, .. }));
        assert!(matches!(err(&files, &[("images/a.png", 0, 1)]), PlanError::Size { index: 0, .. }));
        let twice = [("images/a.png", 1, 1), ("./images/a.png", 1, 1)];
        assert!(matches!(err(&files, &twice), PlanError::Size { index: 1, .. }));
        let PlanError::Listing(message) = err(&["images/a.png", "notes.txt"], &[]) else { panic!() };
        assert!(message.starts_with("cannot tell the dataset format"), "{message}");
    }
}
