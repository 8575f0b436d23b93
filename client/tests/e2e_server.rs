//! Against the real `scnerf-server`:
//! - with the small parity bundle: a capture PUT under its content id, rendered; the scene gone
//!   (deleted: the server answers a render 404 with the hint `reupload`, as for an expired or
//!   evicted scene or a replica that never had it), the client uploads it again under the same id
//!   by itself and the render goes on;
//!   and `scnerf render` of a 5-view capture to frames, depth and a video, in small;
//! - `scnerf render` of the lego capture (20 views) with the default bundle, the acceptance
//!   command, at a small size; reported as ignored when ../shared (the dataset) is absent.

use std::path::Path;
use std::process::Command;
use std::sync::{Arc, Mutex};
use std::time::Duration;

mod common;

use scnerf_capture::readers::{self, ReadOptions};
use scnerf_client::api::{Client, Upload};
use scnerf_e2e::{http_request, repo_root, server_binary, ServerProcess};
use serde_json::{json, Value};

/// A frame is a render, not a blank: its values spread (standard deviation over every channel of
/// every pixel above 2 levels of 255) and fewer than 99 % of its pixels are the background colour
/// (`background`, in [0, 1], rounded as the server quantises).
fn assert_not_blank(frame: &Path, background: [f64; 3]) {
    let img = image::open(frame).unwrap_or_else(|e| panic!("{}: {e}", frame.display())).into_rgb8();
    let values: Vec<f64> = img.as_raw().iter().map(|&b| f64::from(b)).collect();
    let mean = values.iter().sum::<f64>() / values.len() as f64;
    let std = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / values.len() as f64).sqrt();
    let bg = background.map(|c| (255.0 * c).round() as u8);
    let share = img.pixels().filter(|p| p.0 == bg).count() as f64 / f64::from(img.width() * img.height());
    eprintln!("{}: std {std:.2} of 255, {:.1} % background", frame.display(), 100.0 * share);
    assert!(std > 2.0, "{}: a blank frame (std {std:.2} of 255)", frame.display());
    assert!(share < 0.99, "{}: {:.1} % of the pixels are the background", frame.display(), 100.0 * share);
}

/// The orbit looks at the object's centre: the pixels that are not the background (the object's
/// silhouette) have their centroid in the middle third of the frame.
fn assert_object_centred(frame: &Path, background: [f64; 3]) {
    let img = image::open(frame).unwrap().into_rgb8();
    let bg = background.map(|c| (255.0 * c).round() as i32);
    let object: Vec<(u32, u32)> = img
        .enumerate_pixels()
        .filter(|(_, _, p)| p.0.iter().zip(bg).any(|(&c, b)| (i32::from(c) - b).abs() > 8))
        .map(|(x, y, _)| (x, y))
        .collect();
    assert!(!object.is_empty(), "{}: no object", frame.display());
    let n = object.len() as f64;
    let (cx, cy) = object.iter().fold((0.0, 0.0), |(sx, sy), &(x, y)| (sx + f64::from(x) / n, sy + f64::from(y) / n));
    let (w, h) = (f64::from(img.width()), f64::from(img.height()));
    let middle = |c: f64, size: f64| (size / 3.0..=2.0 * size / 3.0).contains(&c);
    assert!(middle(cx, w) && middle(cy, h), "{}: the object's centroid is at ({cx:.1}, {cy:.1})", frame.display());
}

/// The value of an unlabelled sample (`name value`) of the server's /metrics.
fn metric(server: &ServerProcess, name: &str) -> f64 {
    let r = http_request(server.addr, "GET", "/metrics", &[], b"", Duration::from_secs(10)).unwrap();
    let text = String::from_utf8(r.body).unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(name).and_then(|v| v.strip_prefix(' ')))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no {name} in /metrics:\n{text}"))
}

#[test]
fn uploads_again_under_the_same_id_when_the_server_lost_the_scene() {
    let bundle = repo_root().join("tests/fixtures/parity/bundle");
    let mut server = ServerProcess::start(&server_binary(), &["--bundle", bundle.to_str().unwrap(), "--skip-warmup"]);
    server.wait_ready(Duration::from_secs(120));
    let notices = Arc::new(Mutex::new(Vec::<String>::new()));
    let sink = notices.clone();
    let client = Client::new(&format!("http://{}", server.addr), None)
        .with_notice(move |m| sink.lock().unwrap().push(m.to_string()));

    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/datasets/blender");
    let capture = readers::load(&data, None, ReadOptions::default()).unwrap();
    let views: Vec<_> = capture.views.iter().collect();
    let target = capture.views[0].camera.resized(16, 12);
    let mut scene = client.create_scene(Upload::new(&capture, &views)).unwrap();
    let id = scene.id.clone();
    assert!(id.starts_with("cap-"), "{id}");
    let first = client.render(&mut scene, &target, true).unwrap();
    assert_eq!((first.width, first.height, first.depth.as_ref().map(Vec::len)), (16, 12, Some(16 * 12)));
    assert_eq!(first.sources.as_ref().map(Vec::len), Some(3));
    assert!(notices.lock().unwrap().is_empty());

    let path = format!("/v1/scenes/{id}");
    let deleted = http_request(server.addr, "DELETE", &path, &[], b"", Duration::from_secs(10)).unwrap();
    assert_eq!(deleted.status, 204);
    let again = client.render(&mut scene, &target, true).unwrap();
    assert_eq!(scene.id, id, "uploaded again under the same id");
    assert_eq!(again.rgb_png, first.rgb_png, "the same scene renders the same view");
    assert_eq!(notices.lock().unwrap().len(), 1);
    assert!(notices.lock().unwrap()[0].contains("uploading the capture again"));
    // one lookup missed (the render after the delete); the scene is back
    assert_eq!(metric(&server, "scnerf_scene_cache_misses_total"), 1.0);
    assert_eq!(metric(&server, "scnerf_scene_cache_entries"), 1.0);
}

/// The acceptance command, `scnerf render` of the lego capture (20 views) around an orbit with the
/// default bundle, at a small size: 4 frames of 40x40 (each new source triple still builds a
/// paper-size volume from 800x800 sources: about a minute on 2 cores; full tier). Each frame shows
/// the object in its middle, from another side than the frame before.
#[test]
#[cfg_attr(not(shared_data), ignore = "../shared/data is absent: the lego capture cannot be rendered")]
#[cfg_attr(
    all(shared_data, not(full_tier)),
    ignore = "full tier (scripts/test.sh --full): a paper-size volume from 800x800 sources"
)]
fn render_lego_orbit_to_frames_and_video() {
    const FRAMES: usize = 4;
    let lego = repo_root().join("../shared/data/nerf_synthetic_lego");
    let bundle = repo_root().join("bundles/default");
    let mut server = ServerProcess::start(&server_binary(), &["--bundle", bundle.to_str().unwrap()]);
    server.wait_ready(Duration::from_secs(600));
    let out = tempfile::tempdir().unwrap();
    let url = format!("http://{}", server.addr);
    let frames = FRAMES.to_string();
    let args = [
        "render",
        lego.to_str().unwrap(),
        "--server",
        &url,
        "--path",
        "orbit",
        "--frames",
        &frames,
        "--size",
        "40x40",
        "--out",
        out.path().to_str().unwrap(),
    ];
    let run = Command::new(env!("CARGO_BIN_EXE_scnerf")).args(args).output().unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&run.stderr));
    let background = readers::load(&lego, None, ReadOptions::default()).unwrap().background;
    let mut frames = Vec::new();
    for i in 0..FRAMES {
        let frame = out.path().join(format!("frames/frame_{i:04}.png"));
        assert_eq!(image::image_dimensions(&frame).unwrap(), (40, 40));
        assert_not_blank(&frame, background);
        assert_object_centred(&frame, background);
        assert!(out.path().join(format!("depth/frame_{i:04}.npy")).is_file());
        frames.push(image::open(&frame).unwrap().into_rgb8());
    }
    // The camera goes round the object: each frame shows it from another side.
    for (i, pair) in frames.windows(2).enumerate() {
        let moved = pair[0].pixels().zip(pair[1].pixels()).filter(|(a, b)| a != b).count();
        assert!(moved * 10 > 40 * 40, "frames {i} and {} differ in only {moved} pixels", i + 1);
    }
    assert!(out.path().join("video.mp4").is_file() || out.path().join("video.gif").is_file(), "{stdout}");
}

/// The acceptance command's path in small, in every test run: `scnerf render` of a 5-view capture
/// (the Blender fixture) through its captured poses (`--path interpolate`) against the real server with the parity bundle, to PNG
/// frames, depth maps and a video (a GIF: no ffmpeg on PATH), then once more: nothing to render.
#[test]
fn render_a_capture_to_frames_and_video_through_the_real_server() {
    let bundle = repo_root().join("tests/fixtures/parity/bundle");
    let mut server = ServerProcess::start(&server_binary(), &["--bundle", bundle.to_str().unwrap(), "--skip-warmup"]);
    server.wait_ready(Duration::from_secs(120));
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/datasets/blender");
    let out = tempfile::tempdir().unwrap();
    let no_tools = tempfile::tempdir().unwrap();
    let url = format!("http://{}", server.addr);
    let args = [
        "render",
        data.to_str().unwrap(),
        "--server",
        &url,
        "--path",
        "interpolate",
        "--frames",
        "5",
        "--size",
        "16x12",
        "--out",
        out.path().to_str().unwrap(),
    ];
    let run = || Command::new(env!("CARGO_BIN_EXE_scnerf")).args(args).env("PATH", no_tools.path()).output().unwrap();
    let first = run();
    let (stdout, stderr) = (String::from_utf8_lossy(&first.stdout), String::from_utf8_lossy(&first.stderr));
    assert!(first.status.success(), "{stdout}\n{stderr}");
    assert!(stderr.contains("uploaded 5 views as scene cap-"), "{stderr}");
    assert!(stdout.contains("5 rendered, 0 already there"), "{stdout}");
    let background = readers::load(&data, None, ReadOptions::default()).unwrap().background;
    for i in 0..5 {
        let frame = out.path().join(format!("frames/frame_{i:04}.png"));
        assert_eq!(image::image_dimensions(&frame).unwrap(), (16, 12));
        assert_not_blank(&frame, background);
        assert!(out.path().join(format!("depth/frame_{i:04}.npy")).is_file());
    }
    assert!(out.path().join("video.gif").is_file(), "{stdout}");
    let again = run();
    assert!(String::from_utf8_lossy(&again.stdout).contains("0 rendered, 5 already there"));
}

/// Runs `scnerf` with `args` and a PATH without ffmpeg; (stdout, stderr), asserting success.
fn scnerf_ok(args: &[&str]) -> (String, String) {
    let no_tools = tempfile::tempdir().unwrap();
    let run = Command::new(env!("CARGO_BIN_EXE_scnerf")).args(args).env("PATH", no_tools.path()).output().unwrap();
    let (stdout, stderr) =
        (String::from_utf8_lossy(&run.stdout).into_owned(), String::from_utf8_lossy(&run.stderr).into_owned());
    assert!(run.status.success(), "{stdout}\n{stderr}");
    (stdout, stderr)
}

fn frame_files(out: &Path, count: usize) -> Vec<Vec<u8>> {
    (0..count).map(|i| std::fs::read(out.join(format!("frames/frame_{i:04}.png"))).unwrap()).collect()
}

/// The commands in small against the real server (parity bundle, a source limit of
/// 64x48): an LLFF capture as distributed renders a spiral without flags from images_4, named;
/// a nerfstudio camera_path.json of that spiral's poses renders to frames and a video, the
/// frames identical to those of the same cameras in the API's own form.
#[test]
fn distributed_llff_and_nerfstudio_camera_paths_through_the_real_server() {
    let bundle = repo_root().join("tests/fixtures/parity/bundle");
    let args = ["--bundle", bundle.to_str().unwrap(), "--skip-warmup", "--max-source-pixels", "3072"];
    let mut server = ServerProcess::start(&server_binary(), &args);
    server.wait_ready(Duration::from_secs(120));
    let url = format!("http://{}", server.addr);
    let data = tempfile::tempdir().unwrap();
    common::captures::llff(data.path(), (256, 192), &[4, 8]);
    let data = data.path().to_str().unwrap();

    let spiral = tempfile::tempdir().unwrap();
    let (_, stderr) = scnerf_ok(&[
        "render",
        data,
        "--server",
        &url,
        "--path",
        "spiral",
        "--frames",
        "3",
        "--size",
        "32x24",
        "--out",
        spiral.path().to_str().unwrap(),
    ]);
    assert!(
        stderr.contains("image set: images_4 (64x48) of images (256x192), images_4 (64x48), images_8 (32x24)"),
        "{stderr}"
    );

    // the spiral's poses, seen by a lens nerfstudio's way (vertical fov, centred principal point)
    let cameras: Vec<Value> =
        serde_json::from_str(&std::fs::read_to_string(spiral.path().join("cameras.json")).unwrap()).unwrap();
    let (w, h, fov) = (32.0, 24.0, 50.0f64);
    let f = h / 2.0 / (fov.to_radians() / 2.0).tan();
    let w2c = |c: &Value| nalgebra::Matrix4::from_fn(|r, k| c["pose"]["matrix"][r][k].as_f64().unwrap());
    let flip = nalgebra::Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, -1.0, -1.0, 1.0));
    let ns_path: Vec<Value> = cameras
        .iter()
        .map(|c| {
            let c2w_gl = w2c(c).try_inverse().unwrap() * flip;
            json!({"camera_to_world": c2w_gl.transpose().iter().collect::<Vec<_>>(), "fov": fov, "aspect": w / h})
        })
        .collect();
    let own: Vec<Value> = cameras
        .iter()
        .map(|c| json!({"width": 32, "height": 24, "intrinsics": {"fx": f, "fy": f, "cx": w / 2.0 - 0.5, "cy": h / 2.0 - 0.5},
                         "pose": c["pose"]}))
        .collect();
    let files = tempfile::tempdir().unwrap();
    let ns_file = files.path().join("camera_path.json");
    let ns = json!({"camera_type": "perspective", "render_width": 32, "render_height": 24, "camera_path": ns_path,
                    "fps": 12, "seconds": 0.25});
    std::fs::write(&ns_file, ns.to_string()).unwrap();
    let own_file = files.path().join("cameras.json");
    std::fs::write(&own_file, Value::Array(own).to_string()).unwrap();

    let (from_ns, from_own) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    for (file, out) in [(&ns_file, &from_ns), (&own_file, &from_own)] {
        let (stdout, _) = scnerf_ok(&[
            "render",
            data,
            "--server",
            &url,
            "--path",
            file.to_str().unwrap(),
            "--out",
            out.path().to_str().unwrap(),
        ]);
        assert!(stdout.contains("3 rendered") && out.path().join("video.gif").is_file(), "{stdout}");
    }
    assert_eq!(image::image_dimensions(from_ns.path().join("frames/frame_0000.png")).unwrap(), (32, 24));
    let frames = frame_files(from_ns.path(), 3);
    assert!(frames == frame_files(from_own.path(), 3), "the same cameras, the same frames");
    assert!(frames[0] != frames[1] && frames[1] != frames[2], "other poses, other views");
}
