//! The bundle folders below `--models DIR`: every folder with a `manifest.json`, at any depth
//! down to [`MAX_DEPTH`] (a bundle's own subfolders are not searched), in name order so that a
//! scan is repeatable.
//!
//! Links are followed only while they stay inside DIR, and each folder is searched once (by its
//! device and inode): a folder of links to itself costs one visit, not a path per cycle. The
//! scan asks `stop` before each folder, so a deadline ends it.

use std::collections::HashSet;
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};

use crate::bundle::Stop;

/// The manifest's file name: a folder holding one is a bundle folder.
const MANIFEST: &str = "manifest.json";
/// Deepest folder searched below DIR: a huge tree must not stall a reload.
const MAX_DEPTH: usize = 4;

/// What a scan found: the bundle folders, and the folders it did not search, each with why.
#[derive(Debug, Default)]
pub struct Found {
    pub bundles: Vec<PathBuf>,
    pub skipped: Vec<(PathBuf, String)>,
}

/// The bundle folders below `dir` (`dir` itself too, if it is one); `Err` when `stop` ended the
/// scan or DIR itself cannot be read.
pub fn bundle_dirs(dir: &Path, stop: Stop) -> Result<Found, String> {
    let root = std::fs::canonicalize(dir).map_err(|e| format!("cannot read {}: {e}", dir.display()))?;
    let mut scan = Scan { root, stop, visited: HashSet::new(), found: Found::default() };
    scan.search(dir, 0)?;
    Ok(scan.found)
}

struct Scan<'a> {
    /// DIR with its links resolved: no folder outside it is searched.
    root: PathBuf,
    stop: Stop<'a>,
    /// (device, inode) of every folder searched.
    visited: HashSet<(u64, u64)>,
    found: Found,
}

impl Scan<'_> {
    fn search(&mut self, dir: &Path, depth: usize) -> Result<(), String> {
        (self.stop)()?;
        let Some(meta) = self.enter(dir) else { return Ok(()) };
        if !self.visited.insert((meta.dev(), meta.ino())) {
            return Ok(());
        }
        // Only a regular file makes a bundle folder (a FIFO named manifest.json is not read).
        if std::fs::symlink_metadata(dir.join(MANIFEST)).is_ok_and(|m| m.is_file()) {
            match super::names::check_folder(dir) {
                Ok(()) => self.found.bundles.push(dir.to_path_buf()),
                Err(reason) => self.skip(dir, reason),
            }
            return Ok(());
        }
        if depth >= MAX_DEPTH {
            return Ok(());
        }
        let entries = match std::fs::read_dir(dir) {
            Ok(entries) => entries,
            Err(e) => {
                self.skip(dir, format!("cannot read the folder: {e}"));
                return Ok(());
            }
        };
        // Folders and links (a link may lead to a folder); the type comes with the entry, no stat.
        let mut subs: Vec<PathBuf> = entries
            .filter_map(Result::ok)
            .filter(|e| e.file_type().is_ok_and(|t| t.is_dir() || t.is_symlink()))
            .map(|e| e.path())
            .collect();
        subs.sort();
        for sub in subs {
            self.search(&sub, depth + 1)?;
        }
        Ok(())
    }

    /// The folder's metadata when it is a folder inside DIR; a link that leads out is skipped
    /// with the reason, anything that is not a folder silently.
    fn enter(&mut self, dir: &Path) -> Option<std::fs::Metadata> {
        let meta = std::fs::metadata(dir).ok().filter(|m| m.is_dir())?;
        match std::fs::canonicalize(dir) {
            Ok(real) if real.starts_with(&self.root) => Some(meta),
            Ok(_) => {
                self.skip(dir, "a link out of the models folder: not followed".into());
                None
            }
            Err(e) => {
                self.skip(dir, format!("cannot resolve the folder: {e}"));
                None
            }
        }
    }

    fn skip(&mut self, dir: &Path, reason: String) {
        self.found.skipped.push((dir.to_path_buf(), reason));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn go() -> Result<(), String> {
        Ok(())
    }

    fn temp(name: &str) -> PathBuf {
        let root = std::env::temp_dir().join(format!("scnerf-scan-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        std::fs::create_dir_all(&root).unwrap();
        root
    }

    fn relative(root: &Path, found: &[PathBuf]) -> Vec<PathBuf> {
        found.iter().map(|p| p.strip_prefix(root).unwrap().to_path_buf()).collect()
    }

    #[test]
    fn finds_bundle_folders_at_any_depth_but_not_inside_a_bundle() {
        let root = temp("depth");
        for dir in ["b", "a", "group/c", "a/inner", "empty/none"] {
            std::fs::create_dir_all(root.join(dir)).unwrap();
        }
        for dir in ["b", "a", "group/c", "a/inner"] {
            std::fs::write(root.join(dir).join(MANIFEST), "{}").unwrap();
        }
        let found = bundle_dirs(&root, &go).unwrap();
        assert_eq!(relative(&root, &found.bundles), ["a", "b", "group/c"].map(PathBuf::from));
        assert!(found.skipped.is_empty());
        std::fs::remove_dir_all(&root).unwrap();
    }

    /// 80 links to the folder itself cost 80^depth paths when each path is searched; once per
    /// folder, the scan stats each link once.
    #[test]
    fn link_loops_are_searched_once_and_links_out_of_dir_not_at_all() {
        let root = temp("loops");
        let outside = temp("loops-outside");
        std::fs::create_dir_all(root.join("models/a")).unwrap();
        std::fs::write(root.join("models/a").join(MANIFEST), "{}").unwrap();
        for i in 0..80 {
            std::os::unix::fs::symlink(".", root.join(format!("models/self{i}"))).unwrap();
        }
        std::fs::write(outside.join(MANIFEST), "{}").unwrap();
        std::os::unix::fs::symlink(&outside, root.join("models/elsewhere")).unwrap();
        std::os::unix::fs::symlink("a", root.join("models/z-link-to-a")).unwrap();
        let visits = std::cell::Cell::new(0usize);
        let counting = || {
            visits.set(visits.get() + 1);
            Ok(())
        };
        let found = bundle_dirs(&root.join("models"), &counting).unwrap();
        assert_eq!(relative(&root.join("models"), &found.bundles), [PathBuf::from("a")]);
        assert_eq!(found.skipped.len(), 1, "{:?}", found.skipped);
        assert!(found.skipped[0].0.ends_with("elsewhere") && found.skipped[0].1.contains("link out"));
        // The root, a, 80 self-links, the link out, the link to a: each looked at once.
        assert_eq!(visits.get(), 1 + 1 + 80 + 1 + 1);
        std::fs::remove_dir_all(&root).unwrap();
        std::fs::remove_dir_all(&outside).unwrap();
    }

    #[test]
    fn a_fifo_manifest_makes_no_bundle_and_a_stop_ends_the_scan() {
        let root = temp("fifo");
        std::fs::create_dir_all(root.join("a")).unwrap();
        let fifo = std::ffi::CString::new(root.join("a").join(MANIFEST).to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o600) }, 0);
        assert!(bundle_dirs(&root, &go).unwrap().bundles.is_empty());
        let stop = || Err::<(), _>("the reload's deadline passed".to_string());
        assert_eq!(bundle_dirs(&root, &stop).unwrap_err(), "the reload's deadline passed");
        std::fs::remove_dir_all(&root).unwrap();
    }
}
