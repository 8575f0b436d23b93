//! The `scnerf` command line: `info`, `render`, `view`, `eval`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::{Args, Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};

use crate::api::{Client, Upload};
use crate::error::{Error, Result};
use crate::render::{frame_digits, render_frames, server_summary, write_atomically, write_npy};
use crate::{eval, paths, video};
use scnerf_capture::camera::Camera;
use scnerf_capture::files::Disk;
use scnerf_capture::image_sets::{self, Pick, Picked};
use scnerf_capture::readers::{self, Capture, CapturedView, Format, ReadOptions};
use scnerf_capture::undistort::Fit;
use scnerf_capture::upload::fit_to_limit;
use scnerf_capture::wire::WireCamera;

#[derive(Parser)]
#[command(name = "scnerf", version, about = "Render posed photo captures through scnerf-serve")]
pub struct Cli {
    /// The scnerf-server to use.
    #[arg(long, global = true, env = "SCNERF_SERVER", default_value = "http://127.0.0.1:8080")]
    server: String,
    /// Bearer token, for a server started with --auth-token.
    #[arg(long, global = true, env = "SCNERF_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// How views are sampled: guided (coarse to fine, fast) or full (the paper's samples on every
    /// ray). Default: the server's (GET /v1/model).
    #[arg(long, global = true, env = "SCNERF_SAMPLING", value_parser = ["full", "guided"])]
    sampling: Option<String>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
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
struct DataArgs {
    /// Dataset folder (COLMAP, nerfstudio, Blender, LLFF or DTU), or a transforms JSON file.
    data: PathBuf,
    #[arg(long, value_enum, default_value_t = FormatArg::Auto)]
    format: FormatArg,
    /// Near depth, overriding the dataset's.
    #[arg(long)]
    near: Option<f64>,
    /// Far depth, overriding the dataset's.
    #[arg(long)]
    far: Option<f64>,
    /// Use photos with lens distortion as they are, as pinhole, instead of undistorting them.
    #[arg(long)]
    ignore_distortion: bool,
    /// The pinhole camera distorted photos are undistorted to: largest-rectangle crops to valid
    /// pixels, all-pixels keeps every pixel (corners no pixel reaches take the background).
    #[arg(long, value_enum, default_value_t = UndistortTo::LargestRectangle)]
    undistort_to: UndistortTo,
}

#[derive(Clone, Copy, ValueEnum)]
enum UndistortTo {
    LargestRectangle,
    AllPixels,
}

#[derive(Args)]
struct ImageSetArgs {
    /// Read the image set images_N (LLFF, nerfstudio, COLMAP: downscaled copies beside images/);
    /// default: the largest set within the server's source limit.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    downscale: Option<u32>,
}

#[derive(Clone, Copy, ValueEnum)]
enum FormatArg {
    Auto,
    Colmap,
    Nerfstudio,
    Blender,
    Llff,
    Dtu,
}

#[derive(Args)]
struct UploadArgs {
    /// Most views to upload (the server's scene limit): a larger capture is thinned evenly.
    #[arg(long, default_value_t = 64)]
    max_views: usize,
    /// Scene id to upload under (1-64 of A-Z a-z 0-9 . _ -; default: derived from the views'
    /// cameras, depth range, background and image bytes, so the same upload has the same id).
    #[arg(long)]
    scene_id: Option<String>,
}

impl UploadArgs {
    /// `views` of `capture` as one scene, under `--scene-id` if given.
    fn upload(&self, capture: &Capture, views: &[&CapturedView]) -> Upload {
        Upload { scene_id: self.scene_id.clone(), ..Upload::new(capture, views) }
    }
}

#[derive(Args)]
struct RenderArgs {
    #[command(flatten)]
    data: DataArgs,
    #[command(flatten)]
    set: ImageSetArgs,
    #[command(flatten)]
    upload: UploadArgs,
    /// interpolate, orbit, spiral, or a camera file: nerfstudio's camera_path.json or a JSON
    /// array of cameras (API form).
    #[arg(long)]
    path: String,
    /// Number of frames (ignored for a camera file).
    #[arg(long, default_value_t = 48)]
    frames: usize,
    /// Frame size WxH (default: the first view's).
    #[arg(long, value_parser = parse_size)]
    size: Option<(u32, u32)>,
    /// Output folder; frames already in it are not rendered again.
    #[arg(long, default_value = "render")]
    out: PathBuf,
    /// Frames per second of the video (default: a nerfstudio camera path's, else 24).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    fps: Option<u32>,
    /// Skip the depth maps.
    #[arg(long)]
    no_depth: bool,
    /// Skip the video.
    #[arg(long)]
    no_video: bool,
}

#[derive(Args)]
struct ViewArgs {
    #[command(flatten)]
    data: DataArgs,
    #[command(flatten)]
    set: ImageSetArgs,
    #[command(flatten)]
    upload: UploadArgs,
    /// A view name of the capture, or a JSON file with one camera (API form).
    #[arg(long)]
    pose: String,
    /// Output size WxH (default: the camera's).
    #[arg(long, value_parser = parse_size)]
    size: Option<(u32, u32)>,
    /// Render from these three views (reference first) instead of letting the server choose.
    #[arg(long, value_delimiter = ',')]
    sources: Option<Vec<String>>,
    /// Output PNG; the depth map goes next to it as <name>.depth.npy.
    #[arg(long, default_value = "view.png")]
    out: PathBuf,
}

#[derive(Args)]
pub struct EvalArgs {
    #[command(flatten)]
    data: DataArgs,
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

fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("expected WxH, got {s:?}"))?;
    match (w.parse::<u32>(), h.parse::<u32>()) {
        (Ok(w), Ok(h)) if w > 0 && h > 0 => Ok((w, h)),
        _ => Err(format!("expected WxH with positive whole numbers, got {s:?}")),
    }
}

/// `println!` that stops quietly when stdout is closed (`scnerf info DATA | head`).
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}
pub(crate) use say;

pub fn run(cli: Cli) -> Result<()> {
    let client = Client::new(&cli.server, cli.token).with_sampling(cli.sampling);
    match cli.command {
        Command::Info { data, set, json } => info(&data, &set, json),
        Command::Render(args) => render(client, &args),
        Command::View(args) => view(&client, &args),
        Command::Eval(args) => {
            // targets are scored at the size of the image read; the sources are fitted to the limit
            let max_pixels = client.limits()?.max_source_pixels;
            let (capture, _) = load(&args.data, Pick::Fit { max_pixels }, Some(max_pixels))?;
            let mut sources = capture.clone();
            if let Some(note) = fit_to_limit(&mut sources, max_pixels) {
                eprintln!("note: {note}");
            }
            eval::run(&client, &capture, &sources, &args)
        }
    }
}

/// Reads the capture from the image set `rule` picks and prints its warnings and which set it
/// read (`limit`: the server's source limit, when it chose).
fn load(data: &DataArgs, rule: Pick, limit: Option<u64>) -> Result<(Capture, Option<Picked>)> {
    let format = match data.format {
        FormatArg::Auto => None,
        FormatArg::Colmap => Some(Format::Colmap),
        FormatArg::Nerfstudio => Some(Format::Nerfstudio),
        FormatArg::Blender => Some(Format::Blender),
        FormatArg::Llff => Some(Format::Llff),
        FormatArg::Dtu => Some(Format::Dtu),
    };
    let undistort = match data.undistort_to {
        UndistortTo::AllPixels => Fit::AllPixels,
        UndistortTo::LargestRectangle => Fit::LargestRectangle,
    };
    let opts = ReadOptions {
        near: data.near,
        far: data.far,
        ignore_distortion: data.ignore_distortion,
        downscale: None,
        undistort,
    };
    let (capture, picked) = image_sets::load_picked(&Disk, &data.data, format, opts, rule)?;
    for w in &capture.warnings {
        eprintln!("warning: {w}");
    }
    match (&picked, rule, limit) {
        (Some(p), Pick::Fit { max_pixels }, Some(_)) if p.fits && p.sets.len() > 1 => eprintln!(
            "image set: {}: the largest within the server's limit of {max_pixels} pixels per source view \
             (--downscale N picks another)",
            p.describe()
        ),
        (Some(p), Pick::Downscale(n), _) => eprintln!("image set: {} (--downscale {n})", p.describe()),
        _ => {}
    }
    Ok((capture, picked))
}

/// The capture as the server will take it: from `--downscale N`'s set, or else the largest set
/// within the server's source limit; images that still exceed it (no set is small enough, or the
/// capture keeps none) are resized here, said in one line.
fn load_for_server(client: &Client, data: &DataArgs, set: &ImageSetArgs) -> Result<Capture> {
    let max_pixels = client.limits()?.max_source_pixels;
    let rule = set.downscale.map_or(Pick::Fit { max_pixels }, Pick::Downscale);
    let (mut capture, _) = load(data, rule, Some(max_pixels))?;
    if let Some(note) = fit_to_limit(&mut capture, max_pixels) {
        eprintln!("note: {note}");
    }
    Ok(capture)
}

fn info(data: &DataArgs, set: &ImageSetArgs, json: bool) -> Result<()> {
    let rule = set.downscale.map_or(Pick::Fit { max_pixels: u64::MAX }, Pick::Downscale);
    let (capture, picked) = load(data, rule, None)?;
    if json {
        let views: Vec<serde_json::Value> = capture
            .views
            .iter()
            .map(|v| serde_json::json!({"name": v.name, "image": v.image_path, "camera": WireCamera::from(&v.camera)}))
            .collect();
        let out = serde_json::json!({
            "format": capture.format.name(), "near": capture.near, "far": capture.far,
            "depth_range_source": capture.depth_source.describe(),
            "background": capture.background, "views": views,
        });
        say!("{}", serde_json::to_string_pretty(&out).expect("serializable"));
        return Ok(());
    }
    say!(
        "{}: {} views, near {} far {} ({}), background {:?}",
        capture.format.name(),
        capture.views.len(),
        capture.near,
        capture.far,
        capture.depth_source.describe(),
        capture.background
    );
    let undistorted = capture.views.iter().filter(|v| v.lens.is_some()).count();
    if undistorted > 0 {
        say!("undistorted: {undistorted} views, to pinhole cameras of the same size (--undistort-to)");
    }
    if let Some(p) = picked {
        say!("image set: {}", p.describe());
    }
    for v in &capture.views {
        let (c, i) = (&v.camera, v.camera.intrinsics);
        let p = c.center();
        say!(
            "  {:<12} {}x{}  f {:.2},{:.2}  c {:.2},{:.2}  centre ({:.3}, {:.3}, {:.3})",
            v.name,
            c.width,
            c.height,
            i.fx,
            i.fy,
            i.cx,
            i.cy,
            p.x,
            p.y,
            p.z
        );
    }
    Ok(())
}

/// The views `--sources` names: exactly three, the first the reference.
pub(crate) fn source_views<'a>(capture: &'a Capture, names: &[String]) -> Result<Vec<&'a CapturedView>> {
    if names.len() != 3 {
        return Err(Error::Usage(format!("--sources needs 3 view names, got {}", names.len())));
    }
    Ok(names.iter().map(|n| capture.view(n)).collect::<scnerf_capture::Result<_>>()?)
}

/// The capture's views to upload, thinned with a warning to `--max-views` or the server's
/// limit (`max_scene_views` of `GET /v1/limits`), whichever is smaller.
fn scene_views<'a>(client: &Client, capture: &'a Capture, max: usize) -> Result<Vec<&'a CapturedView>> {
    if max < 3 {
        return Err(Error::Usage(format!("--max-views must be at least 3, got {max}")));
    }
    let server = client.limits()?.max_scene_views;
    let (max, why) = if server < max {
        (server, format!("the server keeps at most {server} views per scene"))
    } else {
        (max, "--max-views".to_string())
    };
    let views: Vec<&CapturedView> =
        scnerf_capture::thin_evenly(capture.views.len(), max).into_iter().map(|i| &capture.views[i]).collect();
    if views.len() < capture.views.len() {
        eprintln!("warning: the capture has {} views; uploading {} of them ({why})", capture.views.len(), views.len());
    }
    Ok(views)
}

/// The cameras of `--path`, and the frame rate a camera path file asks for.
fn path_cameras(capture: &Capture, args: &RenderArgs) -> Result<(Vec<Camera>, Option<f64>)> {
    if args.frames == 0 {
        return Err(Error::Usage("--frames must be at least 1".into()));
    }
    let resize = |c: Camera| match args.size {
        Some((w, h)) => c.resized(w, h),
        None => c,
    };
    let cameras: Vec<Camera> = capture.views.iter().map(|v| v.camera.clone()).collect();
    let poses = match args.path.as_str() {
        "interpolate" => paths::interpolate(&cameras.iter().map(|c| c.w2c).collect::<Vec<_>>(), args.frames),
        "orbit" => paths::orbit(&cameras, args.frames)?,
        "spiral" => paths::spiral(&cameras, capture.near, capture.far, args.frames)?,
        file if Path::new(file).is_file() => {
            let path = paths::from_file(Path::new(file))?;
            for w in &path.warnings {
                eprintln!("warning: {w}");
            }
            return Ok((path.cameras.into_iter().map(resize).collect(), path.fps));
        }
        other => {
            return Err(Error::Usage(format!(
                "--path {other:?}: expected interpolate, orbit, spiral or a camera JSON file"
            )))
        }
    };
    let template = resize(cameras[0].clone());
    Ok((poses.into_iter().map(|w2c| Camera { w2c, ..template.clone() }).collect(), None))
}

fn progress_bar() -> ProgressBar {
    let bar = ProgressBar::new(0);
    let style = ProgressStyle::with_template("{bar:30} {pos}/{len} frames  {elapsed} elapsed, ETA {eta}  {msg}")
        .expect("valid template");
    bar.set_style(style);
    bar
}

/// A line above the progress bar, or on stderr when the bar is hidden (not a terminal).
fn notify(bar: &ProgressBar, message: &str) {
    if bar.is_hidden() {
        eprintln!("{message}");
    } else {
        bar.println(message);
    }
}

fn render(client: Client, args: &RenderArgs) -> Result<()> {
    let capture = load_for_server(&client, &args.data, &args.set)?;
    let (cameras, path_fps) = path_cameras(&capture, args)?;
    let started = Instant::now();
    let bar = progress_bar();
    let notices = bar.clone();
    let client = client.with_notice(move |m| notify(&notices, m));
    let views = scene_views(&client, &capture, args.upload.max_views)?;
    let mut scene = client.create_scene(args.upload.upload(&capture, &views))?;
    notify(&bar, &format!("uploaded {} views as scene {}", views.len(), scene.id));
    let done = render_frames(&client, &mut scene, &cameras, &args.out, !args.no_depth, &bar)?;
    bar.finish_and_clear();
    say!(
        "{} frames in {}: {} rendered, {} already there ({:.1} s)",
        cameras.len(),
        args.out.join("frames").display(),
        done.rendered,
        done.skipped,
        started.elapsed().as_secs_f64()
    );
    if args.no_video {
        return Ok(());
    }
    let ffmpeg = video::find_ffmpeg(std::env::var_os("PATH").as_deref());
    let digits = frame_digits(cameras.len());
    let fps = args.fps.unwrap_or_else(|| path_fps.map_or(24, |f| f.round().max(1.0) as u32));
    let v = video::write(&args.out.join("frames"), cameras.len(), digits, fps, &args.out, ffmpeg.as_deref())?;
    say!("video: {}", v.path.display());
    if let Some(note) = v.note {
        say!("note: {note}");
    }
    Ok(())
}

fn view(client: &Client, args: &ViewArgs) -> Result<()> {
    let capture = load_for_server(client, &args.data, &args.set)?;
    let pose = Path::new(&args.pose);
    let camera = if pose.is_file() {
        paths::camera_from_json(&readers::read_json(&Disk, pose)?, pose, "camera")?
    } else {
        capture.view(&args.pose)?.camera.clone()
    };
    let camera = match args.size {
        Some((w, h)) => camera.resized(w, h),
        None => camera,
    };
    let views = match &args.sources {
        Some(names) => source_views(&capture, names)?,
        None => scene_views(client, &capture, args.upload.max_views)?,
    };
    let mut scene = client.create_scene(args.upload.upload(&capture, &views))?;
    let rendered = client.render(&mut scene, &camera, true)?;
    write_atomically(&args.out, &rendered.rgb_png)?;
    let depth = args.out.with_extension("depth.npy");
    if let Some(d) = &rendered.depth {
        write_npy(&depth, d, rendered.height, rendered.width)?;
    }
    let names: Option<Vec<&str>> =
        rendered.sources.as_ref().map(|s| s.iter().filter_map(|&i| views.get(i).map(|v| v.name.as_str())).collect());
    say!("wrote {} ({}x{}) and {}", args.out.display(), rendered.width, rendered.height, depth.display());
    say!("{}{}", server_summary(&rendered), names.map(|n| format!(" ({})", n.join(","))).unwrap_or_default());
    Ok(())
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
