//! A capture folder's files, multipart: every part named `file`, its filename the file's path in
//! the folder (`transforms.json`, `images/r_0.png`, `sparse/0/cameras.txt`, ...). The files other
//! than images, which the readers parse, are capped as they arrive
//! (`--max-capture-metadata-bytes`).

use std::path::Path;

use axum::extract::{FromRequest, Multipart, Request};
use scnerf_capture::files::MemoryFiles;
use scnerf_capture::readers;

use super::multipart::multipart_error;
use crate::captures::CaptureFiles;
use crate::error::ApiError;
use crate::request::Limits;

/// Every `file` part, by its filename, and the bytes of those that are not images (at most
/// `--max-capture-metadata-bytes`: 413 naming the file that goes past it, as it arrives).
pub async fn read_capture_files(req: Request, limits: &Limits) -> Result<CaptureFiles, ApiError> {
    let limit = limits.max_capture_bytes;
    let mut multipart = Multipart::from_request(req, &()).await.map_err(|e| {
        ApiError::malformed(Some("content-type".to_string()), format!("invalid multipart request: {}", e.body_text()))
    })?;
    let (mut files, mut metadata) = (MemoryFiles::new(), 0usize);
    while let Some(mut field) = multipart.next_field().await.map_err(|e| multipart_error(e, "body", limit))? {
        let name = field.name().unwrap_or_default().to_string();
        if name != "file" {
            return Err(ApiError::malformed(
                Some(name.clone()),
                format!("unknown multipart part \"{name}\": every part is a file named `file`"),
            ));
        }
        let filename = field.file_name().map(str::to_string).ok_or_else(|| missing_filename(field.headers()))?;
        let is_image = readers::has_image_extension(Path::new(&filename));
        let mut chunks = Vec::new();
        while let Some(chunk) = field.chunk().await.map_err(|e| multipart_error(e, &filename, limit))? {
            if !is_image {
                metadata += chunk.len();
                if metadata > limits.max_capture_metadata_bytes {
                    return Err(ApiError::TooLarge {
                        field: Some(filename),
                        message: format!(
                            "a capture's files other than images (transforms, COLMAP models, poses) may hold {} \
                             bytes in all (--max-capture-metadata-bytes)",
                            limits.max_capture_metadata_bytes
                        ),
                    });
                }
            }
            chunks.push(chunk);
        }
        if !files.insert(&filename, chunks.concat()) {
            return Err(ApiError::malformed(
                Some(filename),
                "sent twice, or not a relative path inside the capture folder",
            ));
        }
    }
    if files.is_empty() {
        return Err(ApiError::invalid("file", "no files: send the capture folder's files as parts named `file`"));
    }
    Ok(CaptureFiles { files, metadata_bytes: metadata })
}

/// A file part without a (UTF-8) filename: which of the two it is.
fn missing_filename(headers: &axum::http::HeaderMap) -> ApiError {
    let disposition = headers.get(axum::http::header::CONTENT_DISPOSITION).map(|v| v.as_bytes()).unwrap_or_default();
    let has_one = disposition.windows(9).any(|w| w.eq_ignore_ascii_case(b"filename="));
    let message = match has_one {
        true => "the part's filename is not UTF-8: name the file's path in UTF-8",
        false => "a file part needs a filename: its path in the capture",
    };
    ApiError::malformed(Some("file".to_string()), message)
}
