//! Errors of reading a capture. Each names the file it is about (and, in its message, the field
//! or line), so that a command line or an HTTP answer can show it as is.

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot read {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },

    /// A dataset file that is malformed or not usable; the message names the field or line.
    #[error("{path}: {message}")]
    Dataset { path: PathBuf, message: String },

    /// `--downscale N` for a capture without an `images_N` folder; `have` lists its sets.
    #[error("downscale {factor}: there is no {folder} folder; the capture has {have}")]
    UnknownImageSet { factor: u32, folder: String, have: String },

    /// A view name that the capture does not have.
    #[error("view {name:?} is not in the capture; its views are: {}", .known.join(", "))]
    UnknownView { name: String, known: Vec<String> },
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn dataset(path: impl AsRef<Path>, message: impl Into<String>) -> Self {
        Error::Dataset { path: path.as_ref().to_path_buf(), message: message.into() }
    }

    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io { path: path.as_ref().to_path_buf(), source }
    }

    /// The file the error is about (none for an unknown view).
    pub fn path(&self) -> Option<&Path> {
        match self {
            Error::Io { path, .. } | Error::Dataset { path, .. } => Some(path),
            Error::UnknownView { .. } | Error::UnknownImageSet { .. } => None,
        }
    }
}
