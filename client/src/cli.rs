//! The `scnerf` command line: `info`, `render`, `view`, `eval`.

use std::path::Path;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};

use crate::api::Client;
use crate::args::{Cli, Command, DataArgs, FormatArg, ImageSetArgs, RenderArgs, UndistortTo, ViewArgs};
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

pub fn run(cli: Cli) -> Result<()> {
    let client = Client::new(&cli.server, cli.token).with_sampling(cli.sampling).with_model(cli.model);
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
        Some(names) => eval::source_views(&capture, names)?,
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
