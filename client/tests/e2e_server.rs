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

use scnerf_client::api::{Client, Upload};
use scnerf_client::readers::{self, ReadOptions};
use scnerf_e2e::{http_request, repo_root, server_binary, ServerProcess};

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
/// default bundle, at a size that fits CI: 4 frames of 40x40 (each new source triple still builds
/// a paper-size volume from 800x800 sources: about a minute on 2 cores).
#[test]
#[cfg_attr(not(shared_data), ignore = "../shared/data is absent: the lego capture cannot be rendered")]
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
    for i in 0..FRAMES {
        let frame = out.path().join(format!("frames/frame_{i:04}.png"));
        assert_eq!(image::image_dimensions(&frame).unwrap(), (40, 40));
        assert!(out.path().join(format!("depth/frame_{i:04}.npy")).is_file());
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
    for i in 0..5 {
        let frame = out.path().join(format!("frames/frame_{i:04}.png"));
        assert_eq!(image::image_dimensions(&frame).unwrap(), (16, 12));
        assert!(out.path().join(format!("depth/frame_{i:04}.npy")).is_file());
    }
    assert!(out.path().join("video.gif").is_file(), "{stdout}");
    let again = run();
    assert!(String::from_utf8_lossy(&again.stdout).contains("0 rendered, 5 already there"));
}
