//! What a JSON document must pass before and while it is parsed: its size, its nesting depth
//! (checked by a linear scan, before the recursive parser sees it), one document and nothing
//! after it; a parse error names the offending field.

use crate::error::ApiError;

/// Parses a JSON document into `T`, naming the offending field on failure. The nesting depth is
/// checked first (a linear scan), so deeply nested input never reaches the recursive parser.
/// `root` names the whole document in errors about it (`body`, or the multipart part `request`).
pub fn parse_json<T: serde::de::DeserializeOwned>(
    body: &[u8],
    max_depth: usize,
    what: &str,
    root: &str,
) -> Result<T, ApiError> {
    check_json_depth(body, max_depth, root)?;
    let mut de = serde_json::Deserializer::from_slice(body);
    let value = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let message = e.inner().to_string();
        let field = error_field(&e.path().to_string(), &message).unwrap_or_else(|| root.to_string());
        ApiError::malformed(Some(field), format!("invalid JSON {what}: {message}"))
    })?;
    // One document, nothing after it (serde stops at the end of the first value).
    de.end().map_err(|e| ApiError::malformed(Some(root.to_string()), format!("invalid JSON {what}: {e}")))?;
    Ok(value)
}

/// The field a serde error is about: its path, completed with the name of a missing field
/// (serde reports those at the enclosing object). `None`: the document as a whole.
fn error_field(path: &str, message: &str) -> Option<String> {
    // serde_path_to_error writes `?` for a segment it never learnt (input cut inside a key).
    let path = path.trim_end_matches('?').trim_end_matches('.');
    let path = if path == "." { "" } else { path };
    let missing = message.strip_prefix("missing field `").and_then(|m| m.split('`').next());
    match (path.is_empty(), missing) {
        (true, None) => None,
        (true, Some(name)) => Some(name.to_string()),
        (false, None) => Some(path.to_string()),
        (false, Some(name)) => Some(format!("{path}.{name}")),
    }
}

/// Refuses JSON nested deeper than `max_depth` arrays/objects (brackets inside strings do not
/// count). Malformed input passes through: the parser reports it with a better message.
fn check_json_depth(body: &[u8], max_depth: usize, root: &str) -> Result<(), ApiError> {
    let (mut depth, mut in_string, mut escaped) = (0usize, false, false);
    for &b in body {
        if in_string {
            match (escaped, b) {
                (true, _) => escaped = false,
                (false, b'\\') => escaped = true,
                (false, b'"') => in_string = false,
                _ => {}
            }
            continue;
        }
        match b {
            b'"' => in_string = true,
            b'[' | b'{' => {
                depth += 1;
                if depth > max_depth {
                    return Err(ApiError::malformed(
                        Some(root.to_string()),
                        format!("JSON nested deeper than the limit of {max_depth} levels"),
                    ));
                }
            }
            b']' | b'}' => depth = depth.saturating_sub(1),
            _ => {}
        }
    }
    Ok(())
}

/// Refuses a JSON document (without images) larger than the limit, naming where it came from.
pub fn check_json_size(body: &[u8], limit: usize, field: Option<&str>) -> Result<(), ApiError> {
    if body.len() > limit {
        return Err(ApiError::TooLarge {
            field: field.map(str::to_string),
            message: format!("JSON document of {} bytes exceeds the limit of {limit} bytes", body.len()),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_depth_counts_brackets_outside_strings() {
        assert!(check_json_depth(br#"{"a": [[1], {"b": 2}]}"#, 3, "body").is_ok());
        assert!(check_json_depth(br#"{"a": [[1], {"b": 2}]}"#, 2, "body").is_err());
        assert!(check_json_depth(br#"{"a": "[[[[[[\"[[[["}"#, 1, "body").is_ok());
        let deep = "[".repeat(100_000);
        let err = check_json_depth(deep.as_bytes(), 16, "request").unwrap_err();
        assert_eq!(err.field(), Some("request"));
    }

    #[test]
    fn serde_errors_name_the_field() {
        assert_eq!(error_field(".", "missing field `near`"), Some("near".into()));
        assert_eq!(error_field("target.pose", "missing field `axes`"), Some("target.pose.axes".into()));
        assert_eq!(error_field("sources[1]", "invalid type"), Some("sources[1]".into()));
        assert_eq!(error_field(".", "expected value"), None);
        assert_eq!(error_field("sources[0].camera.?", "EOF while parsing"), Some("sources[0].camera".into()));
    }
}
