//! `POST /v1/render`: body -> validated request -> pipeline -> response in the negotiated format.

use axum::extract::{Request, State};
use axum::response::Response;

use super::body::read_render_request;
use super::deadline::Deadline;
use super::negotiate::{request_format, response_format};
use super::openapi::refusals::RenderRefusals;
use super::respond::{finish, Rendered};
use super::state::AppState;
use crate::error::ApiError;
use crate::pipeline::scene::Timings;

/// Renders a target view from source views (one request: decode, encoder, volume, renderer).
#[utoipa::path(
    post, path = "/v1/render", tag = "render", operation_id = "render",
    request_body(content(
        (crate::http::schema::RenderMultipart = "multipart/form-data"),
        (crate::request::wire::JsonRenderRequest = "application/json"),
        (crate::http::schema::Binary = "application/x-protobuf"),
    ), description = "Source views + cameras, near/far, target camera; protobuf: scnerf.v1.RenderRequest"),
    params(Deadline),
    responses(
        (status = 200, description = "The rendered view (by Accept: PNG, JSON, or protobuf scnerf.v1.RenderResponse)", content(
            (crate::http::schema::Binary = "image/png"),
            (crate::http::respond::RenderResponseJson = "application/json"),
            (crate::http::schema::Binary = "application/x-protobuf"),
        )),
        RenderRefusals,
    ),
    security((), ("bearer" = [])),
)]
pub async fn render(State(state): State<AppState>, deadline: Deadline, req: Request) -> Result<Response, ApiError> {
    deadline.run(render_within(state, deadline, req)).await
}

async fn render_within(state: AppState, deadline: Deadline, req: Request) -> Result<Response, ApiError> {
    let format = request_format(req.headers())?;
    let headers = req.headers().clone();
    let parsed = read_render_request(format, req, state.pipeline().limits()).await?;
    let model = state.models.get(parsed.scene.model.as_deref())?;
    let pipeline = &model.pipeline;
    let valid = parsed.validate(pipeline.config(), pipeline.limits())?;
    let out_format = response_format(&headers, valid.view.outputs)?;
    let mut timings = Timings::default();
    let view = pipeline.render(&valid, deadline.due(), &mut timings).await?;
    let rendered = Rendered { view, sources: (0..valid.scene.sources.len()).collect(), model: model.clone() };
    finish(&state, rendered, valid.view.outputs, out_format, timings, deadline.started()).await
}
