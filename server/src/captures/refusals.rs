//! What the readers and validation refuse, named as the client knows it: by the capture's file.

use crate::error::ApiError;

/// A capture the readers refuse: 422 naming the file (relative to the capture's folder).
pub(super) fn capture_error(e: scnerf_capture::Error) -> ApiError {
    if let scnerf_capture::Error::UnknownImageSet { .. } = e {
        return ApiError::invalid("downscale", e.to_string());
    }
    let field = e.path().map(|p| p.to_string_lossy().into_owned()).filter(|p| !p.is_empty());
    ApiError::invalid(field.unwrap_or_else(|| "file".to_string()), e.to_string())
}

/// Validation names a view `sources[i]...`; a capture's client knows it by its file.
pub(super) fn name_the_file(e: ApiError, names: &[String]) -> ApiError {
    let file = |field: &str| {
        let index: usize = field.strip_prefix("sources[")?.split(']').next()?.parse().ok()?;
        names.get(index).cloned()
    };
    match e {
        ApiError::Invalid { field, message } => match file(&field) {
            Some(name) => ApiError::Invalid { message: format!("{name}: {message} ({field})"), field: name },
            None => ApiError::Invalid { field, message },
        },
        other => other,
    }
}
