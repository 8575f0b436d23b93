//! The one error type of the client. Every variant names what it is about (a file and field, a
//! URL, a flag) so that `main` can print it as is.

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot read {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },

    /// A dataset file that is malformed or not usable; the message names the field or line.
    #[error("{path}: {message}")]
    Dataset { path: PathBuf, message: String },

    /// Bad command-line input that clap cannot check by itself.
    #[error("{0}")]
    Usage(String),

    #[error("cannot reach the server at {url}: {message}")]
    Http { url: String, message: String },

    /// A 2xx answer the client cannot use.
    #[error("unexpected answer from the server ({context}): {message}")]
    Response { context: String, message: String },

    /// The server's own `{"error": {"code", "message", "field", "hint"}}`; `hint` is what the
    /// server says to do about it (`reupload`), when it says.
    #[error("the server refused the request ({status} {code}): {message}{}", field_suffix(.field))]
    Server { status: u16, code: String, message: String, field: Option<String>, hint: Option<String> },

    #[error("video: {0}")]
    Video(String),
}

/// A capture error keeps its wording: the same file and message, or a usage error for a view
/// name or an image set the capture does not have.
impl From<scnerf_capture::Error> for Error {
    fn from(e: scnerf_capture::Error) -> Self {
        match e {
            scnerf_capture::Error::Io { path, source } => Error::Io { path, source },
            scnerf_capture::Error::Dataset { path, message } => Error::Dataset { path, message },
            usage @ (scnerf_capture::Error::UnknownView { .. } | scnerf_capture::Error::UnknownImageSet { .. }) => {
                Error::Usage(usage.to_string())
            }
        }
    }
}

fn field_suffix(field: &Option<String>) -> String {
    field.as_ref().map(|f| format!(" [field: {f}]")).unwrap_or_default()
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn dataset(path: impl AsRef<Path>, message: impl Into<String>) -> Self {
        Error::Dataset { path: path.as_ref().to_path_buf(), message: message.into() }
    }

    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io { path: path.as_ref().to_path_buf(), source }
    }
}

/// `std::fs::read` whose error names the file.
pub fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}
