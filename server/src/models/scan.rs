//! The bundle folders below `--models DIR`: every folder with a `manifest.json`, at any depth
//! (a bundle's own subfolders are not searched), in name order so that a scan is repeatable.

use std::path::{Path, PathBuf};

/// The manifest's file name: a folder holding one is a bundle folder.
const MANIFEST: &str = "manifest.json";
/// Deepest folder searched below DIR: a link loop or a huge tree must not stall a reload.
const MAX_DEPTH: usize = 4;

/// The bundle folders below `dir` (`dir` itself too, if it is one), and the folders that could
/// not be read, each with the reason.
pub fn bundle_dirs(dir: &Path) -> (Vec<PathBuf>, Vec<(PathBuf, String)>) {
    let (mut found, mut unreadable) = (Vec::new(), Vec::new());
    search(dir, 0, &mut found, &mut unreadable);
    (found, unreadable)
}

fn search(dir: &Path, depth: usize, found: &mut Vec<PathBuf>, unreadable: &mut Vec<(PathBuf, String)>) {
    if dir.join(MANIFEST).is_file() {
        match super::names::check_folder(dir) {
            Ok(()) => found.push(dir.to_path_buf()),
            Err(reason) => unreadable.push((dir.to_path_buf(), reason)),
        }
        return;
    }
    if depth >= MAX_DEPTH {
        return;
    }
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) => return unreadable.push((dir.to_path_buf(), format!("cannot read the folder: {e}"))),
    };
    let mut dirs: Vec<PathBuf> = entries.filter_map(Result::ok).map(|e| e.path()).filter(|p| p.is_dir()).collect();
    dirs.sort();
    for sub in dirs {
        search(&sub, depth + 1, found, unreadable);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_bundle_folders_at_any_depth_but_not_inside_a_bundle() {
        let root = std::env::temp_dir().join(format!("scnerf-scan-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        for dir in ["b", "a", "group/c", "a/inner", "empty/none"] {
            std::fs::create_dir_all(root.as_path().join(dir)).unwrap();
        }
        for dir in ["b", "a", "group/c", "a/inner"] {
            std::fs::write(root.as_path().join(dir).join(MANIFEST), "{}").unwrap();
        }
        let (found, unreadable) = bundle_dirs(root.as_path());
        let names: Vec<_> = found.iter().map(|p| p.strip_prefix(root.as_path()).unwrap().to_path_buf()).collect();
        assert_eq!(names, ["a", "b", "group/c"].map(PathBuf::from));
        assert!(unreadable.is_empty());
        std::fs::remove_dir_all(&root).unwrap();
    }
}
