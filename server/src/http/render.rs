//! POST /v1/render: body -> validated request -> pipeline -> response in the negotiated format.

use std::time::Instant;

use axum::extract::{Request, State};
use axum::http::{header, HeaderValue};
use axum::response::{IntoResponse, Response};
use base64::Engine;
use prost::Message;
use serde_json::json;

use super::body::read_render_request;
use super::negotiate::{request_format, response_format, ResponseFormat};
use super::AppState;
use crate::error::ApiError;
use crate::image_io;
use crate::pipeline::{assemble, Timings, View};
use crate::request::OutputSet;

pub async fn render(State(state): State<AppState>, req: Request) -> Result<Response, ApiError> {
    let started = Instant::now();
    state.check_ready()?;
    let format = request_format(req.headers())?;
    let headers = req.headers().clone();
    let pipeline = &state.pipeline;
    let parsed = read_render_request(format, req, pipeline.limits.max_body_bytes).await?;
    let valid = parsed.validate(&pipeline.bundle.config, &pipeline.limits)?;
    let out_format = response_format(&headers, valid.outputs)?;

    let mut timings = Timings::default();
    let deadline = state.request_timeout;
    let view = tokio::time::timeout(deadline, pipeline.render(&valid, &mut timings))
        .await
        .map_err(|_| ApiError::DeadlineExceeded { secs: deadline.as_secs() })??;

    let encode_start = Instant::now();
    let rendered = encode_outputs(view, valid.outputs).await?;
    timings.add("encode", encode_start.elapsed());
    timings.add("total", started.elapsed());
    let model_id = &pipeline.bundle.manifest.model_id;
    tracing::info!(timings = ?timings.millis(), "rendered");
    Ok(respond(out_format, rendered, &timings, model_id))
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
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(format.content_type()));
    if let Ok(v) = HeaderValue::from_str(model_id) {
        headers.insert("x-model-id", v);
    }
    let server_timing: Vec<String> = timings.millis().iter().map(|(s, ms)| format!("{s};dur={ms:.1}")).collect();
    if let Ok(v) = HeaderValue::from_str(&server_timing.join(", ")) {
        headers.insert("server-timing", v);
    }
    response
}

fn json_body(out: &Encoded, timings: &Timings, model_id: &str) -> serde_json::Value {
    let b64 = |b: &[u8]| base64::engine::general_purpose::STANDARD.encode(b);
    let float_image = |data: &Option<Vec<u8>>| {
        data.as_ref().map(|d| {
            json!({"width": out.width, "height": out.height, "dtype": "float32", "byte_order": "little", "data": b64(d)})
        })
    };
    let mut body = serde_json::Map::new();
    body.insert("model_id".into(), json!(model_id));
    body.insert("width".into(), json!(out.width));
    body.insert("height".into(), json!(out.height));
    if let Some(png) = &out.rgb_png {
        body.insert("rgb".into(), json!({"format": "png", "data": b64(png)}));
    }
    if let Some(v) = float_image(&out.depth) {
        body.insert("depth".into(), v);
    }
    if let Some(v) = float_image(&out.opacity) {
        body.insert("opacity".into(), v);
    }
    let timings: serde_json::Map<String, serde_json::Value> =
        timings.millis().into_iter().map(|(s, ms)| (s.to_string(), json!(ms))).collect();
    body.insert("timings_ms".into(), serde_json::Value::Object(timings));
    serde_json::Value::Object(body)
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
