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

impl ResponseFormat {
    /// The media types (type, subtype) that name the format.
    fn media_types(self) -> &'static [(&'static str, &'static str)] {
        match self {
            ResponseFormat::Png => &[("image", "png")],
            ResponseFormat::Json => &[("application", "json")],
            ResponseFormat::Protobuf => &[("application", "x-protobuf"), ("application", "protobuf")],
        }
    }
}

/// One media range of an Accept header, with its weight and its place in the header.
#[derive(Debug)]
struct MediaRange {
    kind: String,
    subtype: String,
    q: f32,
    position: usize,
}

impl MediaRange {
    /// How specific the range is for `media` (2: the type itself, 1: `type/*`, 0: `*/*`), or
    /// `None` when it does not match it.
    fn specificity(&self, (kind, subtype): (&str, &str)) -> Option<u8> {
        match (self.kind.as_str(), self.subtype.as_str()) {
            ("*", "*") => Some(0),
            (k, "*") if k == kind => Some(1),
            (k, s) if k == kind && s == subtype => Some(2),
            _ => None,
        }
    }
}

/// Picks the response format from Accept as RFC 9110 (12.5.1) says: each format gets the weight
/// of the most specific media range that matches it (`image/png;q=0` refuses PNG whatever
/// `*/*` says); the heaviest wins, then the one named first, then the server's preference.
/// Without Accept, or by `*/*` alone, a request for RGB only gets a PNG and anything else JSON.
/// A PNG carries RGB alone, so it is no candidate for other outputs: 422 when it was the only
/// acceptable format.
pub fn response_format(headers: &HeaderMap, outputs: OutputSet) -> Result<ResponseFormat, ApiError> {
    use ResponseFormat::{Json, Png, Protobuf};
    let rgb_only = outputs == OutputSet::RGB;
    let Some(accept) = headers.get(header::ACCEPT) else {
        return Ok(if rgb_only { Png } else { Json });
    };
    let accept =
        accept.to_str().map_err(|_| ApiError::malformed(Some("accept".to_string()), "Accept header is not ASCII"))?;
    let ranges = media_ranges(accept)?;
    let preference = if rgb_only { [Png, Json, Protobuf] } else { [Json, Protobuf, Png] };
    let weighed = preference.map(|format| (format, weight(&ranges, format)));
    let acceptable = |format: &ResponseFormat| rgb_only || *format != Png;
    // `min_by` keeps the first of equals: the server's preference.
    let best = weighed
        .iter()
        .filter(|(format, (q, _))| acceptable(format) && *q > 0.0)
        .min_by(|(_, (qa, pa)), (_, (qb, pb))| qb.total_cmp(qa).then(pa.cmp(pb)));
    match best {
        Some((format, _)) => Ok(*format),
        None if weighed.iter().any(|(format, (q, _))| *format == Png && *q > 0.0) => Err(ApiError::invalid(
            "outputs",
            "an image/png response carries only rgb; ask for application/json or application/x-protobuf to get depth or opacity",
        )),
        None => Err(ApiError::NotAcceptable {
            message: format!("cannot produce any of \"{accept}\" (image/png, application/json, application/x-protobuf)"),
        }),
    }
}

/// The weight and header position of the most specific range matching `format` (0: none does).
fn weight(ranges: &[MediaRange], format: ResponseFormat) -> (f32, usize) {
    format
        .media_types()
        .iter()
        .filter_map(|&media| ranges.iter().filter_map(|r| Some((r.specificity(media)?, r))).max_by_key(|(s, _)| *s))
        .max_by_key(|(s, _)| *s)
        .map_or((0.0, usize::MAX), |(_, r)| (r.q, r.position))
}

/// The media ranges of an Accept header; a weight that is not a number in [0, 1] is refused.
fn media_ranges(accept: &str) -> Result<Vec<MediaRange>, ApiError> {
    let malformed = |message: String| ApiError::malformed(Some("accept".to_string()), message);
    let mut ranges = Vec::new();
    for (position, element) in accept.split(',').enumerate() {
        let mut params = element.split(';');
        let media = params.next().unwrap_or_default().trim().to_ascii_lowercase();
        if media.is_empty() {
            continue; // RFC 9110 5.6.1: empty list elements do not count
        }
        let (kind, subtype) = media
            .split_once('/')
            .ok_or_else(|| malformed(format!("\"{media}\" is not a media range (type/subtype)")))?;
        let q = params
            .filter_map(|p| p.trim().strip_prefix("q=").or_else(|| p.trim().strip_prefix("Q=")))
            .map(|q| {
                q.parse::<f32>()
                    .ok()
                    .filter(|q| (0.0..=1.0).contains(q))
                    .ok_or_else(|| malformed(format!("weight q={q} is not a number in [0, 1]")))
            })
            .next()
            .transpose()?
            .unwrap_or(1.0);
        ranges.push(MediaRange { kind: kind.to_string(), subtype: subtype.to_string(), q, position });
    }
    Ok(ranges)
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

    /// RFC 9110 12.5.1: the most specific range decides a format's weight, and q=0 refuses it.
    #[test]
    fn the_most_specific_range_decides_and_zero_refuses() {
        assert_eq!(response_format(&accept("image/png;q=0, */*"), OutputSet::RGB).unwrap(), ResponseFormat::Json);
        assert_eq!(response_format(&accept("image/*;q=0, */*"), OutputSet::RGB).unwrap(), ResponseFormat::Json);
        assert_eq!(
            response_format(&accept("image/*;q=0, image/png"), OutputSet::RGB).unwrap(),
            ResponseFormat::Png,
            "image/png is more specific than image/*"
        );
        assert_eq!(response_format(&accept("*/*;q=0.1, application/json;q=0"), ALL).unwrap(), ResponseFormat::Protobuf);
        assert_eq!(response_format(&accept("application/*"), ALL).unwrap(), ResponseFormat::Json);
        assert!(matches!(
            response_format(&accept("*/*, image/png;q=0, application/*;q=0"), OutputSet::RGB),
            Err(ApiError::NotAcceptable { .. })
        ));
    }

    /// A PNG carries RGB alone: for other outputs the next acceptable format is taken.
    #[test]
    fn png_is_no_candidate_for_depth_or_opacity() {
        let depth = OutputSet { rgb: false, depth: true, opacity: false };
        assert_eq!(response_format(&accept("image/png, application/json;q=0.5"), depth).unwrap(), ResponseFormat::Json);
        assert_eq!(response_format(&accept("image/png, */*;q=0.1"), depth).unwrap(), ResponseFormat::Json);
        assert_eq!(response_format(&accept("*/*"), depth).unwrap(), ResponseFormat::Json);
    }

    #[test]
    fn malformed_weights_and_ranges_are_refused() {
        for bad in ["image/png;q=2", "image/png;q=-1", "image/png;q=high", "png"] {
            let err = response_format(&accept(bad), OutputSet::RGB).unwrap_err();
            assert!(matches!(&err, ApiError::Malformed { field: Some(f), .. } if f == "accept"), "{bad}: {err:?}");
        }
        assert_eq!(response_format(&accept("image/png;Q=0.5, ,"), OutputSet::RGB).unwrap(), ResponseFormat::Png);
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
