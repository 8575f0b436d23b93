//! Reading a bundle's files: only regular files inside the bundle's folder, of bounded size.
//!
//! A bundle folder is written by other processes (a copy, an rsync, the refine Job) while the
//! server may read it, and anything can sit in it: a FIFO (opening one blocks until a writer
//! comes), a link to `/dev/zero` (endless), to `/etc/shadow` (a digest of a secret in an error
//! message), a sparse file of terabytes. Files are opened without blocking and checked on the
//! opened descriptor, so a name swapped between a check and the open changes nothing.

use std::fs::File;
use std::io::Read;
use std::os::unix::fs::{MetadataExt, OpenOptionsExt};
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

/// Largest `manifest.json`: the default bundle's is 28 KB. serde_json's tree of a manifest takes
/// about 15 times its size, which this keeps under 16 MiB.
pub const MAX_MANIFEST_BYTES: u64 = 1 << 20;
/// Largest graph file: protobuf's limit on a message, so the largest ONNX graph that keeps its
/// weights inside the file (external data is refused, `onnx_data`).
pub const MAX_GRAPH_BYTES: u64 = 2 << 30;

/// Whether to keep reading; `Err` says why not (a deadline passed, the reload was abandoned).
pub type Stop<'a> = &'a dyn Fn() -> Result<(), String>;

/// A file of the bundle, open: its descriptor and size.
pub struct BundleFile {
    file: File,
    pub len: u64,
}

/// Opens `rel` in `dir`: a relative path without `..`, to a regular file of at most `max` bytes
/// whose real path (links resolved) lies inside `dir`. `what` names it in errors (a manifest
/// field). Never blocks on a FIFO, never reads a device.
pub fn open_in(dir: &Path, rel: &str, max: u64, what: &str) -> Result<BundleFile, String> {
    let rel_path = Path::new(rel);
    if rel_path.is_absolute() || rel_path.components().any(|c| matches!(c, std::path::Component::ParentDir)) {
        return Err(format!("{what} \"{rel}\" must be a path inside the bundle"));
    }
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY)
        .open(dir.join(rel_path))
        .map_err(|e| format!("{what}: cannot open \"{rel}\": {e}"))?;
    let meta = file.metadata().map_err(|e| format!("{what}: cannot read \"{rel}\": {e}"))?;
    if !meta.is_file() {
        return Err(format!("{what} \"{rel}\" is not a regular file"));
    }
    if !inside(dir, &file, &dir.join(rel_path)) {
        return Err(format!(
            "{what} \"{rel}\" leads outside the bundle (a link): only the bundle's own files are read"
        ));
    }
    if meta.len() > max {
        return Err(format!("{what} \"{rel}\" is {} bytes, more than the {max} a bundle's file may have", meta.len()));
    }
    Ok(BundleFile { file, len: meta.len() })
}

/// Whether the opened file's real path lies inside `dir`'s real path. The descriptor's path
/// (`/proc/self/fd`) is what was opened, whatever the name leads to now.
fn inside(dir: &Path, file: &File, path: &Path) -> bool {
    use std::os::fd::AsRawFd;
    let Ok(root) = std::fs::canonicalize(dir) else { return false };
    let real = std::fs::read_link(format!("/proc/self/fd/{}", file.as_raw_fd()))
        .or_else(|_| std::fs::canonicalize(path))
        .unwrap_or_else(|_| PathBuf::from("/"));
    real.starts_with(&root) && real != root
}

impl BundleFile {
    /// The whole file (at most the size checked at open: a file growing meanwhile is cut there,
    /// and its hash then differs).
    pub fn read_all(self, stop: Stop) -> Result<Vec<u8>, String> {
        let mut bytes = Vec::with_capacity(self.len as usize);
        self.each_chunk(stop, |chunk| bytes.extend_from_slice(chunk))?;
        Ok(bytes)
    }

    /// The file's sha256, lowercase hex.
    pub fn sha256(self, stop: Stop) -> Result<String, String> {
        let mut hasher = Sha256::new();
        self.each_chunk(stop, |chunk| hasher.update(chunk))?;
        Ok(hex::encode(hasher.finalize()))
    }

    /// Reads the file in chunks of 1 MiB, asking `stop` before each.
    fn each_chunk(self, stop: Stop, mut take: impl FnMut(&[u8])) -> Result<(), String> {
        let mut reader = self.file.take(self.len);
        let mut buf = vec![0u8; 1 << 20];
        loop {
            stop()?;
            let n = reader.read(&mut buf).map_err(|e| format!("read failed: {e}"))?;
            if n == 0 {
                return Ok(());
            }
            take(&buf[..n]);
        }
    }
}

/// Identity of a file as it stands (device, inode, size, modification time): a file with the
/// same identity has not been replaced or written since.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FileId {
    pub dev: u64,
    pub ino: u64,
    pub len: u64,
    pub mtime_ns: i128,
}

impl FileId {
    /// The identity of what `path` names (links followed), or `None` when it cannot be stat'ed.
    pub fn of(path: &Path) -> Option<FileId> {
        let m = std::fs::metadata(path).ok()?;
        let mtime_ns = i128::from(m.mtime()) * 1_000_000_000 + i128::from(m.mtime_nsec());
        Some(FileId { dev: m.dev(), ino: m.ino(), len: m.len(), mtime_ns })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn go() -> Result<(), String> {
        Ok(())
    }

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("scnerf-files-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn reads_regular_files_inside_and_nothing_else() {
        let dir = temp("kinds");
        std::fs::write(dir.join("a.onnx"), b"graph").unwrap();
        assert_eq!(open_in(&dir, "a.onnx", 100, "graphs.encoder.file").unwrap().read_all(&go).unwrap(), b"graph");
        std::fs::create_dir(dir.join("inner")).unwrap();
        std::fs::write(dir.join("inner/b.onnx"), b"g").unwrap();
        std::os::unix::fs::symlink("inner/b.onnx", dir.join("link-inside.onnx")).unwrap();
        assert!(open_in(&dir, "link-inside.onnx", 100, "f").is_ok(), "a link that stays inside is read");

        std::os::unix::fs::symlink("/dev/zero", dir.join("zero.onnx")).unwrap();
        let e = open_in(&dir, "zero.onnx", 100, "graphs.encoder.file").err().unwrap();
        assert!(e.contains("not a regular file"), "{e}");
        let fifo = std::ffi::CString::new(dir.join("fifo.onnx").to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o600) }, 0);
        let e = open_in(&dir, "fifo.onnx", 100, "f").err().unwrap();
        assert!(e.contains("not a regular file"), "{e}");

        let outside = temp("outside");
        std::fs::write(outside.join("secret"), b"secret").unwrap();
        std::os::unix::fs::symlink(outside.join("secret"), dir.join("secret.onnx")).unwrap();
        let e = open_in(&dir, "secret.onnx", 100, "f").err().unwrap();
        assert!(e.contains("leads outside the bundle"), "{e}");
        assert!(open_in(&dir, "../outside/secret", 100, "f").err().unwrap().contains("inside the bundle"));
        assert!(open_in(&dir, "a.onnx", 4, "f").err().unwrap().contains("more than the 4"));
        std::fs::remove_dir_all(&dir).unwrap();
        std::fs::remove_dir_all(&outside).unwrap();
    }

    #[test]
    fn reading_stops_when_asked() {
        let dir = temp("stop");
        std::fs::write(dir.join("a"), vec![1u8; 3 << 20]).unwrap();
        let stop = || Err::<(), _>("the deadline passed".to_string());
        let e = open_in(&dir, "a", 4 << 20, "f").unwrap().sha256(&stop).unwrap_err();
        assert_eq!(e, "the deadline passed");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
