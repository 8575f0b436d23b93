//! Optional bearer-token authentication.
//!
//! With tokens configured, every route but `/healthz`, `/readyz`, `/metrics` and
//! `/openapi.json` needs `Authorization: Bearer <token>` (401 otherwise). Health checks stay open
//! for orchestrators, `/metrics` for scrapers (aggregate counts only: no scene data, no ids, no
//! tokens), and the OpenAPI document is public documentation.
//!
//! Only SHA-256 digests of the tokens are kept. A presented token is hashed and compared with
//! every digest in constant time (`subtle`), without stopping at the first match, so the time
//! taken reveals neither which token matched nor how much of it. The digest of the client's
//! token scopes its scenes (`Principal::owner`); the token itself is never stored or logged.

use std::path::Path;
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};
use subtle::{ConditionallySelectable, ConstantTimeEq};

use crate::cache::Owner;
use crate::error::ApiError;

/// Paths served without a token.
pub const PUBLIC_PATHS: [&str; 4] = ["/healthz", "/readyz", "/metrics", "/openapi.json"];

/// The authenticated client of a request, put in the request's extensions by `require_token`.
#[derive(Debug, Clone, Copy, Default)]
pub struct Principal {
    owner: Owner,
}

impl Principal {
    /// The key that scopes the client's scenes: a digest of its token, never the token.
    pub fn owner(&self) -> Owner {
        self.owner
    }
}

/// The accepted tokens, as digests. Empty: authentication is off.
#[derive(Clone, Default)]
pub struct Auth {
    digests: Vec<[u8; 32]>,
}

impl std::fmt::Debug for Auth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Auth({} tokens)", self.digests.len())
    }
}

fn digest(token: &[u8]) -> [u8; 32] {
    Sha256::digest(token).into()
}

impl Auth {
    pub fn disabled() -> Auth {
        Auth::default()
    }

    /// Tokens given directly (blank entries are ignored).
    pub fn from_tokens<S: AsRef<str>>(tokens: &[S]) -> Auth {
        let digests = tokens.iter().map(|t| t.as_ref().trim()).filter(|t| !t.is_empty()).map(|t| digest(t.as_bytes()));
        Auth { digests: digests.collect() }
    }

    /// Tokens from the command line plus a file of one token per line (`#` starts a comment).
    pub fn from_config(tokens: &[String], file: Option<&Path>) -> Result<Auth, String> {
        let mut all: Vec<String> = tokens.to_vec();
        if let Some(path) = file {
            let text = std::fs::read_to_string(path)
                .map_err(|e| format!("cannot read the token file {}: {e}", path.display()))?;
            all.extend(text.lines().map(str::trim).filter(|l| !l.starts_with('#')).map(str::to_string));
        }
        let auth = Auth::from_tokens(&all);
        if file.is_some() && !auth.enabled() {
            return Err("the token file holds no tokens (refusing to start without authentication)".into());
        }
        Ok(auth)
    }

    pub fn enabled(&self) -> bool {
        !self.digests.is_empty()
    }

    pub fn token_count(&self) -> usize {
        self.digests.len()
    }

    /// The digest of `presented` if it is one of the tokens. Constant time in the number and
    /// content of the tokens.
    fn check(&self, presented: &[u8]) -> Option<[u8; 32]> {
        let candidate = digest(presented);
        let mut found = subtle::Choice::from(0);
        for d in &self.digests {
            found |= d.ct_eq(&candidate);
        }
        let mut owner = [0u8; 32];
        for (o, c) in owner.iter_mut().zip(candidate) {
            o.conditional_assign(&c, found);
        }
        bool::from(found).then_some(owner)
    }
}

/// The token of an `Authorization: Bearer <token>` header (scheme case-insensitive).
fn bearer(req: &Request) -> Option<&[u8]> {
    let value = req.headers().get(header::AUTHORIZATION)?.as_bytes();
    let (scheme, token) = value.split_at_checked(7)?;
    (scheme.eq_ignore_ascii_case(b"bearer ") && !token.is_empty()).then_some(token)
}

fn unauthorized(message: &str) -> Response {
    let mut response = ApiError::Unauthorized { message: message.into() }.into_response();
    response
        .headers_mut()
        .insert(header::WWW_AUTHENTICATE, header::HeaderValue::from_static("Bearer realm=\"scnerf\""));
    response
}

/// Middleware: checks the bearer token and records the client as a `Principal`.
pub async fn require_token(State(auth): State<Arc<Auth>>, mut req: Request, next: Next) -> Response {
    if !auth.enabled() || PUBLIC_PATHS.contains(&req.uri().path()) {
        req.extensions_mut().insert(Principal::default());
        return next.run(req).await;
    }
    let owner = match bearer(&req) {
        None => return unauthorized("missing bearer token (Authorization: Bearer <token>)"),
        Some(token) => match auth.check(token) {
            None => return unauthorized("invalid bearer token"),
            Some(owner) => owner,
        },
    };
    req.extensions_mut().insert(Principal { owner: Some(owner) });
    next.run(req).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checks_tokens_and_scopes_by_digest() {
        let auth = Auth::from_tokens(&["alpha", " beta ", ""]);
        assert_eq!(auth.token_count(), 2);
        assert_eq!(auth.check(b"alpha"), Some(digest(b"alpha")));
        assert_eq!(auth.check(b"beta"), Some(digest(b"beta")));
        assert_ne!(auth.check(b"alpha"), auth.check(b"beta"));
        assert_eq!(auth.check(b"alph"), None);
        assert_eq!(auth.check(b"alphaa"), None);
        assert_eq!(auth.check(b""), None);
        assert!(!Auth::disabled().enabled());
        assert_eq!(format!("{auth:?}"), "Auth(2 tokens)", "tokens never appear in debug output");
    }

    #[test]
    fn parses_bearer_headers() {
        let req = |v: &str| Request::builder().header("authorization", v).body(axum::body::Body::empty()).unwrap();
        assert_eq!(bearer(&req("Bearer abc")), Some(&b"abc"[..]));
        assert_eq!(bearer(&req("bearer abc")), Some(&b"abc"[..]));
        assert_eq!(bearer(&req("Basic abc")), None);
        assert_eq!(bearer(&req("Bearer ")), None);
        assert_eq!(bearer(&req("Bear")), None);
    }

    #[test]
    fn token_file() {
        let dir = std::env::temp_dir().join(format!("scnerf-auth-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("tokens");
        std::fs::write(&file, "# clients\nfirst\n\nsecond\n").unwrap();
        let auth = Auth::from_config(&["cli".into()], Some(&file)).unwrap();
        assert_eq!(auth.token_count(), 3);
        std::fs::write(&file, "# nobody\n").unwrap();
        assert!(Auth::from_config(&[], Some(&file)).is_err());
        assert!(Auth::from_config(&[], Some(&dir.join("missing"))).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
