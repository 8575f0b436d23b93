//! The `scnerf` binary end to end against the fake server: what a user runs and reads.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use common::FakeServer;
use scnerf_client::metrics::Image;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/datasets").join(name)
}

/// Runs `scnerf` with a PATH that has no ffmpeg.
fn scnerf(args: &[&str]) -> Output {
    let no_tools = tempfile::tempdir().unwrap();
    Command::new(env!("CARGO_BIN_EXE_scnerf"))
        .args(args)
        .env("PATH", no_tools.path())
        .env_remove("SCNERF_SERVER")
        .output()
        .unwrap()
}

fn text(out: &Output) -> (String, String) {
    (String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned())
}

#[test]
fn render_writes_frames_depth_and_a_gif_then_resumes() {
    let server = FakeServer::start();
    let out = tempfile::tempdir().unwrap();
    let data = fixture("blender");
    let args = [
        "render",
        data.to_str().unwrap(),
        "--server",
        &server.url,
        "--path",
        "orbit",
        "--frames",
        "6",
        "--size",
        "16x12",
        "--out",
        out.path().to_str().unwrap(),
    ];
    let first = scnerf(&args);
    let (stdout, stderr) = text(&first);
    assert!(first.status.success(), "{stdout}\n{stderr}");
    assert!(stderr.contains("warning: ") && stderr.contains("2 of 7 frames have no image file; skipped"), "{stderr}");
    assert!(stderr.contains("uploaded 5 views as scene cap-"), "{stderr}");
    assert!(stdout.contains("6 frames in") && stdout.contains("6 rendered, 0 already there"), "{stdout}");
    assert!(stdout.contains("video.gif") && stdout.contains("note: ffmpeg is not on PATH"), "{stdout}");
    for i in 0..6 {
        assert!(out.path().join(format!("frames/frame_{i:04}.png")).is_file());
        assert!(out.path().join(format!("depth/frame_{i:04}.npy")).is_file());
    }
    assert!(out.path().join("video.gif").is_file());
    assert_eq!(server.uploads(), vec![5]);

    let again = scnerf(&args);
    let (stdout, _) = text(&again);
    assert!(stdout.contains("0 rendered, 6 already there"), "{stdout}");
    assert_eq!(server.renders(), 6);
}

#[test]
fn view_renders_one_named_view_from_three_sources() {
    let server = FakeServer::start();
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("v.png");
    let data = fixture("blender");
    let out = scnerf(&[
        "view",
        data.to_str().unwrap(),
        "--server",
        &server.url,
        "--pose",
        "train/r_1",
        "--size",
        "16x12",
        "--sources",
        "train/r_0,train/r_2,val/r_0",
        "--scene-id",
        "my-view",
        "--out",
        png.to_str().unwrap(),
    ]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("(16x12)")
            && stdout.contains("server: renderer 12 ms, total 13 ms; sources 0,1,2 (train/r_0,train/r_2,val/r_0)"),
        "{stdout}"
    );
    assert_eq!(image::image_dimensions(&png).unwrap(), (16, 12));
    assert!(dir.path().join("v.depth.npy").is_file());
    assert_eq!(server.uploads(), vec![3]);
    assert_eq!(server.ids(), vec!["my-view"]);
}

/// `scnerf view` of the Blender fixture's train/r_1 at 8x6 into `dir`, with `extra` flags.
fn view_r_1(server: &FakeServer, dir: &Path, extra: &[&str]) -> Output {
    let data = fixture("blender");
    let png = dir.join("v.png");
    let mut args = vec!["view", data.to_str().unwrap(), "--server", &server.url, "--pose", "train/r_1"];
    args.extend(["--size", "8x6", "--out", png.to_str().unwrap()]);
    args.extend(extra);
    scnerf(&args)
}

#[test]
fn sampling_is_sent_only_when_asked_for_and_reported() {
    let server = FakeServer::start();
    let dir = tempfile::tempdir().unwrap();
    let view = |extra: &[&str]| view_r_1(&server, dir.path(), extra);
    let out = view(&["--sampling", "full"]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("; full, 128.0 samples per ray"), "{stdout}");
    let out = view(&[]);
    assert!(out.status.success());
    assert_eq!(*server.state.samplings.lock().unwrap(), vec![Some("full".to_string()), None]);
    let bad = view(&["--sampling", "fast"]);
    let (_, stderr) = text(&bad);
    assert!(!bad.status.success() && stderr.contains("--sampling"), "{stderr}");
}

/// `--model` names the model in the upload (so the scene belongs to it, under an id of its
/// own) and in every render; without it neither says one and the server's default renders.
#[test]
fn the_model_is_sent_with_the_upload_and_the_renders_only_when_named() {
    let server = FakeServer::start();
    let dir = tempfile::tempdir().unwrap();
    let view = |extra: &[&str]| {
        let out = view_r_1(&server, dir.path(), extra);
        let (stdout, stderr) = text(&out);
        assert!(out.status.success(), "{stdout}\n{stderr}");
    };
    view(&["--model", "lego-refined"]);
    view(&[]);
    let named = Some("lego-refined".to_string());
    assert_eq!(*server.state.upload_models.lock().unwrap(), vec![named.clone(), None]);
    assert_eq!(*server.state.render_models.lock().unwrap(), vec![named, None]);
    let ids = server.ids();
    assert_ne!(ids[0], ids[1], "a scene of another model has an id of its own");
}

#[test]
fn eval_scores_held_out_views_against_the_nearest_sources() {
    let server = FakeServer::start();
    let data = fixture("dtu");
    let out =
        scnerf(&["eval", data.to_str().unwrap(), "--server", &server.url, "--targets", "0,3", "--downscale", "32"]);
    let (stdout, stderr) = text(&out);
    // views 1 and 2 are all that is left: not enough sources
    assert!(!out.status.success());
    assert!(stderr.contains("error: 2 of 4 views held out: fewer than 3 are left as sources"), "{stderr}");

    let out = scnerf(&["eval", data.to_str().unwrap(), "--server", &server.url, "--holdout", "4", "--downscale", "32"]);
    let (stdout2, stderr2) = text(&out);
    assert!(out.status.success(), "{stdout}{stdout2}\n{stderr2}");
    let lines: Vec<&str> = stdout2.lines().collect();
    assert_eq!(lines.len(), 2, "{stdout2}");
    assert!(
        lines[0].trim_start().starts_with("0  ") && lines[0].contains("1,2,3") && lines[0].contains("PSNR"),
        "{stdout2}"
    );
    assert!(lines[1].trim_start().starts_with("mean"), "{stdout2}");
    assert_eq!(server.uploads(), vec![3]);
}

#[test]
fn eval_writes_each_views_render_and_its_absolute_error() {
    let server = FakeServer::start();
    let data = fixture("dtu");
    let out = tempfile::tempdir().unwrap();
    let dir = out.path().to_str().unwrap();
    let run = scnerf(&[
        "eval",
        data.to_str().unwrap(),
        "--server",
        &server.url,
        "--holdout",
        "4",
        "--downscale",
        "32",
        "--out",
        dir,
    ]);
    assert!(run.status.success(), "{:?}", text(&run));
    let read = |path: &Path| Image::decode(&std::fs::read(path).unwrap(), [0.0; 3]).unwrap();
    let render = read(&out.path().join("0.png"));
    let error = read(&out.path().join("0.error.png"));
    let truth = read(&data.join("Rectified/scan1_train/rect_001_3_r5000.png")).downscaled(32);
    assert_eq!((error.width, error.height), (render.width, render.height));
    let expected: Vec<f64> =
        render.data.iter().zip(&truth.data).map(|(r, t)| ((r - t).abs() * 255.0).round()).collect();
    let got: Vec<f64> = error.data.iter().map(|e| (e * 255.0).round()).collect();
    assert_eq!(got, expected);
    assert!(got.iter().any(|&e| e > 0.0), "the fake render differs from the truth somewhere");
}

#[test]
fn info_and_bad_input_in_plain_words() {
    let out = scnerf(&["info", fixture("colmap_binary").to_str().unwrap()]);
    let (stdout, _) = text(&out);
    assert!(stdout.starts_with("colmap: 4 views, near 1.6393846850976874 far 4.9899239451399096"), "{stdout}");

    let out = scnerf(&["info", "/no/such/capture"]);
    let (_, stderr) = text(&out);
    assert_eq!(out.status.code(), Some(1));
    assert_eq!(stderr.trim(), "error: /no/such/capture: no such dataset folder");

    let server = FakeServer::start();
    let out = scnerf(&["render", fixture("llff").to_str().unwrap(), "--path", "orbit", "--server", &server.url]);
    let (_, stderr) = text(&out);
    assert!(
        stderr.contains(
            "error: the cameras do not look at a common point (a forward-facing capture?): use --path spiral"
        ),
        "{stderr}"
    );

    let out = scnerf(&[
        "render",
        fixture("llff").to_str().unwrap(),
        "--path",
        "spiral",
        "--frames",
        "2",
        "--server",
        "http://127.0.0.1:9",
    ]);
    let (_, stderr) = text(&out);
    // the first call asks the server for its limits, before the capture is read
    assert!(stderr.contains("error: cannot reach the server at http://127.0.0.1:9/v1/limits"), "{stderr}");

    let out = scnerf(&["render", fixture("llff").to_str().unwrap(), "--path", "zigzag", "--server", &server.url]);
    let (_, stderr) = text(&out);
    assert!(
        stderr.contains("--path \"zigzag\": expected interpolate, orbit, spiral or a camera JSON file"),
        "{stderr}"
    );

    let out = scnerf(&["render", fixture("llff").to_str().unwrap(), "--path", "orbit", "--size", "16by12"]);
    assert!(text(&out).1.contains("expected WxH"), "{}", text(&out).1);
}

/// `scnerf render DATA --path spiral ...` into a fresh folder against `server`; its output.
fn render_spiral(server: &FakeServer, data: &Path, extra: &[&str]) -> (String, String) {
    let out = tempfile::tempdir().unwrap();
    let mut args = vec!["render", data.to_str().unwrap(), "--server", &server.url, "--path", "spiral"];
    args.extend(["--frames", "2", "--size", "16x12", "--no-video", "--out", out.path().to_str().unwrap()]);
    args.extend(extra);
    let run = scnerf(&args);
    let (stdout, stderr) = text(&run);
    assert!(run.status.success(), "{stdout}\n{stderr}");
    (stdout, stderr)
}

fn first_image_sizes(server: &FakeServer) -> Vec<(u32, u32)> {
    server.state.first_image_sizes.lock().unwrap().clone()
}

/// An LLFF capture as distributed (images/, images_4/, images_8/): without flags the largest set
/// within the server's source limit is uploaded and named; `--downscale 8` takes images_8.
#[test]
fn llff_as_distributed_uploads_the_largest_set_the_server_takes() {
    let data = tempfile::tempdir().unwrap();
    common::captures::llff(data.path(), (256, 192), &[4, 8]);
    let server = FakeServer::start();
    server.state.max_source_pixels.store(64 * 48, std::sync::atomic::Ordering::SeqCst);
    let (_, stderr) = render_spiral(&server, data.path(), &[]);
    assert!(
        stderr.contains(
            "image set: images_4 (64x48) of images (256x192), images_4 (64x48), images_8 (32x24): the largest within \
             the server's limit of 3072 pixels per source view"
        ),
        "{stderr}"
    );
    let (_, stderr) = render_spiral(&server, data.path(), &["--downscale", "8"]);
    assert!(
        stderr.contains("image set: images_8 (32x24) of images (256x192)") && stderr.contains("(--downscale 8)"),
        "{stderr}"
    );
    assert_eq!(first_image_sizes(&server), [(64, 48), (32, 24)]);
    let run = scnerf(&[
        "render",
        data.path().to_str().unwrap(),
        "--server",
        &server.url,
        "--path",
        "spiral",
        "--downscale",
        "2",
    ]);
    let (_, stderr) = text(&run);
    assert!(!run.status.success());
    assert!(
        stderr.contains("downscale 2: there is no images_2 folder; the capture has images (256x192), images_4"),
        "{stderr}"
    );
}

/// The same with nerfstudio's images_2/4/8; with a limit below every set, the smallest is
/// resized here to fit, said in one line, and the images sent are of the cameras' size.
#[test]
fn nerfstudio_sets_and_resizing_when_none_fits() {
    let data = tempfile::tempdir().unwrap();
    common::captures::nerfstudio(data.path(), (128, 96), &[2, 4, 8]);
    let server = FakeServer::start();
    server.state.max_source_pixels.store(1000, std::sync::atomic::Ordering::SeqCst);
    let (_, stderr) = render_spiral(&server, data.path(), &[]);
    assert!(stderr.contains("image set: images_4 (32x24) of images (128x96), images_2 (64x48), images_4 (32x24), images_8 (16x12): the largest"), "{stderr}");
    // a set chosen by hand that exceeds the limit is resized too
    let (_, stderr) = render_spiral(&server, data.path(), &["--downscale", "2"]);
    assert!(stderr.contains("image set: images_2 (64x48)"), "{stderr}");
    let note = "note: 5 images of 64x48 exceed the server's limit of 1000 pixels per source view: resizing them to \
                36x27";
    assert!(stderr.contains(note), "{stderr}");
    server.state.max_source_pixels.store(100, std::sync::atomic::Ordering::SeqCst);
    let (_, stderr) = render_spiral(&server, data.path(), &[]);
    let note = "note: 5 images of 16x12 exceed the server's limit of 100 pixels per source view: resizing them to 11x8";
    assert!(stderr.contains(note), "{stderr}");
    assert!(!stderr.contains("image set:"), "{stderr}");
    // the fake checks that every image is of its camera's size
    assert_eq!(first_image_sizes(&server), [(32, 24), (36, 27), (11, 8)]);
}

/// A phone capture as its tools leave it (instant-ngp layout, lens distortion, no depth range,
/// portrait photos over the server's source limit): info, render and eval run without flags;
/// eval fits its sources to the limit as render does, said in the same line, and scores the
/// targets at their own size against their undistorted photos.
#[test]
fn a_phone_capture_needs_no_flags_and_eval_fits_sources_as_render_does() {
    let data = tempfile::tempdir().unwrap();
    common::captures::phone(data.path(), (54, 96), 9);
    let path = data.path().to_str().unwrap();
    let (stdout, stderr) = text(&scnerf(&["info", path]));
    assert!(stdout.starts_with("nerfstudio: 9 views, near "), "{stdout}\n{stderr}");
    assert!(stdout.contains("(from the poses (0.4 x the nearest"), "{stdout}");
    assert!(stdout.contains("undistorted: 9 views, to pinhole cameras of the same size"), "{stdout}");

    let server = FakeServer::start();
    server.state.max_source_pixels.store(3000, std::sync::atomic::Ordering::SeqCst);
    let note = "note: 9 images of 54x96 exceed the server's limit of 3000 pixels per source view: resizing them to \
                41x73";
    let (_, stderr) = render_spiral(&server, data.path(), &[]);
    assert!(stderr.contains(note), "{stderr}");

    let out = scnerf(&["eval", path, "--server", &server.url, "--holdout", "4", "--downscale", "2"]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(stderr.contains(note), "{stderr}");
    assert_eq!(stdout.lines().filter(|l| l.contains("PSNR")).count(), 4, "3 targets and the mean: {stdout}");
    // every scene the fake took (it checks each image is its camera's size) is of fitted sources
    assert!(first_image_sizes(&server).iter().all(|&size| size == (41, 73)), "{:?}", first_image_sizes(&server));
}
