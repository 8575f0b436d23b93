//! Where a capture's files come from: a folder on disk ([`Disk`], the client) or files held in
//! memory ([`MemoryFiles`], the server's `POST /v1/captures`, which writes nothing to disk). The
//! readers see only this interface, so both read a capture by the same code.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::{Component, Path, PathBuf};

use crate::error::{Error, Result};
use crate::images::{self, ImageError};

/// Read access to a tree of files.
pub trait Files {
    fn is_file(&self, path: &Path) -> bool;
    fn is_dir(&self, path: &Path) -> bool;
    fn read(&self, path: &Path) -> Result<Cow<'_, [u8]>>;
    /// The entries (files and folders) directly in `dir`, as paths under it, in no set order.
    fn list(&self, dir: &Path) -> Result<Vec<PathBuf>>;

    /// (width, height) from an image's header, as displayed (`images::read_header`).
    fn image_size(&self, path: &Path) -> Result<(u32, u32)> {
        let bytes = self.read(path)?;
        image_size(path, std::io::Cursor::new(bytes.as_ref()))
    }

    fn read_text(&self, path: &Path) -> Result<String> {
        let bytes = self.read(path)?;
        String::from_utf8(bytes.into_owned()).map_err(|_| Error::dataset(path, "not UTF-8 text"))
    }
}

fn image_size(path: &Path, reader: impl std::io::BufRead + std::io::Seek) -> Result<(u32, u32)> {
    match images::read_header(reader) {
        Ok(header) => Ok((header.width, header.height)),
        Err(ImageError::Io(e)) => Err(Error::io(path, e)),
        Err(other) => Err(Error::dataset(path, format!("cannot read the image header: {other}"))),
    }
}

/// The file system.
#[derive(Debug, Clone, Copy, Default)]
pub struct Disk;

impl Files for Disk {
    fn is_file(&self, path: &Path) -> bool {
        path.is_file()
    }

    fn is_dir(&self, path: &Path) -> bool {
        path.is_dir()
    }

    fn read(&self, path: &Path) -> Result<Cow<'_, [u8]>> {
        std::fs::read(path).map(Cow::Owned).map_err(|e| Error::io(path, e))
    }

    fn list(&self, dir: &Path) -> Result<Vec<PathBuf>> {
        let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
        Ok(entries.filter_map(|e| e.ok().map(|e| e.path())).collect())
    }

    /// Only the header is read, not the whole image.
    fn image_size(&self, path: &Path) -> Result<(u32, u32)> {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        image_size(path, std::io::BufReader::new(file))
    }
}

/// Files held in memory under relative paths (`transforms.json`, `images/r_0.png`); folders are
/// implied by the paths. Paths are compared in their normal form: `.` segments dropped, `..`
/// taken lexically, so `./train/r_0.png` (as transforms files write it) finds `train/r_0.png`.
#[derive(Debug, Clone, Default)]
pub struct MemoryFiles {
    files: BTreeMap<PathBuf, Vec<u8>>,
}

impl MemoryFiles {
    pub fn new() -> MemoryFiles {
        MemoryFiles::default()
    }

    /// Adds a file; false (and nothing changes) when a file of that normal path is already there
    /// or the path names no file (empty, or leaving the root with `..`).
    pub fn insert(&mut self, path: &str, bytes: Vec<u8>) -> bool {
        match normal(Path::new(path)) {
            Some(p) if !p.as_os_str().is_empty() && !self.files.contains_key(&p) => {
                self.files.insert(p, bytes);
                true
            }
            _ => false,
        }
    }

    /// Takes a file out (a reader is done with it), by any spelling of its path.
    pub fn remove(&mut self, path: &Path) -> Option<Vec<u8>> {
        self.files.remove(&normal(path)?)
    }

    pub fn len(&self) -> usize {
        self.files.len()
    }

    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }

    /// A file's bytes, by any spelling of its path.
    pub fn get(&self, path: &Path) -> Option<&[u8]> {
        self.files.get(&normal(path)?).map(Vec::as_slice)
    }

    /// The files below the folder `dir` (a normal path), in order. Paths order component by
    /// component, so they are the keys right after `dir` that start with it: a folder is found in
    /// O(log n), and a capture's folders are listed in time linear in their files (DTU's
    /// detection asks whether each entry of `Rectified/` is a folder).
    fn under<'a>(&'a self, dir: &'a Path) -> impl Iterator<Item = &'a PathBuf> + 'a {
        self.files
            .range::<Path, _>((std::ops::Bound::Excluded(dir), std::ops::Bound::Unbounded))
            .map(|(path, _)| path)
            .take_while(move |path| path.starts_with(dir))
    }

    /// The normal form of `path` (what [`MemoryFiles`] keys files by).
    pub fn normal_path(path: &Path) -> Option<PathBuf> {
        normal(path)
    }
}

/// `path` without `.` segments and with `..` applied; `None` when it leaves the root or is
/// absolute (a capture's files are relative to its folder).
fn normal(path: &Path) -> Option<PathBuf> {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            Component::Normal(s) => out.push(s),
            Component::CurDir => {}
            Component::ParentDir => {
                if !out.pop() {
                    return None;
                }
            }
            Component::RootDir | Component::Prefix(_) => return None,
        }
    }
    Some(out)
}

impl Files for MemoryFiles {
    fn is_file(&self, path: &Path) -> bool {
        self.get(path).is_some()
    }

    fn is_dir(&self, path: &Path) -> bool {
        normal(path).is_some_and(|dir| self.under(&dir).next().is_some())
    }

    fn read(&self, path: &Path) -> Result<Cow<'_, [u8]>> {
        self.get(path)
            .map(Cow::Borrowed)
            .ok_or_else(|| Error::io(path, std::io::Error::from(std::io::ErrorKind::NotFound)))
    }

    fn list(&self, dir: &Path) -> Result<Vec<PathBuf>> {
        if !self.is_dir(dir) {
            return Err(Error::io(dir, std::io::Error::from(std::io::ErrorKind::NotFound)));
        }
        let base = normal(dir).unwrap_or_default();
        let mut children: Vec<PathBuf> = self
            .under(&base)
            .filter_map(|f| f.strip_prefix(&base).ok()?.components().next())
            .map(|c| dir.join(c.as_os_str()))
            .collect();
        children.dedup();
        Ok(children)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memory_files_find_any_spelling_and_imply_folders() {
        let mut files = MemoryFiles::new();
        assert!(files.insert("train/r_0.png", vec![1]));
        assert!(files.insert("transforms.json", vec![2]));
        assert!(files.insert("sparse/0/cameras.txt", vec![3]));
        assert!(!files.insert("./train/r_0.png", vec![4]), "the same file twice");
        assert!(!files.insert("../escape.png", vec![5]));
        assert!(!files.insert("/etc/passwd", vec![6]));
        assert!(!files.insert("./", vec![7]));
        assert_eq!(files.len(), 3);
        assert_eq!(files.get(Path::new("./train/../train/r_0.png")), Some(&[1u8][..]));
        assert!(files.is_file(Path::new("transforms.json")) && !files.is_file(Path::new("train")));
        assert!(files.is_dir(Path::new("")) && files.is_dir(Path::new("sparse/0")));
        assert!(!files.is_dir(Path::new("images")) && !files.is_dir(Path::new("transforms.json")));
        let mut root = files.list(Path::new("")).unwrap();
        root.sort();
        assert_eq!(root, [Path::new("sparse"), Path::new("train"), Path::new("transforms.json")]);
        assert_eq!(files.list(Path::new("sparse")).unwrap(), [Path::new("sparse/0")]);
        assert!(files.list(Path::new("images")).is_err());
        assert!(files.read(Path::new("missing.json")).is_err());
    }
}
