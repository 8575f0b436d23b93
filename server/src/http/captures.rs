//! `POST /v1/captures`: a capture folder's files (`body::read_capture_files`), made a scene by
//! `crate::captures` (the readers the `scnerf` client uses, from an image set, thinned to
//! `--max-scene-views`) and kept as `POST /v1/scenes` keeps one. Nothing is written to disk.
//!
//! Memory: the files are the body, held against the memory budget as it arrives (see
//! `middleware::limit_in_flight`); what parsing them takes is held before it starts, and the
//! views are then decoded as any scene's are, admitted by their estimate.

use axum::extract::rejection::QueryRejection;
use axum::extract::{Query, Request, State};
use axum::http::StatusCode;
use axum::response::Response;
use scnerf_capture::wire::WireCamera;
use serde::Serialize;

use super::body::read_capture_files;
use super::deadline::Deadline;
use super::negotiate::{request_format, RequestFormat};
use super::openapi::refusals::CaptureRefusals;
use super::respond::rfc3339;
use super::scenes::{owner_of, proxy_scene_id, scene_response, store_scene, SceneIdHeader};
use super::state::AppState;
use crate::captures::{self, CaptureLimits, CaptureOptions};
use crate::error::ApiError;
use crate::pipeline::scene::Timings;

/// `201 Created` body of `POST /v1/captures`: the scene, and what the capture was read as.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct CaptureCreated {
    pub scene_id: String,
    /// The model the scene belongs to.
    pub model: String,
    /// RFC 3339 UTC, as for `POST /v1/scenes`.
    pub expires_at: String,
    /// Every view of the scene (canonical: OpenCV world-to-camera), in the order of the indices
    /// that renders report in `sources` and may pin.
    pub cameras: Vec<WireCamera>,
    /// The image file of each camera (its path in the capture).
    pub names: Vec<String>,
    pub near: f64,
    pub far: f64,
    /// colmap, nerfstudio, blender, llff or dtu.
    pub format: String,
    /// The image set read (`images`, `images_4`, ...), when the capture keeps sets.
    pub image_set: Option<String>,
    /// What the reader skipped or ignored, the image sets sent but not read, and whether the
    /// capture was thinned.
    pub warnings: Vec<String>,
}

#[utoipa::path(
    post, path = "/v1/captures", tag = "render", operation_id = "create_capture_scene",
    request_body(content((crate::http::schema::CaptureMultipart = "multipart/form-data")),
        description = "A capture folder's files: COLMAP (cameras/images/points3D .txt or .bin, in ., sparse/0 or sparse; images/), nerfstudio or Blender (transforms*.json + images), LLFF (poses_bounds.npy + images/), DTU (Cameras/ + Rectified/)"),
    params(
        CaptureOptions,
        Deadline,
        SceneIdHeader,
    ),
    responses(
        (status = 201, description = "The capture is a scene", body = CaptureCreated,
         headers(("location" = String, description = "/v1/scenes/{scene_id}"))),
        CaptureRefusals,
    ),
    security((), ("bearer" = [])),
)]
pub async fn create(
    State(state): State<AppState>,
    deadline: Deadline,
    query: Result<Query<CaptureOptions>, QueryRejection>,
    req: Request,
) -> Result<Response, ApiError> {
    let Query(options) = query.map_err(|e| ApiError::malformed(Some("query".to_string()), e.body_text()))?;
    let id = proxy_scene_id(req.headers())?;
    deadline.run(create_within(state, deadline, options, id, req)).await
}

async fn create_within(
    state: AppState,
    deadline: Deadline,
    options: CaptureOptions,
    id: Option<String>,
    req: Request,
) -> Result<Response, ApiError> {
    if request_format(req.headers())? != RequestFormat::Multipart {
        return Err(ApiError::UnsupportedMediaType {
            field: Some("content-type".into()),
            message: "a capture is sent as multipart/form-data, one part named `file` per file".into(),
        });
    }
    let owner = owner_of(&req);
    // Before the upload is read: a wrong name costs the client no upload.
    let model = state.models.get(options.model())?;
    let files = read_capture_files(req, state.pipeline().limits()).await?;
    let sizes = CaptureLimits::new(&model, &state.scenes);
    let read = captures::read_scene(files, options, state.pipeline().executor(), &model.pipeline, sizes).await?;
    let (near, far) = (read.scene.near, read.scene.far);
    let mut timings = Timings::default();
    let stored = store_scene(&state, &model, read.scene, id, owner, &deadline, &mut timings).await?;
    let body = CaptureCreated {
        scene_id: stored.id.clone(),
        model: model.name.to_string(),
        expires_at: rfc3339(stored.expires_at),
        cameras: read.cameras,
        names: read.names,
        near,
        far,
        format: read.format,
        image_set: read.image_set,
        warnings: read.warnings,
    };
    let status = if stored.replaced { StatusCode::OK } else { StatusCode::CREATED };
    Ok(scene_response(&model, status, &stored.id, body, &timings))
}
