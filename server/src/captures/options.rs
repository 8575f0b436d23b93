//! What the client chooses about how its capture is read: the options the readers take from the
//! command line in the `scnerf` client, as `POST /v1/captures`'s query parameters.

use std::num::NonZeroU32;

use scnerf_capture::image_sets::Pick;
use scnerf_capture::readers::ReadOptions;
use scnerf_capture::undistort::Fit;
use serde::Deserialize;

use crate::request::Limits;

/// What the readers take from the command line in the client, as query parameters.
#[derive(Debug, Default, Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct CaptureOptions {
    /// Near depth, overriding the capture's (its files', COLMAP's points' or else its poses'; the
    /// readers' messages call it `--near`).
    near: Option<f64>,
    /// Far depth, overriding the capture's.
    far: Option<f64>,
    /// Use photos with lens distortion as they are, as pinhole, instead of undistorting them.
    #[serde(default)]
    ignore_distortion: bool,
    /// The pinhole camera distorted photos are undistorted to: `largest_rectangle` (default)
    /// crops to valid pixels, `all_pixels` keeps every pixel (corners no pixel reaches take the
    /// background).
    #[serde(default)]
    #[param(value_type = Option<String>, pattern = "^(largest_rectangle|all_pixels)$")]
    undistort_to: Fit,
    /// Read the image set `images_N` (LLFF, nerfstudio, COLMAP); without it, the largest set
    /// sent whose images fit `max_source_pixels` (GET /v1/limits).
    #[param(value_type = Option<u32>, minimum = 1)]
    downscale: Option<NonZeroU32>,
    /// The model the scene belongs to (a name `GET /v1/models` lists); default: the server's.
    model: Option<String>,
}

impl CaptureOptions {
    /// The model named, if any.
    pub fn model(&self) -> Option<&str> {
        self.model.as_deref()
    }

    /// The readers' options; the image set is chosen by [`Self::pick`].
    pub(super) fn read_options(&self) -> ReadOptions {
        ReadOptions {
            near: self.near,
            far: self.far,
            ignore_distortion: self.ignore_distortion,
            downscale: None,
            undistort: self.undistort_to,
        }
    }

    /// The image set named, or else the largest within the source limit.
    pub(super) fn pick(&self, limits: &Limits) -> Pick {
        match self.downscale {
            Some(factor) => Pick::Downscale(factor.get()),
            None => Pick::Fit { max_pixels: limits.max_source_pixels },
        }
    }
}
