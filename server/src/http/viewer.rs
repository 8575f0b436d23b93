//! The browser viewer. `GET /` serves a page (plain HTML, ES modules and CSS from
//! `server/viewer/`, embedded in the binary: no build step, nothing fetched from elsewhere) that
//! drives the scenes API; `GET /viewer/example/{file}` serves the example scene it opens on, read
//! from `--viewer-example`.
//!
//! These routes sit outside the API's layers (no token, no request metrics): a browser cannot
//! attach a bearer token to a page load, and the page holds no data of its own. Its API calls
//! carry the token the user types, and the API routes check it as for any other client.

use std::path::PathBuf;
use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;

use crate::config::Config;
use crate::error::ApiError;

/// The example scene the page opens on, relative to the repository root. The one place that
/// names it: `--viewer-example` overrides it, the page only knows `/viewer/example/`.
pub const DEFAULT_EXAMPLE: &str = "examples/tabletop";

/// `<repo>/DEFAULT_EXAMPLE`, resolved when the binary is compiled (as the default bundle is).
pub fn default_example_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/..")).join(DEFAULT_EXAMPLE)
}

/// The page and its modules: URL path, content type, body.
const ASSETS: [(&str, &str, &str); 11] = [
    ("/", HTML, include_str!("../../viewer/index.html")),
    ("/viewer/viewer.css", CSS, include_str!("../../viewer/viewer.css")),
    ("/viewer/main.js", JS, include_str!("../../viewer/main.js")),
    ("/viewer/api.js", JS, include_str!("../../viewer/api.js")),
    ("/viewer/camera.js", JS, include_str!("../../viewer/camera.js")),
    ("/viewer/controls.js", JS, include_str!("../../viewer/controls.js")),
    ("/viewer/overview.js", JS, include_str!("../../viewer/overview.js")),
    ("/viewer/progressive.js", JS, include_str!("../../viewer/progressive.js")),
    ("/viewer/images.js", JS, include_str!("../../viewer/images.js")),
    ("/viewer/capture.js", JS, include_str!("../../viewer/capture.js")),
    ("/viewer/scene.js", JS, include_str!("../../viewer/scene.js")),
];
const HTML: &str = "text/html; charset=utf-8";
const CSS: &str = "text/css; charset=utf-8";
const JS: &str = "text/javascript; charset=utf-8";

/// The browser refuses anything the page would load from elsewhere (scripts, styles, fetches,
/// images): "nothing fetched from outside the server" holds even if a bug tried.
const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
     img-src 'self' blob: data:; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// Adds the viewer's routes to `app` unless `--viewer off`.
pub fn mount(app: Router, config: &Config) -> Router {
    if !config.viewer {
        return app;
    }
    let example = config.viewer_example.clone().unwrap_or_else(default_example_dir);
    app.merge(routes(example))
}

/// The page, its assets and the example files of `example_dir`.
pub fn routes(example_dir: PathBuf) -> Router {
    let mut router = Router::new();
    for (path, content_type, body) in ASSETS {
        router = router.route(path, get(move || async move { asset(content_type, body) }));
    }
    router
        .route("/viewer/example/{file}", get(example_file))
        .method_not_allowed_fallback(|| async { ApiError::MethodNotAllowed.into_response() })
        .with_state(Arc::new(example_dir))
}

fn asset(content_type: &'static str, body: &'static str) -> Response {
    let mut response = body.into_response();
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    headers.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CONTENT_SECURITY_POLICY));
    headers.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    headers.insert(header::REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
    // Revalidate every load: a rebuilt server may embed different assets at the same URLs.
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    response
}

/// The content type of a file the page may fetch from the example folder: `request.json` and
/// `source_N.png|jpg|jpeg`. Nothing else in that folder is served.
fn example_content_type(name: &str) -> Option<&'static str> {
    if name == "request.json" {
        return Some("application/json");
    }
    let (stem, ext) = name.strip_prefix("source_")?.split_once('.')?;
    if stem.is_empty() || !stem.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    match ext {
        "png" => Some("image/png"),
        "jpg" | "jpeg" => Some("image/jpeg"),
        _ => None,
    }
}

async fn example_file(State(dir): State<Arc<PathBuf>>, Path(name): Path<String>) -> Result<Response, ApiError> {
    // The name is echoed in the message: keep a hostile one short.
    let shown: String = name.chars().take(64).collect();
    let not_found = || ApiError::NotFound { path: format!("/viewer/example/{shown}") };
    let content_type = example_content_type(&name).ok_or_else(not_found)?;
    let path = dir.join(&name);
    let read = tokio::task::spawn_blocking(move || std::fs::read(path))
        .await
        .map_err(|e| ApiError::Internal(format!("reading an example file failed: {e}")))?;
    let bytes = match read {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(not_found()),
        // A broken example folder (not a folder, unreadable): the operator's log says where and
        // why; the client learns that the file is not served, not the server's paths.
        Err(e) => {
            tracing::warn!(dir = %dir.display(), file = %shown, error = %e, "the viewer's example cannot be read");
            return Err(not_found());
        }
    };
    // nosniff: the example folder is the operator's; a file served as an image stays an image.
    let headers = [
        (header::CONTENT_TYPE, content_type),
        (header::CACHE_CONTROL, "no-cache"),
        (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
    ];
    Ok((StatusCode::OK, headers, bytes).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::body::Body;
    use axum::http::Request;
    use tower::ServiceExt;

    async fn get(app: &Router, method: &str, uri: &str) -> (StatusCode, String, Vec<u8>) {
        let request = Request::builder().method(method).uri(uri).body(Body::empty()).unwrap();
        let response = app.clone().oneshot(request).await.unwrap();
        let status = response.status();
        if status == StatusCode::OK {
            assert_eq!(response.headers()[header::X_CONTENT_TYPE_OPTIONS], "nosniff", "{uri}");
        }
        let content_type =
            response.headers().get(header::CONTENT_TYPE).map_or("", |v| v.to_str().unwrap_or("")).to_string();
        let body = http_body_util::BodyExt::collect(response.into_body()).await.unwrap().to_bytes().to_vec();
        (status, content_type, body)
    }

    #[tokio::test]
    async fn serves_the_page_its_modules_and_the_example() {
        let app = routes(default_example_dir());
        let (status, content_type, body) = get(&app, "GET", "/").await;
        assert_eq!((status, content_type.as_str()), (StatusCode::OK, HTML));
        assert!(String::from_utf8(body).unwrap().contains("/viewer/main.js"));
        for (path, content_type, _) in ASSETS {
            assert_eq!(get(&app, "GET", path).await.1, content_type, "{path}");
        }
        let (status, content_type, body) = get(&app, "GET", "/viewer/example/request.json").await;
        assert_eq!((status, content_type.as_str()), (StatusCode::OK, "application/json"));
        assert!(serde_json::from_slice::<serde_json::Value>(&body).unwrap()["sources"].is_array());
        let (status, content_type, body) = get(&app, "GET", "/viewer/example/source_0.png").await;
        assert_eq!((status, content_type.as_str()), (StatusCode::OK, "image/png"));
        assert!(body.starts_with(b"\x89PNG"));
    }

    #[tokio::test]
    async fn serves_nothing_else_and_answers_errors_in_json() {
        let app = routes(default_example_dir());
        let refused = ["README.md", "..%2Fregression.json", "source_9.png"];
        for uri in refused.map(|name| format!("/viewer/example/{name}")) {
            let (status, content_type, body) = get(&app, "GET", &uri).await;
            assert_eq!((status, content_type.as_str()), (StatusCode::NOT_FOUND, "application/json"), "{uri}");
            let error: crate::error::ErrorBody = serde_json::from_slice(&body).unwrap();
            assert_eq!(error.error.code, "not_found");
        }
        let (status, _, _) = get(&app, "POST", "/").await;
        assert_eq!(status, StatusCode::METHOD_NOT_ALLOWED);
        let missing = routes(PathBuf::from("/nonexistent/example"));
        assert_eq!(get(&missing, "GET", "/viewer/example/request.json").await.0, StatusCode::NOT_FOUND);
        // A file where the folder should be, and a folder where a file should be: 404 without
        // the server's paths, not a 500 that shows them.
        let scratch = std::env::temp_dir().join(format!("scnerf-viewer-{}", std::process::id()));
        std::fs::create_dir_all(scratch.join("folder/request.json")).unwrap();
        std::fs::write(scratch.join("file"), b"not a folder").unwrap();
        for broken in [scratch.join("file"), scratch.join("folder")] {
            let (status, _, body) = get(&routes(broken.clone()), "GET", "/viewer/example/request.json").await;
            let body = String::from_utf8(body).unwrap();
            assert_eq!(status, StatusCode::NOT_FOUND, "{broken:?}: {body}");
            assert!(!body.contains(scratch.to_str().unwrap()), "{body}");
        }
        std::fs::remove_dir_all(&scratch).unwrap();
    }

    #[tokio::test]
    async fn mounted_unless_switched_off() {
        use clap::Parser;
        let off = Config::try_parse_from(["scnerf-server", "--viewer", "off"]).unwrap();
        assert_eq!(get(&mount(Router::new(), &off), "GET", "/").await.0, StatusCode::NOT_FOUND);
        let on = Config::try_parse_from(["scnerf-server", "--viewer-example", "/nonexistent"]).unwrap();
        let app = mount(Router::new(), &on);
        assert_eq!(get(&app, "GET", "/").await.0, StatusCode::OK);
        assert_eq!(get(&app, "GET", "/viewer/example/request.json").await.0, StatusCode::NOT_FOUND);
    }

    #[test]
    fn example_files_by_name() {
        assert_eq!(example_content_type("request.json"), Some("application/json"));
        assert_eq!(example_content_type("source_12.jpg"), Some("image/jpeg"));
        assert_eq!(example_content_type("source_.png"), None);
        assert_eq!(example_content_type("source_1.png.bak"), None);
        assert_eq!(example_content_type("source_-1.png"), None);
        assert_eq!(example_content_type("target_truth.png"), None);
    }
}
