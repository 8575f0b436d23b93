//! `POST /v1/captures/plan`: what a client sends of a capture folder to `POST /v1/captures`,
//! decided from the folder's listing by the capture crate's rules (`scnerf_capture::plan`): which
//! files a capture needs, which image set goes (`images/`, `images_N/`), and the size each image
//! over `--max-source-pixels` is resized to before it is sent. The viewer and the Python client
//! ask here instead of keeping copies of those rules.
//!
//! The set is picked by the size of each set's first image, which the client reads from one
//! header per folder of images: a listing without those sizes is answered with `sizes_needed`,
//! and the client asks again with them. The listing is a JSON document (`--max-json-bytes`);
//! every entry that cannot be planned is refused, naming it.

use std::num::NonZeroU32;

use axum::extract::{Request, State};
use axum::Json;
use scnerf_capture::image_sets::Pick;
use scnerf_capture::plan::{plan, LeftOut, Outcome, Plan, PlanError};
use serde::{Deserialize, Serialize};

use super::body::read_bytes;
use super::deadline::Deadline;
use super::negotiate::{request_format, RequestFormat};
use super::openapi::refusals::CapturePlanRefusals;
use super::state::AppState;
use crate::blocking;
use crate::error::ApiError;
use crate::request::wire::parse_json;

/// `POST /v1/captures/plan` body: a capture folder's listing.
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CapturePlanRequest {
    /// Every file of the capture folder (hidden ones and any others too: the server chooses), by
    /// its path in the folder with `/` separators: `transforms.json`, `images/IMG_0001.JPG`,
    /// `sparse/0/cameras.bin`, `.DS_Store`.
    #[schema(min_items = 1)]
    files: Vec<String>,
    /// Sizes of images in `files`: those an answer's `sizes_needed` asked for (the first image of
    /// each folder of images), or more (an image whose size is given is planned by it).
    #[serde(default)]
    sizes: Vec<CaptureImageSize>,
    /// Send the image set `images_N` (`images` for 1), as `POST /v1/captures?downscale=N` reads
    /// it; without it, the largest set whose images fit `max_source_pixels` (GET /v1/limits).
    #[serde(default)]
    #[schema(value_type = Option<u32>, minimum = 1)]
    downscale: Option<NonZeroU32>,
}

/// The size of one listed image, as displayed (EXIF orientation applied).
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CaptureImageSize {
    /// As in `files`.
    path: String,
    #[schema(minimum = 1)]
    width: u32,
    #[schema(minimum = 1)]
    height: u32,
}

/// `200` body of `POST /v1/captures/plan`. While `sizes_needed` is not empty nothing is planned
/// yet and every list but it is empty: send the listing again with those images' sizes.
#[derive(Debug, Default, Serialize, utoipa::ToSchema)]
pub struct CapturePlan {
    /// Images (paths as listed) whose sizes the plan needs: the first, in name order, of each
    /// folder holding images (one per image set). Empty once the plan is made.
    pub sizes_needed: Vec<String>,
    /// What the file names say the capture is: colmap, nerfstudio, blender, llff or dtu; null for
    /// a single transforms.json (Blender or nerfstudio, which its content tells).
    pub format: Option<String>,
    /// The files to send to `POST /v1/captures`, in the listing's order, paths as listed.
    pub send: Vec<PlannedFile>,
    /// The files not to send, in the listing's order, and why.
    pub left_out: Vec<LeftOutFile>,
    /// The image set sent (`images`, `images_4`), when the capture keeps sets.
    pub image_set: Option<String>,
    /// Every image set of the capture, largest first, each with the size of its first image.
    pub image_sets: Vec<CaptureImageSet>,
    /// What to tell the user, one line each: the set picked and why, the images resized, the
    /// files that are neither images nor camera files.
    pub notes: Vec<String>,
}

/// A file to send.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct PlannedFile {
    pub path: String,
    /// Present for an image over `max_source_pixels`: resample it to `to` first (aspect kept,
    /// sizes rounded down: `POST /v1/captures` fits images by the same rule) when its size is
    /// `from` (its own size as given, else its folder's first image's); an image of another size
    /// is sent as it is, and the server fits it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resize: Option<PlannedResize>,
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct PlannedResize {
    pub from: PixelSize,
    pub to: PixelSize,
}

#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct PixelSize {
    pub width: u32,
    pub height: u32,
}

/// A listed file that is not sent.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct LeftOutFile {
    pub path: String,
    /// `hidden` (a name in its path starts with `.`), `not_capture_file` (neither an image, .png
    /// .jpg .jpeg, nor a camera file, .json .npy .txt .bin, in any case) or `other_image_set`
    /// (in the folder of a set not picked).
    #[schema(pattern = "^(hidden|not_capture_file|other_image_set)$")]
    pub reason: &'static str,
}

/// An image set: `images/` (factor 1) or `images_N/`, and the size of its first image.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct CaptureImageSet {
    pub folder: String,
    pub factor: u32,
    pub width: u32,
    pub height: u32,
}

#[utoipa::path(
    post, path = "/v1/captures/plan", tag = "render", operation_id = "plan_capture",
    request_body(content = CapturePlanRequest, content_type = "application/json",
        description = "The capture folder's listing: every file's path, the sizes of the images asked for, and `downscale`"),
    params(Deadline),
    responses(
        (status = 200, description = "What to send to POST /v1/captures, or the image sizes needed first", body = CapturePlan),
        CapturePlanRefusals,
    ),
    security((), ("bearer" = [])),
)]
pub async fn plan_capture(
    State(state): State<AppState>,
    deadline: Deadline,
    req: Request,
) -> Result<Json<CapturePlan>, ApiError> {
    deadline.run(plan_within(state, req)).await
}

async fn plan_within(state: AppState, req: Request) -> Result<Json<CapturePlan>, ApiError> {
    if request_format(req.headers())? != RequestFormat::Json {
        return Err(ApiError::UnsupportedMediaType {
            field: Some("content-type".into()),
            message: "a capture's listing is sent as application/json".into(),
        });
    }
    let limits = state.pipeline().limits().clone();
    let body = read_bytes(req.into_body(), limits.max_json_bytes).await?;
    // A listing of up to --max-json-bytes of short paths is many thousands of entries: off the
    // async workers.
    let answer = blocking::run(move |_| {
        let request: CapturePlanRequest = parse_json(&body, limits.max_json_depth, "capture listing", "body")?;
        let rule = match request.downscale {
            Some(factor) => Pick::Downscale(factor.get()),
            None => Pick::Fit { max_pixels: limits.max_source_pixels },
        };
        let files: Vec<&str> = request.files.iter().map(String::as_str).collect();
        let sizes: Vec<(&str, u32, u32)> = request.sizes.iter().map(|s| (s.path.as_str(), s.width, s.height)).collect();
        match plan(&files, &sizes, rule, limits.max_source_pixels).map_err(refusal)? {
            Outcome::SizesNeeded(needed) => Ok(CapturePlan {
                sizes_needed: needed.into_iter().map(|i| files[i].to_string()).collect(),
                ..Default::default()
            }),
            Outcome::Planned(plan) => Ok(answer(&files, plan)),
        }
    })
    .await?;
    Ok(Json(answer))
}

/// A plan as the API writes it, paths as the client listed them.
fn answer(files: &[&str], plan: Plan) -> CapturePlan {
    let size = |(width, height): (u32, u32)| PixelSize { width, height };
    let send = plan
        .send
        .into_iter()
        .map(|s| PlannedFile {
            path: files[s.index].to_string(),
            resize: s.resize.map(|r| PlannedResize { from: size(r.from), to: size(r.to) }),
        })
        .collect();
    let reason = |why: LeftOut| match why {
        LeftOut::Hidden => "hidden",
        LeftOut::NotCaptureFile => "not_capture_file",
        LeftOut::OtherImageSet => "other_image_set",
    };
    let left_out = plan
        .left_out
        .into_iter()
        .map(|(i, why)| LeftOutFile { path: files[i].to_string(), reason: reason(why) })
        .collect();
    let folder = |f: &std::path::Path| f.to_string_lossy().into_owned();
    CapturePlan {
        sizes_needed: Vec::new(),
        format: plan.format.map(|f| f.name().to_string()),
        send,
        left_out,
        image_set: plan.picked.as_ref().map(|p| folder(&p.set.folder)),
        image_sets: plan.picked.map_or_else(Vec::new, |p| {
            p.sets
                .iter()
                .map(|s| CaptureImageSet {
                    folder: folder(&s.folder),
                    factor: s.factor,
                    width: s.width,
                    height: s.height,
                })
                .collect()
        }),
        notes: plan.notes,
    }
}

/// A listing that cannot be planned: 422 naming the entry (`files[3]`, `sizes[0]`), `files` for
/// the listing as a whole, or `downscale`.
fn refusal(e: PlanError) -> ApiError {
    let message = e.to_string();
    match e {
        PlanError::File { index, .. } => ApiError::invalid(format!("files[{index}]"), message),
        PlanError::Size { index, .. } => ApiError::invalid(format!("sizes[{index}]"), message),
        PlanError::Listing(_) => ApiError::invalid("files", message),
        PlanError::Downscale(_) => ApiError::invalid("downscale", message),
    }
}
