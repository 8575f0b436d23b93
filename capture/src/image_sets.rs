//! The image sets of a capture as LLFF, nerfstudio and COLMAP users keep them: the full-size
//! photos in `images/` and downscaled copies beside them in `images_N/` (LLFF's `factor`,
//! nerfstudio's `--downscale-factor`), and which set to read.
//!
//! The readers read `images_N` when [`ReadOptions::downscale`] is `Some(N)`. The cameras stay
//! those of the full-size images (LLFF's `poses_bounds.npy` and COLMAP's `cameras.txt` describe
//! them; nerfstudio's `w`, `h`) and are scaled to the size of the image actually read, so every
//! set gives the same views at its own resolution.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::files::Files;
pub use crate::readers::folder_name;
use crate::readers::{self, list_images, Capture, Format, ReadOptions};

/// One image set: `images/` (factor 1) or `images_N/`, with the size of its first image.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ImageSet {
    pub factor: u32,
    pub folder: PathBuf,
    pub width: u32,
    pub height: u32,
}

impl ImageSet {
    pub fn pixels(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }

    /// `images_4 (1008x756)`.
    pub fn describe(&self) -> String {
        let name = self.folder.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        format!("{name} ({}x{})", self.width, self.height)
    }
}

/// The image sets of the capture at `root`, largest first (factor 1, 2, 4, ...): the folders
/// `images` and `images_N` (N > 1) that hold at least one image. Empty for the formats that do
/// not keep sets (Blender, DTU) and for a root that is a transforms file.
pub fn image_sets(fs: &dyn Files, root: &Path, format: Format) -> Result<Vec<ImageSet>> {
    if !matches!(format, Format::Llff | Format::Nerfstudio | Format::Colmap) || !fs.is_dir(root) {
        return Ok(Vec::new());
    }
    let mut factors: Vec<u32> =
        fs.list(root)?.iter().filter(|p| fs.is_dir(p)).filter_map(|p| factor_of(p.file_name()?.to_str()?)).collect();
    factors.sort_unstable();
    factors.dedup();
    let mut sets = Vec::new();
    for factor in factors {
        let folder = root.join(folder_name(factor));
        if let Some(first) = first_image(fs, &folder)? {
            let (width, height) = fs.image_size(&first)?;
            sets.push(ImageSet { factor, folder, width, height });
        }
    }
    Ok(sets)
}

/// 1 for `images`, N for `images_N` with N > 1; `None` for any other name.
fn factor_of(name: &str) -> Option<u32> {
    if name == "images" {
        return Some(1);
    }
    let n: u32 = name.strip_prefix("images_")?.parse().ok()?;
    (n > 1 && name == format!("images_{n}")).then_some(n)
}

/// The first image of a folder in name order (hidden files left out): the one whose size is the
/// set's.
pub fn first_image(fs: &dyn Files, folder: &Path) -> Result<Option<PathBuf>> {
    Ok(list_images(fs, folder)?.into_iter().next())
}

/// Which set to read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pick {
    /// `images_N` (`images` for 1): the user's `--downscale N`.
    Downscale(u32),
    /// The largest set whose images have at most this many pixels (the server's
    /// `max_source_pixels`); the smallest set when none does.
    Fit { max_pixels: u64 },
}

/// The set a [`Pick`] chose, and whether its images fit the limit it was chosen for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Picked {
    pub set: ImageSet,
    pub fits: bool,
    /// Every set of the capture, largest first.
    pub sets: Vec<ImageSet>,
}

impl Picked {
    /// What to tell the user: `images_8 (504x378) of images (4032x3024), images_4 (1008x756),
    /// images_8 (504x378)`.
    pub fn describe(&self) -> String {
        let all: Vec<String> = self.sets.iter().map(ImageSet::describe).collect();
        format!("{} of {}", self.set.describe(), all.join(", "))
    }
}

/// The set `pick` chooses among `sets` (largest first); `None` when there are no sets (the
/// capture is read as it is). A `--downscale N` the capture has no folder for is an error naming
/// the folders it has.
pub fn pick(sets: &[ImageSet], pick: Pick) -> Result<Option<Picked>> {
    let chosen = match pick {
        Pick::Downscale(factor) => {
            if sets.is_empty() && factor <= 1 {
                return Ok(None);
            }
            let set = sets.iter().find(|s| s.factor == factor.max(1)).ok_or_else(|| {
                let have: Vec<String> = sets.iter().map(ImageSet::describe).collect();
                let have = if have.is_empty() { "no image sets".to_string() } else { have.join(", ") };
                Error::UnknownImageSet { factor, folder: folder_name(factor), have }
            })?;
            Some((set.clone(), true))
        }
        Pick::Fit { max_pixels } => match sets.iter().find(|s| s.pixels() <= max_pixels) {
            Some(set) => Some((set.clone(), true)),
            None => sets.last().map(|set| (set.clone(), false)),
        },
    };
    Ok(chosen.map(|(set, fits)| Picked { set, fits, sets: sets.to_vec() }))
}

/// Reads the capture at `root` from the set `rule` picks (`format` `None` detects it): the
/// capture, and the set read when the capture has sets.
pub fn load_picked(
    fs: &dyn Files,
    root: &Path,
    format: Option<Format>,
    opts: ReadOptions,
    rule: Pick,
) -> Result<(Capture, Option<Picked>)> {
    let format = match format {
        Some(f) => f,
        None => readers::detect(fs, root)?,
    };
    let sets = image_sets(fs, root, format)?;
    let picked = pick(&sets, rule)?;
    let downscale = picked.as_ref().map(|p| p.set.factor).filter(|&f| f > 1);
    let capture = readers::load_from(fs, root, Some(format), ReadOptions { downscale, ..opts })?;
    Ok((capture, picked))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(factor: u32, width: u32, height: u32) -> ImageSet {
        ImageSet { factor, folder: PathBuf::from(folder_name(factor)), width, height }
    }

    #[test]
    fn folder_names_are_images_and_images_n() {
        assert_eq!((factor_of("images"), factor_of("images_4"), factor_of("images_1")), (Some(1), Some(4), None));
        assert_eq!((factor_of("images_04"), factor_of("images_x"), factor_of("imgs_2")), (None, None, None));
        assert_eq!((folder_name(1), folder_name(8)), ("images".to_string(), "images_8".to_string()));
    }

    #[test]
    fn fit_takes_the_largest_set_within_the_limit() {
        let sets = [set(1, 4032, 3024), set(4, 1008, 756), set(8, 504, 378)];
        let fit = |max_pixels| pick(&sets, Pick::Fit { max_pixels }).unwrap().unwrap();
        assert_eq!((fit(1 << 20).set.factor, fit(1 << 20).fits), (4, true));
        assert_eq!((fit(4032 * 3024).set.factor, fit(1008 * 756 - 1).set.factor), (1, 8));
        assert_eq!((fit(1000).set.factor, fit(1000).fits), (8, false), "none fits: the smallest, flagged");
        assert_eq!(
            fit(1 << 20).describe(),
            "images_4 (1008x756) of images (4032x3024), images_4 (1008x756), images_8 (504x378)"
        );
    }

    #[test]
    fn downscale_takes_its_folder_or_names_those_there_are() {
        let sets = [set(1, 64, 48), set(4, 16, 12)];
        assert_eq!(pick(&sets, Pick::Downscale(4)).unwrap().unwrap().set.factor, 4);
        assert_eq!(pick(&sets, Pick::Downscale(1)).unwrap().unwrap().set.factor, 1);
        let err = pick(&sets, Pick::Downscale(2)).unwrap_err().to_string();
        assert!(
            err.contains("downscale 2: there is no images_2 folder; the capture has images (64x48), images_4 (16x12)"),
            "{err}"
        );
        assert_eq!(pick(&[], Pick::Downscale(1)).unwrap(), None);
        assert_eq!(pick(&[], Pick::Fit { max_pixels: 10 }).unwrap(), None);
    }
}
