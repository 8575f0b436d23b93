//! The HTTP side: upload a capture once as a scene (`PUT /v1/scenes/{id}`, multipart), render
//! views of it (`POST /v1/scenes/{id}/render`, JSON). The id is the caller's
//! ([`Upload::scene_id`], `--scene-id`) or else derived from what is uploaded (cameras, depth
//! range, background, image bytes), so the same capture always has the same id: behind a proxy
//! that routes scenes by the hash of their id, an upload and every render of it, and an upload
//! again after a miss, reach the same replica. 503/429 are retried after their `Retry-After`; a
//! render answered 404 with the server's hint `reupload` (the scene expired, was evicted, or its
//! server restarted or is gone) uploads the scene again under the same id, once, and retries.
//! Server errors come back as [`Error::Server`] with the server's own code, message, field and
//! hint.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use base64::Engine;
use serde::Deserialize;
use serde_json::{json, Value};
use sha2::{Digest, Sha256};

use crate::error::{read_bytes, Error, Result};
use scnerf_capture::camera::Camera;
use scnerf_capture::readers::{Capture, CapturedView};
use scnerf_capture::upload::image_bytes;
use scnerf_capture::wire::WireCamera;

/// The server's limits (`GET /v1/limits`): what it accepts, read before anything is uploaded.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq, Eq)]
pub struct Limits {
    pub max_source_pixels: u64,
    pub max_target_pixels: u64,
    pub max_scene_views: usize,
    pub max_body_bytes: usize,
    pub max_capture_bytes: usize,
}

/// Header in which the server names the sources it chose for a view ("i,j,k", capture order).
pub const SOURCES_HEADER: &str = "x-scnerf-sources";

/// The server's `hint` on a 404 for a scene it does not hold: upload it again.
pub const HINT_REUPLOAD: &str = "reupload";

/// The views of a scene and what the server needs with them; kept to upload again.
#[derive(Debug, Clone)]
pub struct Upload {
    /// The scene id to PUT under; `None`: derived from the content ([`content_id`]).
    pub scene_id: Option<String>,
    pub sources: Vec<CapturedView>,
    pub near: f64,
    pub far: f64,
    pub background: [f64; 3],
}

impl Upload {
    /// `views` of `capture`, in that order (the first is the reference when there are 3).
    pub fn new(capture: &Capture, views: &[&CapturedView]) -> Upload {
        Upload {
            scene_id: None,
            sources: views.iter().map(|&v| v.clone()).collect(),
            near: capture.near,
            far: capture.far,
            background: capture.background,
        }
    }
}

#[derive(Debug)]
pub struct Scene {
    pub id: String,
    upload: Upload,
}

#[derive(Debug)]
pub struct Rendered {
    pub width: u32,
    pub height: u32,
    pub rgb_png: Vec<u8>,
    /// Row-major z-depth, when asked for.
    pub depth: Option<Vec<f32>>,
    /// The server's own stage timings ("renderer", "total", ...).
    pub timings_ms: BTreeMap<String, f64>,
    /// Indices into the scene's sources, when the server names them.
    pub sources: Option<Vec<usize>>,
    /// How the view was sampled and the network samples per pixel, when the server says.
    pub sampling: Option<(String, f64)>,
}

pub struct Client {
    agent: ureq::Agent,
    base: String,
    token: Option<String>,
    /// 503/429 answers retried per request before giving up.
    pub max_retries: u32,
    notice: Box<dyn Fn(&str) + Send + Sync>,
    /// Read once, by [`Client::limits`]; uploads are checked against them.
    limits: std::sync::OnceLock<Limits>,
    /// How views are sampled (`full`, `guided`); `None`: the server's default.
    sampling: Option<String>,
    /// The model scenes are uploaded to and rendered with (`GET /v1/models`); `None`: the
    /// server's default.
    model: Option<String>,
}

impl Client {
    pub fn new(base: &str, token: Option<String>) -> Client {
        // Status codes are handled here, with the server's error body.
        let agent = ureq::Agent::config_builder().http_status_as_error(false).build().into();
        Client {
            agent,
            base: base.trim_end_matches('/').to_string(),
            token,
            max_retries: 30,
            notice: Box::new(|m| eprintln!("{m}")),
            limits: std::sync::OnceLock::new(),
            sampling: None,
            model: None,
        }
    }

    /// Uploads scenes to and renders them with this model (the server checks the name).
    pub fn with_model(mut self, model: Option<String>) -> Client {
        self.model = model;
        self
    }

    /// Renders sample views this way (`full` or `guided`; the server checks the name).
    pub fn with_sampling(mut self, sampling: Option<String>) -> Client {
        self.sampling = sampling;
        self
    }

    /// Where waits and re-uploads are reported (stderr by default; the progress bar's line).
    pub fn with_notice(mut self, notice: impl Fn(&str) + Send + Sync + 'static) -> Client {
        self.notice = Box::new(notice);
        self
    }

    pub fn create_scene(&self, upload: Upload) -> Result<Scene> {
        let id = self.upload(&upload)?;
        Ok(Scene { id, upload })
    }

    /// The server's limits (`GET /v1/limits`), asked once.
    pub fn limits(&self) -> Result<Limits> {
        if let Some(limits) = self.limits.get() {
            return Ok(*limits);
        }
        let reply = self.send("GET", "/v1/limits", None)?;
        let limits: Limits = parse_json(&reply.body, "/v1/limits")?;
        Ok(*self.limits.get_or_init(|| limits))
    }

    /// PUTs the scene under its id (the caller's, else the content's); returns that id.
    fn upload(&self, upload: &Upload) -> Result<String> {
        // A `Value`, whose keys are sorted: the bytes, and so the content's id, stay those of
        // earlier versions of the client.
        let sources: Vec<Value> =
            upload.sources.iter().map(|v| json!({ "camera": WireCamera::from(&v.camera) })).collect();
        let mut request = json!({
            "sources": sources, "near": upload.near, "far": upload.far, "background": upload.background,
        });
        // Only when named: an upload to the default model keeps the id earlier clients gave it,
        // and one to another model gets an id of its own (a scene belongs to one model).
        if let Some(model) = &self.model {
            request["model"] = json!(model);
        }
        let mut parts = vec![Part { name: "request".into(), file: None, bytes: request.to_string().into_bytes() }];
        for (i, view) in upload.sources.iter().enumerate() {
            let photo = read_bytes(&view.image_path)?;
            let bytes = image_bytes(view, &photo, upload.background)?.into_owned();
            parts.push(Part { name: format!("source_{i}"), file: Some(view.image_path.clone()), bytes });
        }
        let id = upload.scene_id.clone().unwrap_or_else(|| content_id(&parts));
        let path = format!("/v1/scenes/{id}");
        let (content_type, body) = multipart(&parts);
        if let Some(limits) = self.limits.get().filter(|l| body.len() > l.max_body_bytes) {
            return Err(Error::Usage(format!(
                "the upload of {} views is {:.1} MiB, more than the server takes ({:.1} MiB, its --max-body-bytes): \
                 upload fewer views (--max-views) or smaller images (--downscale)",
                upload.sources.len(),
                body.len() as f64 / 1048576.0,
                limits.max_body_bytes as f64 / 1048576.0
            )));
        }
        let response = match self.send("PUT", &path, Some((&content_type, &body))) {
            Err(Error::Http { url, message }) => return Err(self.refusal_during_upload(&path, &parts[0], url, message)),
            other => other?,
        };
        #[derive(Deserialize)]
        struct Created {
            scene_id: String,
        }
        let created: Created = parse_json(&response.body, &path)?;
        Ok(created.scene_id)
    }

    /// An upload whose connection broke: if the server refused it from its `request` part (a
    /// server older than the one that reads a refused body to its end, or one that refuses
    /// before reading it, as for a wrong token), the `request` part alone gets the same refusal
    /// back; anything else about it (its images are missing, of course) keeps the network error.
    fn refusal_during_upload(&self, path: &str, request: &Part, url: String, message: String) -> Error {
        let (content_type, body) = multipart(std::slice::from_ref(request));
        match self.send("PUT", path, Some((&content_type, &body))) {
            Err(Error::Server { field: Some(f), .. }) if f.starts_with("source_") => Error::Http { url, message },
            Err(refusal @ Error::Server { .. }) => refusal,
            _ => Error::Http { url, message },
        }
    }

    /// Renders `target`; `depth` asks for the depth map too.
    pub fn render(&self, scene: &mut Scene, target: &Camera, depth: bool) -> Result<Rendered> {
        let outputs: &[&str] = if depth { &["rgb", "depth"] } else { &["rgb"] };
        let mut body = json!({ "target": WireCamera::from(target), "outputs": outputs });
        if let Some(sampling) = &self.sampling {
            body["sampling"] = json!(sampling);
        }
        // The scene's model already; named again, a scene of another model is refused (409).
        if let Some(model) = &self.model {
            body["model"] = json!(model);
        }
        let body = body.to_string();
        let mut uploaded_again = false;
        loop {
            let path = format!("/v1/scenes/{}/render", scene.id);
            match self.send("POST", &path, Some(("application/json", body.as_bytes()))) {
                Err(Error::Server { status: 404, hint: Some(hint), .. })
                    if hint == HINT_REUPLOAD && !uploaded_again =>
                {
                    (self.notice)("the server no longer has the scene: uploading the capture again");
                    scene.id = self.upload(&scene.upload)?;
                    uploaded_again = true;
                }
                Err(e) => return Err(e),
                Ok(response) => return parse_rendered(&response, &path),
            }
        }
    }

    /// Sends `method` with `body` (content type and bytes), waiting out 503/429 answers; any
    /// other error status becomes [`Error::Server`].
    fn send(&self, method: &str, path: &str, body: Option<(&str, &[u8])>) -> Result<Reply> {
        let url = format!("{}{path}", self.base);
        let mut retries = 0;
        loop {
            let mut request =
                ureq::http::Request::builder().method(method).uri(&url).header("accept", "application/json");
            if let Some((content_type, _)) = body {
                request = request.header("content-type", content_type);
            }
            if let Some(token) = &self.token {
                request = request.header("authorization", format!("Bearer {token}"));
            }
            let request = request
                .body(body.map_or(&[][..], |(_, bytes)| bytes))
                .map_err(|e| Error::Http { url: url.clone(), message: e.to_string() })?;
            let mut response =
                self.agent.run(request).map_err(|e| Error::Http { url: url.clone(), message: e.to_string() })?;
            let status = response.status().as_u16();
            let header = |name: &str| response.headers().get(name).and_then(|v| v.to_str().ok()).map(str::to_string);
            let (retry_after, sources) = (header("retry-after"), header(SOURCES_HEADER));
            let bytes = response
                .body_mut()
                .with_config()
                .limit(u64::MAX)
                .read_to_vec()
                .map_err(|e| Error::Http { url: url.clone(), message: format!("reading the response: {e}") })?;
            if status < 400 {
                return Ok(Reply { body: bytes, sources });
            }
            let error = server_error(status, &bytes);
            if (status == 503 || status == 429) && retries < self.max_retries {
                retries += 1;
                // Retry-After in seconds (the server's form); an HTTP date or nothing: 1 s
                let wait = retry_after.and_then(|v| v.trim().parse::<u64>().ok()).unwrap_or(1);
                (self.notice)(&format!("{error}; retrying in {wait} s ({retries}/{})", self.max_retries));
                std::thread::sleep(Duration::from_secs(wait));
                continue;
            }
            return Err(error);
        }
    }
}

struct Reply {
    body: Vec<u8>,
    sources: Option<String>,
}

/// The server's `{"error": {"code", "message", "field", "hint"}}`, or the status and start of the
/// body.
fn server_error(status: u16, body: &[u8]) -> Error {
    #[derive(Deserialize)]
    struct Body {
        error: Detail,
    }
    #[derive(Deserialize)]
    struct Detail {
        code: String,
        message: String,
        field: Option<String>,
        #[serde(default)]
        hint: Option<String>,
    }
    match serde_json::from_slice::<Body>(body) {
        Ok(Body { error: Detail { code, message, field, hint } }) => {
            Error::Server { status, code, message, field, hint }
        }
        Err(_) => {
            let text: String = String::from_utf8_lossy(body).chars().take(200).collect();
            Error::Server { status, code: format!("http_{status}"), message: text, field: None, hint: None }
        }
    }
}

fn parse_json<T: serde::de::DeserializeOwned>(body: &[u8], what: &str) -> Result<T> {
    serde_json::from_slice(body)
        .map_err(|e| Error::Http { url: what.into(), message: format!("unexpected answer: {e}") })
}

fn parse_rendered(reply: &Reply, path: &str) -> Result<Rendered> {
    #[derive(Deserialize)]
    struct Body {
        width: u32,
        height: u32,
        rgb: Option<Data>,
        depth: Option<Data>,
        #[serde(default)]
        timings_ms: BTreeMap<String, f64>,
        sources: Option<Vec<usize>>,
        sampling: Option<String>,
        samples_per_ray: Option<f64>,
    }
    #[derive(Deserialize)]
    struct Data {
        data: String,
    }
    let body: Body = parse_json(&reply.body, path)?;
    let decode = |d: &Data| {
        base64::engine::general_purpose::STANDARD
            .decode(&d.data)
            .map_err(|e| Error::Response { context: path.into(), message: format!("bad base64: {e}") })
    };
    let rgb_png = decode(
        body.rgb
            .as_ref()
            .ok_or_else(|| Error::Http { url: path.into(), message: "the answer has no rgb image".into() })?,
    )?;
    let depth = match &body.depth {
        Some(d) => Some(decode(d)?.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()),
        None => None,
    };
    let from_header =
        reply.sources.as_deref().and_then(|s| s.split(',').map(|i| i.trim().parse().ok()).collect::<Option<Vec<_>>>());
    Ok(Rendered {
        width: body.width,
        height: body.height,
        rgb_png,
        depth,
        timings_ms: body.timings_ms,
        sources: from_header.or(body.sources),
        sampling: body.sampling.zip(body.samples_per_ray),
    })
}

struct Part {
    name: String,
    file: Option<PathBuf>,
    bytes: Vec<u8>,
}

/// The scene id of an upload that was not given one: `cap-` and 32 hex digits of the SHA-256 of
/// the parts (the request JSON, then each image), each preceded by its length.
fn content_id(parts: &[Part]) -> String {
    let mut hash = Sha256::new();
    for part in parts {
        hash.update((part.bytes.len() as u64).to_le_bytes());
        hash.update(&part.bytes);
    }
    format!("cap-{}", hex::encode(&hash.finalize()[..16]))
}

/// multipart/form-data with a boundary that occurs in no part.
fn multipart(parts: &[Part]) -> (String, Vec<u8>) {
    let mut n: u64 = 0x5c0e_12f0;
    let boundary = loop {
        let b = format!("scnerf-{n:016x}");
        if !parts.iter().any(|p| p.bytes.windows(b.len()).any(|w| w == b.as_bytes())) {
            break b;
        }
        n = n.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    };
    let mut body = Vec::new();
    for p in parts {
        body.extend_from_slice(
            format!("--{boundary}\r\nContent-Disposition: form-data; name=\"{}\"", p.name).as_bytes(),
        );
        let content_type = match &p.file {
            Some(file) => {
                let name = file.file_name().map(|n| n.to_string_lossy().replace('"', "")).unwrap_or_default();
                body.extend_from_slice(format!("; filename=\"{name}\"").as_bytes());
                image_type(file)
            }
            None => "application/json",
        };
        body.extend_from_slice(format!("\r\nContent-Type: {content_type}\r\n\r\n").as_bytes());
        body.extend_from_slice(&p.bytes);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
    (format!("multipart/form-data; boundary={boundary}"), body)
}

fn image_type(path: &Path) -> &'static str {
    match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
        Some("jpg" | "jpeg") => "image/jpeg",
        _ => "image/png",
    }
}
