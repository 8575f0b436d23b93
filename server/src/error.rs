//! The one error type of the HTTP API, mapped to a status and docs/design.md's JSON body in one place:
//! `{"error": {"code", "message", "field"}}`.

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

use crate::backend::BackendError;
use crate::cache::shares::NoRoom;

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

    /// Authentication is on and the request has no valid bearer token.
    #[error("{message}")]
    Unauthorized { message: String },

    /// A state-changing request from a site the server does not let change its state
    /// (`http::origin`).
    #[error("{message}")]
    Forbidden { field: String, message: String },

    #[error("not found: {path}")]
    NotFound { path: String },

    /// No live scene with this id for this client here (unknown, expired, evicted, deleted,
    /// created with another token, or held by another replica: these are deliberately
    /// indistinguishable). Its hint tells the client to upload it again.
    #[error("no scene {id} here (unknown, expired, evicted, or on another replica): upload it again (PUT /v1/scenes/{id}) and retry")]
    SceneNotFound { id: String },

    /// The request names a model this server does not serve (`GET /v1/models` lists them).
    #[error("no model \"{name}\" here: GET /v1/models lists the models served")]
    ModelNotFound { name: String },

    /// A scene is rendered with the model it was created with; the request names another.
    #[error("scene {scene} was created with model \"{scene_model}\", not \"{requested}\": render it with \"{scene_model}\" (or without \"model\"), or upload it again with \"model\": \"{requested}\"")]
    ModelMismatch { scene: String, scene_model: String, requested: String },

    #[error("method not allowed")]
    MethodNotAllowed,

    /// The request body arrived too slowly (see `http::body::UploadPolicy`).
    #[error("{message}")]
    BodyTimeout { message: String },

    /// This client already has as many requests in flight as one client may.
    #[error("{message}")]
    TooManyRequests { message: String, retry_after_secs: u64 },

    /// Not ready yet (warming up) or overloaded; the client may retry later.
    #[error("{message}")]
    Unavailable { message: String, retry_after_secs: u64 },

    /// The request's deadline passed before the render finished.
    #[error("the request's deadline of {ms} ms passed before the render finished")]
    DeadlineExceeded { ms: u64 },

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
            Self::Unauthorized { .. } => StatusCode::UNAUTHORIZED,
            Self::Forbidden { .. } => StatusCode::FORBIDDEN,
            Self::NotFound { .. } | Self::SceneNotFound { .. } | Self::ModelNotFound { .. } => StatusCode::NOT_FOUND,
            Self::ModelMismatch { .. } => StatusCode::CONFLICT,
            Self::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            Self::BodyTimeout { .. } => StatusCode::REQUEST_TIMEOUT,
            Self::TooManyRequests { .. } => StatusCode::TOO_MANY_REQUESTS,
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
            Self::Unauthorized { .. } => "unauthorized",
            Self::Forbidden { .. } => "forbidden",
            Self::NotFound { .. } => "not_found",
            Self::SceneNotFound { .. } => "scene_not_found",
            Self::ModelNotFound { .. } => "model_not_found",
            Self::ModelMismatch { .. } => "model_mismatch",
            Self::MethodNotAllowed => "method_not_allowed",
            Self::BodyTimeout { .. } => "body_timeout",
            Self::TooManyRequests { .. } => "too_many_requests",
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
            Self::Invalid { field, .. } | Self::Forbidden { field, .. } => Some(field),
            Self::SceneNotFound { .. } => Some("scene_id"),
            Self::ModelNotFound { .. } | Self::ModelMismatch { .. } => Some("model"),
            Self::BodyTimeout { .. } => Some("body"),
            // Not fields of the body, but what the client got wrong all the same.
            Self::Unauthorized { .. } => Some("authorization"),
            Self::NotFound { .. } => Some("path"),
            Self::MethodNotAllowed => Some("method"),
            Self::NotAcceptable { .. } => Some("accept"),
            Self::TooManyRequests { .. }
            | Self::Unavailable { .. }
            | Self::DeadlineExceeded { .. }
            | Self::Internal(_) => None,
        }
    }

    /// What the client should do, when that is one thing (`ErrorDetail::hint`).
    pub fn hint(&self) -> Option<&'static str> {
        match self {
            Self::SceneNotFound { .. } => Some(HINT_REUPLOAD),
            _ => None,
        }
    }

    /// The message as sent and logged: client data quoted in it is clipped (see `clip_quoted`).
    pub fn message(&self) -> String {
        clip_quoted(&self.to_string())
    }

    pub fn body(&self) -> ErrorBody {
        ErrorBody {
            error: ErrorDetail {
                code: self.code().to_string(),
                message: self.message(),
                field: self.field().map(clip_quoted),
                hint: self.hint().map(str::to_string),
            },
        }
    }
}

impl From<BackendError> for ApiError {
    fn from(e: BackendError) -> Self {
        match e {
            BackendError::QueueFull => {
                ApiError::Unavailable { message: "server busy: inference queue is full".into(), retry_after_secs: 2 }
            }
            // Work admitted before it is what makes it late: the client may come back when that
            // is done. With none ahead the server could not meet the deadline even idle.
            BackendError::WouldMissDeadline { ahead_secs, .. } if ahead_secs > 0.0 => ApiError::TooManyRequests {
                message: format!("server busy: {e}"),
                retry_after_secs: ahead_secs.ceil().max(1.0) as u64,
            },
            BackendError::WouldMissDeadline { .. } => {
                ApiError::Unavailable { message: e.to_string(), retry_after_secs: 1 }
            }
            // Come back when the work ahead is within the wait (a client's deadline header
            // makes the wait as long as it allows).
            BackendError::QueueWaitTooLong { ahead_secs, max_secs } => ApiError::TooManyRequests {
                message: format!("server busy: {e}"),
                retry_after_secs: (ahead_secs - max_secs).ceil().max(1.0) as u64,
            },
            BackendError::MemoryBusy { ahead_secs, .. } => ApiError::Unavailable {
                message: format!("server busy: {e}"),
                retry_after_secs: ahead_secs.ceil().max(1.0) as u64,
            },
            // `Pipeline::admit` names the sizes that make a request too large; this is the rule.
            BackendError::TooLarge { .. } => ApiError::invalid("sources", format!("the request needs {e}")),
            // The handler's own timer normally fires first and knows the deadline; this is the
            // executor noticing it between two graph runs.
            BackendError::DeadlineExceeded => ApiError::DeadlineExceeded { ms: 0 },
            other => ApiError::Internal(other.to_string()),
        }
    }
}

/// A scene too large for the whole cache is a property of its sources.
impl From<NoRoom> for ApiError {
    fn from(e: NoRoom) -> Self {
        match e {
            NoRoom::TooLarge { .. } => ApiError::invalid("sources", e.to_string()),
            // Room comes back as other clients' scenes expire (their idle TTL).
            NoRoom::Full => ApiError::Unavailable { message: e.to_string(), retry_after_secs: 60 },
        }
    }
}

/// Every error response: `{"error": {"code", "message", "field"}}`.
#[derive(Debug, Serialize, serde::Deserialize, PartialEq, utoipa::ToSchema)]
#[schema(as = Error)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

#[derive(Debug, Serialize, serde::Deserialize, PartialEq, utoipa::ToSchema)]
pub struct ErrorDetail {
    /// Stable machine-readable code, e.g. `invalid_request`, `scene_not_found`.
    pub code: String,
    pub message: String,
    /// The offending field (`sources[1].camera.pose.matrix`, `source_2`, `near`, `content-type`,
    /// `authorization`, ...), or null when the error is not about the request.
    pub field: Option<String>,
    /// What to do about it, when that is one thing: `reupload` (404 `scene_not_found`: upload
    /// the scene again, e.g. `PUT /v1/scenes/{id}` with the same id, and retry). Absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hint: Option<String>,
}

/// `ErrorDetail::hint` of a scene this server does not hold.
pub const HINT_REUPLOAD: &str = "reupload";

/// Longest quoted client string kept in an error message.
const MAX_QUOTED_CHARS: usize = 32;
/// Longest error message.
const MAX_MESSAGE_CHARS: usize = 1000;

/// Parsers quote what they could not use (`invalid type: string "iVBORw0KGgo...", expected
/// f64`): that can be a base64 image or a token pasted into the wrong field. Quoted strings are
/// cut to their first characters, and the whole message to a sane length, so that neither
/// responses nor logs carry image data or secrets. Runs of digits are cut the same way: a number
/// such as 1e308 is echoed with all its 309 digits.
pub fn clip_quoted(message: &str) -> String {
    let mut out = String::with_capacity(message.len().min(MAX_MESSAGE_CHARS));
    let (mut quoted, mut run) = (false, 0usize);
    for c in message.chars() {
        if out.len() >= MAX_MESSAGE_CHARS {
            out.push('…');
            break;
        }
        if c == '"' {
            quoted = !quoted;
            run = 0;
        } else if quoted || c.is_ascii_digit() {
            run += 1;
            if run > MAX_QUOTED_CHARS {
                if run == MAX_QUOTED_CHARS + 1 {
                    out.push('…');
                }
                continue;
            }
        } else {
            run = 0;
        }
        out.push(c);
    }
    out
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        // Only our own failures are errors; refusals (4xx, busy, warming up) are routine. The
        // message of a refusal may quote client data, so only its code and field are logged.
        match &self {
            Self::Internal(_) => tracing::error!(code = self.code(), "{}", self.message()),
            Self::DeadlineExceeded { .. } => tracing::warn!(code = self.code(), "{}", self.message()),
            _ => tracing::debug!(code = self.code(), field = self.field(), "request refused"),
        }
        let mut response = (status, axum::Json(self.body())).into_response();
        if let Self::Unavailable { retry_after_secs, .. } | Self::TooManyRequests { retry_after_secs, .. } = &self {
            response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(*retry_after_secs));
        }
        response
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quoted_client_data_is_clipped() {
        let long = "A".repeat(5000);
        let m = clip_quoted(&format!("invalid type: string \"{long}\", expected f64"));
        assert_eq!(m, format!("invalid type: string \"{}…\", expected f64", "A".repeat(32)));
        assert_eq!(clip_quoted("unknown part \"x\""), "unknown part \"x\"");
        assert!(clip_quoted(&"b".repeat(5000)).chars().count() <= MAX_MESSAGE_CHARS + 1);
        let huge = format!("near ({}) must be smaller than far (2)", 1e308);
        assert_eq!(
            clip_quoted(&huge),
            format!("near ({}…) must be smaller than far (2)", "1".to_owned() + &"0".repeat(31))
        );
        assert_eq!(clip_quoted("sources[12].camera, 1920x1080"), "sources[12].camera, 1920x1080");
    }
}
