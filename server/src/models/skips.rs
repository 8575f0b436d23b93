//! The bundle folders a scan of `--models DIR` did not load: each with its reason, clipped, and
//! the refusals remembered by the identity of the files read, so that a folder refused for
//! what it holds is not read and hashed again on every reload until one of them changes.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use serde::Serialize;

use super::model_name;
use crate::bundle::{Bundle, FileId};
use crate::error::clip_quoted;

/// A bundle folder a reload did not load.
#[derive(Debug, Clone, Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct Skipped {
    /// The model's name it would have had (its folder's name).
    pub name: String,
    pub path: String,
    /// What is wrong with it (the manifest, a graph's hash or signature, its name, memory, its
    /// warm-up).
    pub reason: String,
}

impl Skipped {
    /// `dir` skipped for `reason`. What the folder holds (its name, manifest text quoted in the
    /// reason) is clipped as any client data is ([`clip_quoted`]): a bounded line per folder.
    pub fn new(dir: &Path, reason: &str) -> Skipped {
        Skipped {
            name: clip_quoted(&model_name(dir)),
            path: clip_quoted(&dir.display().to_string()),
            reason: clip_quoted(reason),
        }
    }
}

/// The most skipped folders listed one by one (in a reload's answer, and in the log).
pub const MAX_LISTED: usize = 64;

/// Logs the first [`MAX_LISTED`] of `skipped` (escaped: a newline in a folder's name cannot
/// start a log line) and how many more there were; returns those listed and that count.
pub fn report(mut skipped: Vec<Skipped>) -> (Vec<Skipped>, usize) {
    let more = skipped.len().saturating_sub(MAX_LISTED);
    skipped.truncate(MAX_LISTED);
    for s in &skipped {
        tracing::warn!(path = %one_line(&s.path), reason = %one_line(&s.reason), "bundle skipped");
    }
    if more > 0 {
        tracing::warn!(more, "more bundle folders skipped (not listed)");
    }
    (skipped, more)
}

/// `text` with its control characters escaped (`\n`): a folder's name or a manifest's text
/// cannot start a line of the text log.
pub fn one_line(text: &str) -> String {
    text.chars().map(|c| if c.is_control() { c.escape_default().to_string() } else { c.to_string() }).collect()
}

/// Refusals for what a bundle folder holds (its manifest, a graph's hash, its graphs' sessions,
/// its warm-up), by folder. Refusals for the server's state (memory, a name taken) are not kept:
/// they may pass on the next reload with nothing changed in the folder.
#[derive(Default)]
pub struct Refusals(Mutex<HashMap<PathBuf, Refused>>);

struct Refused {
    files: Vec<(PathBuf, Option<FileId>)>,
    reason: String,
}

impl Refusals {
    /// The reason `dir` was refused, when none of the files it was refused for changed since.
    pub fn recall(&self, dir: &Path) -> Option<String> {
        let map = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let refused = map.get(dir)?;
        let unchanged = refused.files.iter().all(|(path, id)| FileId::of(path) == *id);
        unchanged.then(|| format!("{} (unchanged since it was refused: not read again)", refused.reason))
    }

    /// Remembers `reason` for the folder of `read`, the identities of its files taken before
    /// they were read: a file that changed while it was read (a copy still under way) has
    /// another identity now, and is read again on the next reload.
    pub fn remember(&self, read: Snapshot, reason: &str) {
        let refused = Refused { files: read.files, reason: clip_quoted(reason) };
        self.0.lock().unwrap_or_else(|p| p.into_inner()).insert(read.dir, refused);
    }

    /// Forgets the folders that a scan no longer finds.
    pub fn keep_only(&self, found: &[PathBuf]) {
        self.0.lock().unwrap_or_else(|p| p.into_inner()).retain(|dir, _| found.contains(dir));
    }
}

/// The identity of a bundle folder, its manifest and the graph files it names, as they stand:
/// a rename into the folder, a rewritten manifest or graph each change one.
#[derive(Debug, Clone)]
pub struct Snapshot {
    dir: PathBuf,
    files: Vec<(PathBuf, Option<FileId>)>,
}

impl Snapshot {
    pub fn of(dir: &Path) -> Snapshot {
        let files = std::iter::once(dir.to_path_buf()).chain(Bundle::files_named(dir));
        Snapshot { dir: dir.to_path_buf(), files: files.map(|path| (path.clone(), FileId::of(&path))).collect() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_log_field_stays_on_one_line() {
        assert_eq!(one_line("lego\nINFO fake line\r\u{1b}[31m"), "lego\\nINFO fake line\\r\\u{1b}[31m");
        assert_eq!(one_line("café \"quoted\""), "café \"quoted\"");
    }

    #[test]
    fn a_refusal_stands_until_a_file_it_read_changes() {
        let dir = std::env::temp_dir().join(format!("scnerf-refusals-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("manifest.json"), r#"{"graphs": {"encoder": {"file": "encoder.onnx"}}}"#).unwrap();
        std::fs::write(dir.join("encoder.onnx"), b"one").unwrap();
        let refusals = Refusals::default();
        refusals.remember(Snapshot::of(&dir), "graphs.encoder: sha256 of encoder.onnx is 00, manifest says 11");
        assert!(refusals.recall(&dir).unwrap().contains("not read again"));
        std::fs::write(dir.join("unrelated.txt"), b"x").unwrap();
        let stands = refusals.recall(&dir).is_some();
        // A new file changes the folder's mtime: read again (a rename into place looks the same).
        assert!(!stands);
        refusals.remember(Snapshot::of(&dir), "again");
        std::fs::write(dir.join("encoder.onnx"), b"two, longer").unwrap();
        assert!(refusals.recall(&dir).is_none(), "a rewritten graph is read again");
        let before = Snapshot::of(&dir);
        std::fs::write(dir.join("encoder.onnx"), b"the rest of a copy").unwrap();
        refusals.remember(before, "read while it was being written");
        assert!(refusals.recall(&dir).is_none(), "a graph that changed while it was read is read again");
        refusals.remember(Snapshot::of(&dir), "again");
        refusals.keep_only(&[]);
        assert!(refusals.recall(&dir).is_none());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
