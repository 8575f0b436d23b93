//! POST /v1/render: body -> validated request -> pipeline -> response in the negotiated format.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderValue};
use axum::response::{IntoResponse, Response};
use base64::Engine;
use prost::Message;
use serde::Serialize;

use super::body::read_render_request;
use super::negotiate::{request_format, response_format, ResponseFormat};
use super::AppState;
use crate::error::ApiError;
use crate::image_io;
use crate::pipeline::{assemble, Timings, View};
use crate::request::OutputSet;

/// Renders a target view from source views (one request: decode, encoder, volume, renderer).
#[utoipa::path(
    post, path = "/v1/render", tag = "render", operation_id = "render",
    request_body(content(
        (crate::http::openapi::RenderMultipart = "multipart/form-data"),
        (crate::request::JsonRenderRequest = "application/json"),
        (crate::http::openapi::Binary = "application/x-protobuf"),
    ), description = "Source views + cameras, near/far, target camera; protobuf: scnerf.v1.RenderRequest"),
    params(
        ("x-scnerf-deadline-ms" = Option<u64>, Header, nullable = false, minimum = 1, description = "Shortens the server's deadline for this request (ms)"),
    ),
    responses(
        (status = 200, description = "The rendered view (by Accept: PNG, JSON, or protobuf scnerf.v1.RenderResponse)", content(
            (crate::http::openapi::Binary = "image/png"),
            (RenderResponseJson = "application/json"),
            (crate::http::openapi::Binary = "application/x-protobuf"),
        )),
        (status = 400, description = "Malformed request", body = crate::error::ErrorBody),
        (status = 401, description = "Missing or wrong bearer token", body = crate::error::ErrorBody),
        (status = 406, description = "Accept cannot be satisfied", body = crate::error::ErrorBody),
        (status = 408, description = "The body arrived too slowly", body = crate::error::ErrorBody),
        (status = 413, description = "Body or JSON document too large", body = crate::error::ErrorBody),
        (status = 415, description = "Unsupported content type or image format", body = crate::error::ErrorBody),
        (status = 422, description = "Semantically invalid (camera, view count, sizes, near/far...)", body = crate::error::ErrorBody),
        (status = 429, description = "This client has too many requests in flight (Retry-After)", body = crate::error::ErrorBody),
        (status = 503, description = "Warming up, overloaded, or the request cannot finish by its deadline (Retry-After)", body = crate::error::ErrorBody),
        (status = 504, description = "Deadline exceeded", body = crate::error::ErrorBody),
    ),
    security((), ("bearer" = [])),
)]
pub async fn render(State(state): State<AppState>, req: Request) -> Result<Response, ApiError> {
    let started = Instant::now();
    state.check_ready()?;
    let budget = deadline_of(req.headers(), state.request_timeout)?;
    with_deadline(budget, render_within(state, req, started, started + budget)).await
}

async fn render_within(
    state: AppState,
    req: Request,
    started: Instant,
    deadline: Instant,
) -> Result<Response, ApiError> {
    let format = request_format(req.headers())?;
    let headers = req.headers().clone();
    let pipeline = &state.pipeline;
    let parsed = read_render_request(format, req, &pipeline.limits).await?;
    let valid = parsed.validate(&pipeline.bundle.config, &pipeline.limits)?;
    let out_format = response_format(&headers, valid.view.outputs)?;

    let work = pipeline.scene_work(&valid.scene.cameras()).plus(pipeline.view_work(&valid.view.target));
    let ticket = pipeline.admit(deadline, work)?;
    let mut timings = Timings::default();
    let view = pipeline.render(&ticket, &valid, &mut timings).await?;
    drop(ticket); // encoding needs no inference: let the next request in
    finish(&state, view, valid.view.outputs, out_format, timings, started).await
}

/// Header with which a client shortens its request's deadline (milliseconds).
pub const DEADLINE_HEADER: &str = "x-scnerf-deadline-ms";

/// The request's time budget: the configured timeout, or less when the client asks for less.
/// The header sent twice is refused rather than one of its values picked.
pub(super) fn deadline_of(headers: &HeaderMap, default: Duration) -> Result<Duration, ApiError> {
    let malformed = |message| ApiError::malformed(Some(DEADLINE_HEADER.to_string()), message);
    let mut values = headers.get_all(DEADLINE_HEADER).iter();
    let Some(value) = values.next() else { return Ok(default) };
    if values.next().is_some() {
        return Err(malformed("sent more than once"));
    }
    let ms = value
        .to_str()
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .filter(|&ms| ms > 0)
        .ok_or_else(|| malformed("expected a whole number of milliseconds > 0"))?;
    Ok(default.min(Duration::from_millis(ms)))
}

/// Runs a request's whole handling (body, decoding, inference, encoding) within its time budget
/// (504 past it). On timeout the work is dropped, and with it its ticket: the executor drops
/// the request's waiting graph runs.
pub(super) async fn with_deadline<T>(
    budget: Duration,
    work: impl std::future::Future<Output = Result<T, ApiError>>,
) -> Result<T, ApiError> {
    let ms = u64::try_from(budget.as_millis()).unwrap_or(u64::MAX);
    match tokio::time::timeout(budget, work).await {
        Ok(Err(ApiError::DeadlineExceeded { .. })) | Err(_) => Err(ApiError::DeadlineExceeded { ms }),
        Ok(result) => result,
    }
}

/// Encodes a rendered view and answers in the negotiated format (shared by /v1/render and
/// /v1/scenes/{id}/render, so both endpoints answer identically).
pub(super) async fn finish(
    state: &AppState,
    view: View,
    outputs: OutputSet,
    format: ResponseFormat,
    mut timings: Timings,
    started: Instant,
) -> Result<Response, ApiError> {
    let encode_start = Instant::now();
    let rendered = encode_outputs(view, outputs).await?;
    timings.add("encode", encode_start.elapsed());
    timings.add("total", started.elapsed());
    tracing::info!(timings = ?timings.millis(), "rendered");
    state.metrics.observe_stages(&timings);
    Ok(respond(format, rendered, &timings, &state.pipeline.bundle.manifest.model_id))
}

/// The outputs in their wire encodings: PNG for rgb, little-endian float32 for the others.
pub struct Encoded {
    pub width: u32,
    pub height: u32,
    pub rgb_png: Option<Vec<u8>>,
    pub depth: Option<Vec<u8>>,
    pub opacity: Option<Vec<u8>>,
}

async fn encode_outputs(view: View, outputs: OutputSet) -> Result<Encoded, ApiError> {
    tokio::task::spawn_blocking(move || {
        let rgb_png = if outputs.rgb {
            Some(image_io::encode_png(view.width, view.height, &assemble::quantize(&view.rgb))?)
        } else {
            None
        };
        let le = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        Ok(Encoded {
            width: view.width,
            height: view.height,
            rgb_png,
            depth: outputs.depth.then(|| le(&view.depth)),
            opacity: outputs.opacity.then(|| le(&view.opacity)),
        })
    })
    .await
    .map_err(|e| ApiError::Internal(format!("encoding task failed: {e}")))?
}

fn respond(format: ResponseFormat, out: Encoded, timings: &Timings, model_id: &str) -> Response {
    let mut response = match format {
        ResponseFormat::Png => out.rgb_png.unwrap_or_default().into_response(),
        ResponseFormat::Json => axum::Json(json_body(&out, timings, model_id)).into_response(),
        ResponseFormat::Protobuf => proto_body(out, timings, model_id).encode_to_vec().into_response(),
    };
    response.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(format.content_type()));
    set_common_headers(&mut response, timings, model_id);
    response
}

/// `x-model-id` and `server-timing` (per-stage milliseconds), on every successful response.
pub(super) fn set_common_headers(response: &mut Response, timings: &Timings, model_id: &str) {
    let headers = response.headers_mut();
    if let Ok(v) = HeaderValue::from_str(model_id) {
        headers.insert("x-model-id", v);
    }
    let server_timing: Vec<String> = timings.millis().iter().map(|(s, ms)| format!("{s};dur={ms:.1}")).collect();
    if let Ok(v) = HeaderValue::from_str(&server_timing.join(", ")) {
        headers.insert("server-timing", v);
    }
}

/// `application/json` render response (`POST /v1/render`, `POST /v1/scenes/{id}/render`).
#[derive(Debug, Serialize, utoipa::ToSchema)]
#[schema(as = RenderResponse)]
pub struct RenderResponseJson {
    pub model_id: String,
    pub width: u32,
    pub height: u32,
    /// Present when `rgb` was asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rgb: Option<PngImageJson>,
    /// Target z-depth (`sum w_k z_k`), when `depth` was asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub depth: Option<FloatImageJson>,
    /// `sum w_k`, when `opacity` was asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opacity: Option<FloatImageJson>,
    /// Wall time per stage: decode, encoder, volume, renderer, assemble, encode, total.
    pub timings_ms: BTreeMap<String, f64>,
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
#[schema(as = PngImage)]
pub struct PngImageJson {
    /// Always `png`.
    pub format: &'static str,
    /// Base64 PNG (8-bit RGB).
    pub data: String,
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
#[schema(as = FloatImage)]
pub struct FloatImageJson {
    pub width: u32,
    pub height: u32,
    /// Always `float32`.
    pub dtype: &'static str,
    /// Always `little`.
    pub byte_order: &'static str,
    /// Base64 of height x width little-endian float32, row-major.
    pub data: String,
}

fn json_body(out: &Encoded, timings: &Timings, model_id: &str) -> RenderResponseJson {
    let b64 = |b: &[u8]| base64::engine::general_purpose::STANDARD.encode(b);
    let float_image = |data: &Option<Vec<u8>>| {
        data.as_ref().map(|d| FloatImageJson {
            width: out.width,
            height: out.height,
            dtype: "float32",
            byte_order: "little",
            data: b64(d),
        })
    };
    RenderResponseJson {
        model_id: model_id.to_string(),
        width: out.width,
        height: out.height,
        rgb: out.rgb_png.as_ref().map(|png| PngImageJson { format: "png", data: b64(png) }),
        depth: float_image(&out.depth),
        opacity: float_image(&out.opacity),
        timings_ms: timings.millis().into_iter().map(|(s, ms)| (s.to_string(), ms)).collect(),
    }
}

fn proto_body(out: Encoded, timings: &Timings, model_id: &str) -> scnerf_proto::v1::RenderResponse {
    use scnerf_proto::v1 as pb;
    let float_image =
        |data: Option<Vec<u8>>| data.map(|data| pb::FloatImage { width: out.width, height: out.height, data });
    pb::RenderResponse {
        model_id: model_id.to_string(),
        width: out.width,
        height: out.height,
        rgb_png: out.rgb_png.clone().unwrap_or_default(),
        depth: float_image(out.depth.clone()),
        opacity: float_image(out.opacity.clone()),
        timings_ms: timings.millis().into_iter().map(|(s, ms)| (s.to_string(), ms)).collect(),
    }
}
