//! The capture's files as the readers see them while the request lasts.

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use scnerf_capture::files::{Files, MemoryFiles};

use crate::blocking::Cancel;

/// `files`, failing every access once the request is gone: the readers then stop at their next
/// look at a file.
pub(super) struct Interruptible<'a> {
    pub(super) files: &'a MemoryFiles,
    pub(super) cancel: &'a Cancel,
}

impl Interruptible<'_> {
    fn check(&self, path: &Path) -> scnerf_capture::Result<()> {
        match self.cancel.is_set() {
            true => Err(scnerf_capture::Error::io(path, std::io::ErrorKind::Interrupted.into())),
            false => Ok(()),
        }
    }
}

impl Files for Interruptible<'_> {
    fn is_file(&self, path: &Path) -> bool {
        !self.cancel.is_set() && self.files.is_file(path)
    }

    fn is_dir(&self, path: &Path) -> bool {
        !self.cancel.is_set() && self.files.is_dir(path)
    }

    fn read(&self, path: &Path) -> scnerf_capture::Result<Cow<'_, [u8]>> {
        self.check(path)?;
        self.files.read(path)
    }

    fn list(&self, dir: &Path) -> scnerf_capture::Result<Vec<PathBuf>> {
        self.check(dir)?;
        self.files.list(dir)
    }
}
