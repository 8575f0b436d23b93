//! Content negotiation: which body format came in (Content-Type) and which goes out (Accept).

use axum::http::{header, HeaderMap};

use crate::error::ApiError;
use crate::request::OutputSet;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RequestFormat {
    Multipart,
    Json,
    Protobuf,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResponseFormat {
    Png,
    Json,
    Protobuf,
}

impl ResponseFormat {
    pub fn content_type(self) -> &'static str {
        match self {
            ResponseFormat::Png => "image/png",
            ResponseFormat::Json => "application/json",
            ResponseFormat::Protobuf => "application/x-protobuf",
        }
    }
}

pub fn request_format(headers: &HeaderMap) -> Result<RequestFormat, ApiError> {
    let unsupported = |message: String| ApiError::UnsupportedMediaType { field: Some("content-type".into()), message };
    let raw = headers.get(header::CONTENT_TYPE).ok_or_else(|| {
        unsupported("missing Content-Type (multipart/form-data, application/json or application/x-protobuf)".into())
    })?;
    let mime: mime::Mime =
        raw.to_str().ok().and_then(|s| s.parse().ok()).ok_or_else(|| unsupported("unparsable Content-Type".into()))?;
    match (mime.type_().as_str(), mime.subtype().as_str()) {
        ("multipart", "form-data") => Ok(RequestFormat::Multipart),
        ("application", "json") => Ok(RequestFormat::Json),
        ("application", "x-protobuf" | "protobuf") => Ok(RequestFormat::Protobuf),
        _ => Err(unsupported(format!(
            "Content-Type {}/{} is not supported (multipart/form-data, application/json, application/x-protobuf)",
            mime.type_(),
            mime.subtype()
        ))),
    }
}

/// Picks the response format from Accept (highest q first, then order). Without Accept, or for
/// `*/*`, a request for RGB only gets a PNG and anything else JSON.
pub fn response_format(headers: &HeaderMap, outputs: OutputSet) -> Result<ResponseFormat, ApiError> {
    let default = if outputs == OutputSet::RGB { ResponseFormat::Png } else { ResponseFormat::Json };
    let Some(accept) = headers.get(header::ACCEPT) else {
        return Ok(default);
    };
    let accept =
        accept.to_str().map_err(|_| ApiError::malformed(Some("accept".to_string()), "Accept header is not ASCII"))?;
    let mut ranges: Vec<(f32, usize, String)> = accept
        .split(',')
        .enumerate()
        .filter_map(|(i, part)| {
            let mut it = part.split(';');
            let media = it.next()?.trim().to_ascii_lowercase();
            let q = it
                .filter_map(|p| p.trim().strip_prefix("q=").and_then(|q| q.trim().parse::<f32>().ok()))
                .next()
                .unwrap_or(1.0);
            (!media.is_empty() && q > 0.0).then_some((q, i, media))
        })
        .collect();
    ranges.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let chosen = ranges.iter().find_map(|(_, _, media)| match media.as_str() {
        "image/png" | "image/*" => Some(ResponseFormat::Png),
        "application/json" => Some(ResponseFormat::Json),
        "application/x-protobuf" | "application/protobuf" => Some(ResponseFormat::Protobuf),
        "*/*" => Some(default),
        _ => None,
    });
    let format = chosen.ok_or_else(|| ApiError::NotAcceptable {
        message: format!("cannot produce any of \"{accept}\" (image/png, application/json, application/x-protobuf)"),
    })?;
    if format == ResponseFormat::Png && outputs != OutputSet::RGB {
        return Err(ApiError::invalid(
            "outputs",
            "an image/png response carries only rgb; ask for application/json or application/x-protobuf to get depth or opacity",
        ));
    }
    Ok(format)
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    fn accept(v: &str) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(header::ACCEPT, HeaderValue::from_str(v).unwrap());
        h
    }

    const ALL: OutputSet = OutputSet { rgb: true, depth: true, opacity: true };

    #[test]
    fn picks_by_accept() {
        assert_eq!(response_format(&HeaderMap::new(), OutputSet::RGB).unwrap(), ResponseFormat::Png);
        assert_eq!(response_format(&HeaderMap::new(), ALL).unwrap(), ResponseFormat::Json);
        assert_eq!(response_format(&accept("*/*"), OutputSet::RGB).unwrap(), ResponseFormat::Png);
        assert_eq!(response_format(&accept("application/json"), OutputSet::RGB).unwrap(), ResponseFormat::Json);
        assert_eq!(response_format(&accept("application/x-protobuf"), ALL).unwrap(), ResponseFormat::Protobuf);
        assert_eq!(
            response_format(&accept("image/png;q=0.5, application/json"), OutputSet::RGB).unwrap(),
            ResponseFormat::Json
        );
        assert_eq!(response_format(&accept("text/html, image/*"), OutputSet::RGB).unwrap(), ResponseFormat::Png);
    }

    #[test]
    fn refuses_unproducible() {
        assert!(matches!(response_format(&accept("text/html"), OutputSet::RGB), Err(ApiError::NotAcceptable { .. })));
        assert!(matches!(
            response_format(&accept("image/png;q=0"), OutputSet::RGB),
            Err(ApiError::NotAcceptable { .. })
        ));
        assert!(matches!(response_format(&accept("image/png"), ALL), Err(ApiError::Invalid { .. })));
    }

    #[test]
    fn content_types() {
        let mut h = HeaderMap::new();
        assert!(request_format(&h).is_err());
        h.insert(header::CONTENT_TYPE, HeaderValue::from_static("application/json; charset=utf-8"));
        assert_eq!(request_format(&h).unwrap(), RequestFormat::Json);
        h.insert(header::CONTENT_TYPE, HeaderValue::from_static("multipart/form-data; boundary=x"));
        assert_eq!(request_format(&h).unwrap(), RequestFormat::Multipart);
        h.insert(header::CONTENT_TYPE, HeaderValue::from_static("text/plain"));
        assert!(matches!(request_format(&h), Err(ApiError::UnsupportedMediaType { .. })));
    }
}
