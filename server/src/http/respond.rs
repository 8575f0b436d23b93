//! The response layer of the render endpoints: a rendered view encoded (PNG, float32) and
//! answered in the negotiated format, with the headers every successful response carries. The
//! JSON types here are also the OpenAPI schema of the responses.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

use axum::http::{header, HeaderValue};
use axum::response::{IntoResponse, Response};
use base64::Engine;
use ndarray::Array2;
use prost::Message;
use serde::Serialize;

use super::negotiate::ResponseFormat;
use super::state::AppState;
use crate::error::ApiError;
use crate::image_io;
use crate::models::Model;
use crate::pipeline::assemble;
use crate::pipeline::scene::SamplingReport;
use crate::pipeline::scene::{Timings, View};
use crate::request::OutputSet;
use crate::request::Sampling;

/// Header naming the views a render used: `i,j,k`, indices into the scene's views, the volume's
/// reference first.
pub const SOURCES_HEADER: &str = "x-scnerf-sources";

/// Headers saying how a view was sampled: `full` or `guided`, and the network samples per pixel.
pub const SAMPLING_HEADER: &str = "x-scnerf-sampling";
pub const SAMPLES_PER_RAY_HEADER: &str = "x-scnerf-samples-per-ray";

/// A rendered view and the views it was rendered from.
pub struct Rendered {
    pub view: View,
    pub sources: Vec<usize>,
    /// The model that rendered it.
    pub model: Arc<Model>,
}

/// Encodes a rendered view and answers in the negotiated format (shared by /v1/render and
/// /v1/scenes/{id}/render, so both endpoints answer identically).
pub async fn finish(
    state: &AppState,
    rendered: Rendered,
    outputs: OutputSet,
    format: ResponseFormat,
    mut timings: Timings,
    started: Instant,
) -> Result<Response, ApiError> {
    let encode_start = Instant::now();
    let encoded = encode_outputs(rendered.view, outputs, &rendered.sources).await?;
    let model = &rendered.model;
    timings.add("encode", encode_start.elapsed());
    timings.add("total", started.elapsed());
    let sampling = encoded.sampling;
    tracing::info!(model = %model.name, timings = ?timings.millis(), sources = ?rendered.sources, sampling = %sampling.mode,
                   samples_per_ray = sampling.samples_per_ray, "rendered");
    state.metrics.observe_stages(model, &timings);
    state.metrics.observe_sampling(model, &sampling);
    Ok(respond(format, encoded, &timings, model))
}

/// The outputs in their wire encodings: PNG for rgb, little-endian float32 for the others.
struct Encoded {
    width: u32,
    height: u32,
    rgb_png: Option<Vec<u8>>,
    depth: Option<Vec<u8>>,
    opacity: Option<Vec<u8>>,
    sources: Vec<u32>,
    sampling: SamplingReport,
}

async fn encode_outputs(view: View, outputs: OutputSet, sources: &[usize]) -> Result<Encoded, ApiError> {
    let sources: Vec<u32> = sources.iter().map(|&i| i as u32).collect();
    tokio::task::spawn_blocking(move || {
        let (width, height) = (view.width(), view.height());
        let rgb_png =
            if outputs.rgb { Some(image_io::encode_png(width, height, &assemble::quantize(&view.rgb))?) } else { None };
        // Row-major, as the arrays iterate.
        let le = |v: &Array2<f32>| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        Ok(Encoded {
            width,
            height,
            rgb_png,
            depth: outputs.depth.then(|| le(&view.depth)),
            opacity: outputs.opacity.then(|| le(&view.opacity)),
            sources,
            sampling: view.sampling,
        })
    })
    .await
    .map_err(|e| ApiError::Internal(format!("encoding task failed: {e}")))?
}

fn respond(format: ResponseFormat, out: Encoded, timings: &Timings, model: &Model) -> Response {
    let mut response = match format {
        ResponseFormat::Png => out.rgb_png.unwrap_or_default().into_response(),
        ResponseFormat::Json => axum::Json(json_body(&out, timings, model)).into_response(),
        ResponseFormat::Protobuf => proto_body(&out, timings, model).encode_to_vec().into_response(),
    };
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(format.content_type()));
    let sources: Vec<String> = out.sources.iter().map(u32::to_string).collect();
    if let Ok(v) = HeaderValue::from_str(&sources.join(",")) {
        headers.insert(SOURCES_HEADER, v);
    }
    headers.insert(SAMPLING_HEADER, HeaderValue::from_static(out.sampling.mode.name()));
    if let Ok(v) = HeaderValue::from_str(&format!("{:.2}", out.sampling.samples_per_ray)) {
        headers.insert(SAMPLES_PER_RAY_HEADER, v);
    }
    set_common_headers(&mut response, timings, model);
    response
}

/// Header naming the model (its name, what requests send as `"model"`) that answered.
pub const MODEL_HEADER: &str = "x-scnerf-model";

/// `x-model-id`, [`MODEL_HEADER`] and `server-timing` (per-stage milliseconds), on every
/// successful response of the render and scene endpoints.
pub fn set_common_headers(response: &mut Response, timings: &Timings, model: &Model) {
    let headers = response.headers_mut();
    if let Ok(v) = HeaderValue::from_str(&model.bundle().manifest.model_id) {
        headers.insert("x-model-id", v);
    }
    if let Ok(v) = HeaderValue::from_str(&model.name) {
        headers.insert(MODEL_HEADER, v);
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
    /// The model's name (`GET /v1/models`).
    pub model: String,
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
    /// The views rendered from: indices into the scene's views, the volume's reference first
    /// (`[0, 1, 2]` for /v1/render). Also in the `x-scnerf-sources` header.
    pub sources: Vec<u32>,
    /// How the view was sampled (also in the `x-scnerf-sampling` header).
    pub sampling: Sampling,
    /// Network samples per pixel, on average over the view (`x-scnerf-samples-per-ray`).
    pub samples_per_ray: f64,
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

fn json_body(out: &Encoded, timings: &Timings, model: &Model) -> RenderResponseJson {
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
        model_id: model.bundle().manifest.model_id.clone(),
        model: model.name.to_string(),
        width: out.width,
        height: out.height,
        rgb: out.rgb_png.as_ref().map(|png| PngImageJson { format: "png", data: b64(png) }),
        depth: float_image(&out.depth),
        opacity: float_image(&out.opacity),
        timings_ms: timings.millis().into_iter().map(|(s, ms)| (s.to_string(), ms)).collect(),
        sources: out.sources.clone(),
        sampling: out.sampling.mode,
        samples_per_ray: out.sampling.samples_per_ray,
    }
}

fn proto_body(out: &Encoded, timings: &Timings, model: &Model) -> scnerf_proto::v1::RenderResponse {
    use scnerf_proto::v1 as pb;
    let float_image =
        |data: Option<Vec<u8>>| data.map(|data| pb::FloatImage { width: out.width, height: out.height, data });
    pb::RenderResponse {
        model_id: model.bundle().manifest.model_id.clone(),
        model: model.name.to_string(),
        width: out.width,
        height: out.height,
        rgb_png: out.rgb_png.clone().unwrap_or_default(),
        depth: float_image(out.depth.clone()),
        opacity: float_image(out.opacity.clone()),
        timings_ms: timings.millis().into_iter().map(|(s, ms)| (s.to_string(), ms)).collect(),
        sources: out.sources.clone(),
        sampling: out.sampling.mode.name().to_string(),
        samples_per_ray: out.sampling.samples_per_ray,
    }
}

/// RFC 3339 UTC with milliseconds, e.g. `2026-01-01T12:00:00.000Z`.
pub fn rfc3339(t: std::time::SystemTime) -> String {
    humantime::format_rfc3339_millis(t).to_string()
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, SystemTime};

    use super::rfc3339;

    #[test]
    fn formats_rfc3339() {
        let t = SystemTime::UNIX_EPOCH + Duration::from_millis(1_767_225_600_123);
        assert_eq!(rfc3339(t), "2026-01-01T00:00:00.123Z");
    }
}
