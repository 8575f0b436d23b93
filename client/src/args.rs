//! The `scnerf` command line's arguments: what each subcommand takes.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand, ValueEnum};
use scnerf_capture::readers::{Capture, CapturedView};

use crate::api::Upload;

#[derive(Parser)]
#[command(name = "scnerf", version, about = "Render posed photo captures through scnerf-serve")]
pub struct Cli {
    /// The scnerf-server to use.
    #[arg(long, global = true, env = "SCNERF_SERVER", default_value = "http://127.0.0.1:8080")]
    pub(crate) server: String,
    /// Bearer token, for a server started with --auth-token.
    #[arg(long, global = true, env = "SCNERF_TOKEN", hide_env_values = true)]
    pub(crate) token: Option<String>,
    /// How views are sampled: guided (coarse to fine, fast) or full (the paper's samples on every
    /// ray). Default: the server's (GET /v1/model).
    #[arg(long, global = true, env = "SCNERF_SAMPLING", value_parser = ["full", "guided"])]
    pub(crate) sampling: Option<String>,
    /// The model to render with, for a server of several (GET /v1/models lists them). Default:
    /// the server's default model.
    #[arg(long, global = true, env = "SCNERF_MODEL")]
    pub(crate) model: Option<String>,
    #[command(subcommand)]
    pub(crate) command: Command,
}

#[derive(Subcommand)]
pub(crate) enum Command {
    /// Print what the reader makes of a dataset: format, views, cameras, near/far.
    Info {
        #[command(flatten)]
        data: DataArgs,
        #[command(flatten)]
        set: ImageSetArgs,
        /// Every camera in the API's JSON form.
        #[arg(long)]
        json: bool,
    },
    /// Render a camera path through the capture to PNG frames, depth maps and a video.
    Render(RenderArgs),
    /// Render one view.
    View(ViewArgs),
    /// Render held-out captured views from the others and score them (PSNR, SSIM).
    Eval(EvalArgs),
}

#[derive(Args)]
pub(crate) struct DataArgs {
    /// Dataset folder (COLMAP, nerfstudio, Blender, LLFF or DTU), or a transforms JSON file.
    pub(crate) data: PathBuf,
    #[arg(long, value_enum, default_value_t = FormatArg::Auto)]
    pub(crate) format: FormatArg,
    /// Near depth, overriding the dataset's.
    #[arg(long)]
    pub(crate) near: Option<f64>,
    /// Far depth, overriding the dataset's.
    #[arg(long)]
    pub(crate) far: Option<f64>,
    /// Use photos with lens distortion as they are, as pinhole, instead of undistorting them.
    #[arg(long)]
    pub(crate) ignore_distortion: bool,
    /// The pinhole camera distorted photos are undistorted to: largest-rectangle crops to valid
    /// pixels, all-pixels keeps every pixel (corners no pixel reaches take the background).
    #[arg(long, value_enum, default_value_t = UndistortTo::LargestRectangle)]
    pub(crate) undistort_to: UndistortTo,
}

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum UndistortTo {
    LargestRectangle,
    AllPixels,
}

#[derive(Args)]
pub(crate) struct ImageSetArgs {
    /// Read the image set images_N (LLFF, nerfstudio, COLMAP: downscaled copies beside images/);
    /// default: the largest set within the server's source limit.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub(crate) downscale: Option<u32>,
}

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum FormatArg {
    Auto,
    Colmap,
    Nerfstudio,
    Blender,
    Llff,
    Dtu,
}

#[derive(Args)]
pub(crate) struct UploadArgs {
    /// Most views to upload (the server's scene limit): a larger capture is thinned evenly.
    #[arg(long, default_value_t = 64)]
    pub(crate) max_views: usize,
    /// Scene id to upload under (1-64 of A-Z a-z 0-9 . _ -; default: derived from the views'
    /// cameras, depth range, background and image bytes, so the same upload has the same id).
    #[arg(long)]
    pub(crate) scene_id: Option<String>,
}

impl UploadArgs {
    /// `views` of `capture` as one scene, under `--scene-id` if given.
    pub(crate) fn upload(&self, capture: &Capture, views: &[&CapturedView]) -> Upload {
        Upload { scene_id: self.scene_id.clone(), ..Upload::new(capture, views) }
    }
}

#[derive(Args)]
pub(crate) struct RenderArgs {
    #[command(flatten)]
    pub(crate) data: DataArgs,
    #[command(flatten)]
    pub(crate) set: ImageSetArgs,
    #[command(flatten)]
    pub(crate) upload: UploadArgs,
    /// interpolate, orbit, spiral, or a camera file: nerfstudio's camera_path.json or a JSON
    /// array of cameras (API form).
    #[arg(long)]
    pub(crate) path: String,
    /// Number of frames (ignored for a camera file).
    #[arg(long, default_value_t = 48)]
    pub(crate) frames: usize,
    /// Frame size WxH (default: the first view's).
    #[arg(long, value_parser = parse_size)]
    pub(crate) size: Option<(u32, u32)>,
    /// Output folder; frames already in it are not rendered again.
    #[arg(long, default_value = "render")]
    pub(crate) out: PathBuf,
    /// Frames per second of the video (default: a nerfstudio camera path's, else 24).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub(crate) fps: Option<u32>,
    /// Skip the depth maps.
    #[arg(long)]
    pub(crate) no_depth: bool,
    /// Skip the video.
    #[arg(long)]
    pub(crate) no_video: bool,
}

#[derive(Args)]
pub(crate) struct ViewArgs {
    #[command(flatten)]
    pub(crate) data: DataArgs,
    #[command(flatten)]
    pub(crate) set: ImageSetArgs,
    #[command(flatten)]
    pub(crate) upload: UploadArgs,
    /// A view name of the capture, or a JSON file with one camera (API form).
    #[arg(long)]
    pub(crate) pose: String,
    /// Output size WxH (default: the camera's).
    #[arg(long, value_parser = parse_size)]
    pub(crate) size: Option<(u32, u32)>,
    /// Render from these three views (reference first) instead of letting the server choose.
    #[arg(long, value_delimiter = ',')]
    pub(crate) sources: Option<Vec<String>>,
    /// Output PNG; the depth map goes next to it as <name>.depth.npy.
    #[arg(long, default_value = "view.png")]
    pub(crate) out: PathBuf,
}

#[derive(Args)]
pub struct EvalArgs {
    #[command(flatten)]
    pub(crate) data: DataArgs,
    /// Hold out every K-th view (0, K, 2K, ...; LLFF's convention).
    #[arg(long, required_unless_present = "targets", conflicts_with = "targets")]
    pub holdout: Option<usize>,
    /// Hold out these views.
    #[arg(long, value_delimiter = ',')]
    pub targets: Option<Vec<String>>,
    /// The same three sources for every target (default: per target, the 3 nearest others).
    #[arg(long, value_delimiter = ',')]
    pub sources: Option<Vec<String>>,
    /// Render targets at 1/N of their size, against box-averaged ground truth.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    pub downscale: u32,
    /// Save the rendered views here, each with its absolute error image (NAME.error.png).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub(crate) fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("expected WxH, got {s:?}"))?;
    match (w.parse::<u32>(), h.parse::<u32>()) {
        (Ok(w), Ok(h)) if w > 0 && h > 0 => Ok((w, h)),
        _ => Err(format!("expected WxH with positive whole numbers, got {s:?}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_as_width_x_height() {
        assert_eq!(parse_size("200x100"), Ok((200, 100)));
        assert!(parse_size("0x100").is_err() && parse_size("200").is_err());
    }
}
