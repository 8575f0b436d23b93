//! Which sites may change state: a browser sends `Origin` (or at least `Sec-Fetch-Site`) with
//! every cross-site POST, PUT and DELETE, and a page of another site must not reload the models,
//! upload scenes or spend the executor through a visitor's browser, least of all on a server
//! without tokens. A state-changing request is let through when it comes from no browser (no
//! `Origin`, no `Sec-Fetch-Site`), from the server's own origin (its `Origin`'s host and port
//! are the `Host` it was sent to: the viewer's), or from an origin in `--allowed-origins`; any
//! other is refused with 403 naming the header. Reading (GET, HEAD, OPTIONS) is not concerned.

use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, Method};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use crate::error::ApiError;

/// The origins besides the server's own that may change state (`--allowed-origins`), as
/// `scheme://host[:port]`, compared without case and trailing `/`.
#[derive(Debug, Clone, Default)]
pub struct OriginPolicy {
    allowed: Vec<String>,
}

impl OriginPolicy {
    pub fn new(allowed: &[String]) -> OriginPolicy {
        OriginPolicy { allowed: allowed.iter().map(|o| canonical(o)).filter(|o| !o.is_empty()).collect() }
    }

    /// Why a state-changing request with `headers` is refused, if it is.
    fn refusal(&self, headers: &HeaderMap) -> Option<ApiError> {
        let Some(origin) = headers.get(header::ORIGIN) else {
            // Browsers that send no Origin still say where a request comes from.
            let site = headers.get("sec-fetch-site").map(|v| v.as_bytes());
            return match site {
                Some(b"cross-site") | Some(b"same-site") => {
                    Some(forbidden("sec-fetch-site", "a request from another site may not change this server's state"))
                }
                _ => None,
            };
        };
        let origin = canonical(origin.to_str().unwrap_or_default());
        let host = headers.get(header::HOST).and_then(|h| h.to_str().ok()).map(str::to_ascii_lowercase);
        let same_origin = authority(&origin).is_some_and(|a| Some(a) == host.as_deref());
        match same_origin || self.allowed.contains(&origin) {
            true => None,
            false => Some(forbidden(
                "origin",
                "this origin may not change this server's state: only the server's own origin and \
                 --allowed-origins may",
            )),
        }
    }
}

fn forbidden(field: &str, message: &str) -> ApiError {
    ApiError::Forbidden { field: field.to_string(), message: message.to_string() }
}

/// `origin` lowercased, without a trailing `/`.
fn canonical(origin: &str) -> String {
    origin.trim().trim_end_matches('/').to_ascii_lowercase()
}

/// The `host[:port]` of a `scheme://host[:port]` origin (none for `null` or anything else).
fn authority(origin: &str) -> Option<&str> {
    let (scheme, rest) = origin.split_once("://")?;
    (matches!(scheme, "http" | "https") && !rest.is_empty() && !rest.contains('/')).then_some(rest)
}

/// Middleware: refuses a state-changing request from a site the policy does not allow.
pub async fn check_origin(State(policy): State<Arc<OriginPolicy>>, req: Request, next: Next) -> Response {
    let reads = [Method::GET, Method::HEAD, Method::OPTIONS];
    if !reads.contains(req.method()) {
        if let Some(refusal) = policy.refusal(req.headers()) {
            return refusal.into_response();
        }
    }
    next.run(req).await
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut map = HeaderMap::new();
        for (name, value) in pairs {
            map.insert(*name, value.parse().unwrap());
        }
        map
    }

    #[test]
    fn own_origin_listed_origins_and_non_browsers_pass() {
        let policy = OriginPolicy::new(&["https://Studio.example.com/".to_string()]);
        let host = ("host", "scnerf.internal:8080");
        assert!(policy.refusal(&headers(&[host])).is_none(), "no browser");
        assert!(policy.refusal(&headers(&[host, ("origin", "http://scnerf.internal:8080")])).is_none());
        assert!(policy.refusal(&headers(&[host, ("origin", "https://studio.example.com")])).is_none());
        assert!(policy.refusal(&headers(&[host, ("sec-fetch-site", "same-origin")])).is_none());
        for origin in ["https://evil.example", "null", "http://scnerf.internal:8081", "http://scnerf.internal:8080/x"] {
            let refused = policy.refusal(&headers(&[host, ("origin", origin)])).unwrap();
            assert_eq!((refused.status().as_u16(), refused.field()), (403, Some("origin")), "{origin}");
        }
        let refused = policy.refusal(&headers(&[host, ("sec-fetch-site", "cross-site")])).unwrap();
        assert_eq!(refused.field(), Some("sec-fetch-site"));
    }
}
