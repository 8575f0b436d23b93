//! The one error type of the HTTP API, mapped to a status and DESIGN.md's JSON body in one place:
//! `{"error": {"code", "message", "field"}}`.

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// The body cannot be parsed (bad JSON, broken multipart, undecodable image, unknown field).
    #[error("{message}")]
    Malformed { field: Option<String>, message: String },

    /// The body or a part of it exceeds a configured size limit.
    #[error("{message}")]
    TooLarge { field: Option<String>, message: String },

    /// Content-Type (or an image part's format) is not one we accept.
    #[error("{message}")]
    UnsupportedMediaType { field: Option<String>, message: String },

    /// None of the Accept media types can be produced.
    #[error("{message}")]
    NotAcceptable { message: String },

    /// Well-formed but semantically invalid (non-finite or singular camera, wrong view count...).
    #[error("{message}")]
    Invalid { field: String, message: String },

    #[error("not found: {path}")]
    NotFound { path: String },

    #[error("method not allowed")]
    MethodNotAllowed,

    /// Not ready yet (warming up) or overloaded; the client may retry later.
    #[error("{message}")]
    Unavailable { message: String, retry_after_secs: u64 },

    /// The request's deadline passed before the render finished.
    #[error("deadline of {secs} s exceeded")]
    DeadlineExceeded { secs: u64 },

    /// A failure of ours (inference backend, unexpected graph output). Never caused by input.
    #[error("{0}")]
    Internal(String),
}

impl ApiError {
    pub fn malformed(field: impl Into<Option<String>>, message: impl Into<String>) -> Self {
        Self::Malformed { field: field.into(), message: message.into() }
    }

    pub fn invalid(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self::Invalid { field: field.into(), message: message.into() }
    }

    pub fn status(&self) -> StatusCode {
        match self {
            Self::Malformed { .. } => StatusCode::BAD_REQUEST,
            Self::TooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            Self::UnsupportedMediaType { .. } => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            Self::NotAcceptable { .. } => StatusCode::NOT_ACCEPTABLE,
            Self::Invalid { .. } => StatusCode::UNPROCESSABLE_ENTITY,
            Self::NotFound { .. } => StatusCode::NOT_FOUND,
            Self::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            Self::Unavailable { .. } => StatusCode::SERVICE_UNAVAILABLE,
            Self::DeadlineExceeded { .. } => StatusCode::GATEWAY_TIMEOUT,
            Self::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    /// Stable machine-readable code of the error.
    pub fn code(&self) -> &'static str {
        match self {
            Self::Malformed { .. } => "malformed_request",
            Self::TooLarge { .. } => "payload_too_large",
            Self::UnsupportedMediaType { .. } => "unsupported_media_type",
            Self::NotAcceptable { .. } => "not_acceptable",
            Self::Invalid { .. } => "invalid_request",
            Self::NotFound { .. } => "not_found",
            Self::MethodNotAllowed => "method_not_allowed",
            Self::Unavailable { .. } => "unavailable",
            Self::DeadlineExceeded { .. } => "deadline_exceeded",
            Self::Internal(_) => "internal",
        }
    }

    pub fn field(&self) -> Option<&str> {
        match self {
            Self::Malformed { field, .. } | Self::TooLarge { field, .. } | Self::UnsupportedMediaType { field, .. } => {
                field.as_deref()
            }
            Self::Invalid { field, .. } => Some(field),
            _ => None,
        }
    }

    pub fn body(&self) -> ErrorBody {
        ErrorBody {
            error: ErrorDetail {
                code: self.code().to_string(),
                message: self.to_string(),
                field: self.field().map(str::to_string),
            },
        }
    }
}

#[derive(Debug, Serialize, serde::Deserialize, PartialEq)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

#[derive(Debug, Serialize, serde::Deserialize, PartialEq)]
pub struct ErrorDetail {
    pub code: String,
    pub message: String,
    pub field: Option<String>,
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        // Only our own failures are errors; refusals (4xx, busy, warming up) are routine.
        match &self {
            Self::Internal(_) => tracing::error!(code = self.code(), "{self}"),
            Self::DeadlineExceeded { .. } => tracing::warn!(code = self.code(), "{self}"),
            _ => tracing::debug!(code = self.code(), field = self.field(), "{self}"),
        }
        let mut response = (status, axum::Json(self.body())).into_response();
        if let Self::Unavailable { retry_after_secs, .. } = &self {
            response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(*retry_after_secs));
        }
        response
    }
}
