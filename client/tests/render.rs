//! Frames through the fake server: written as PNG + depth .npy, resumed after an interruption
//! (frames already there are skipped), a folder of another path refused; the video falls back to
//! a GIF without ffmpeg and runs ffmpeg when there is one.

mod common;

use std::path::{Path, PathBuf};

use common::FakeServer;
use indicatif::ProgressBar;
use scnerf_capture::camera::Camera;
use scnerf_capture::readers::{self, ReadOptions};
use scnerf_client::api::{Client, Upload};
use scnerf_client::render::{frame_path, render_frames, Done};
use scnerf_client::video;

fn capture_and_path(frames: usize) -> (Upload, Vec<Camera>) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/datasets/blender");
    let capture = readers::load(&dir, None, ReadOptions::default()).unwrap();
    let cams: Vec<Camera> = capture.views.iter().map(|v| v.camera.clone()).collect();
    let path = scnerf_client::paths::orbit(&cams, frames).unwrap();
    let template = cams[0].resized(16, 12);
    let cameras = path.into_iter().map(|w2c| Camera { w2c, ..template.clone() }).collect();
    let views: Vec<_> = capture.views.iter().collect();
    (Upload::new(&capture, &views), cameras)
}

#[test]
fn resumes_skipping_frames_already_written() {
    let server = FakeServer::start();
    let client = Client::new(&server.url, None);
    let (upload, cameras) = capture_and_path(4);
    let mut scene = client.create_scene(upload).unwrap();
    let out = tempfile::tempdir().unwrap();
    let bar = ProgressBar::hidden();

    let done = render_frames(&client, &mut scene, &cameras, out.path(), true, &bar).unwrap();
    assert_eq!(done, Done { rendered: 4, skipped: 0 });
    for i in 0..4 {
        assert!(frame_path(out.path(), i, 4).is_file());
        let npy = std::fs::read(out.path().join(format!("depth/frame_{i:04}.npy"))).unwrap();
        let depth = npyz::NpyFile::new(&npy[..]).unwrap();
        assert_eq!(depth.shape(), &[12, 16]);
        assert_eq!(depth.into_vec::<f32>().unwrap()[1], 2.01);
    }
    assert!(out.path().join("cameras.json").is_file());

    // an interrupted run: frame 2 never written
    std::fs::remove_file(frame_path(out.path(), 2, 4)).unwrap();
    let done = render_frames(&client, &mut scene, &cameras, out.path(), true, &bar).unwrap();
    assert_eq!(done, Done { rendered: 1, skipped: 3 });
    assert_eq!(server.renders(), 5);
    let leftovers: Vec<PathBuf> = std::fs::read_dir(out.path().join("frames"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.to_string_lossy().contains(".partial"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");

    // another path into the same folder would mix frames
    let (_, other) = capture_and_path(5);
    let err = render_frames(&client, &mut scene, &other, out.path(), true, &bar).unwrap_err().to_string();
    assert!(err.contains("holds frames of another camera path"), "{err}");
}

fn write_frames(dir: &Path, count: usize) {
    std::fs::create_dir_all(dir).unwrap();
    for i in 0..count {
        let img = image::RgbImage::from_fn(9, 7, |x, _| image::Rgb([(x * 20 + i as u32 * 30) as u8, 0, 0]));
        img.save(dir.join(format!("frame_{i:04}.png"))).unwrap();
    }
}

#[test]
fn gif_when_ffmpeg_is_not_on_path() {
    let dir = tempfile::tempdir().unwrap();
    write_frames(&dir.path().join("frames"), 3);
    let empty = tempfile::tempdir().unwrap();
    let ffmpeg = video::find_ffmpeg(Some(empty.path().as_os_str()));
    assert!(ffmpeg.is_none());
    let v = video::write(&dir.path().join("frames"), 3, 4, 12, dir.path(), ffmpeg.as_deref()).unwrap();
    assert_eq!(v.path, dir.path().join("video.gif"));
    assert!(v.note.unwrap().contains("ffmpeg is not on PATH"));
    use image::AnimationDecoder;
    let file = std::io::BufReader::new(std::fs::File::open(&v.path).unwrap());
    let frames = image::codecs::gif::GifDecoder::new(file).unwrap().into_frames().collect_frames().unwrap();
    assert_eq!(frames.len(), 3);
    assert_eq!(frames[0].buffer().dimensions(), (9, 7));
}

/// A stand-in `ffmpeg` (a shell script) that records its arguments and exits with `code`.
fn fake_ffmpeg(dir: &Path, code: i32) -> PathBuf {
    use std::os::unix::fs::PermissionsExt;
    let path = dir.join("ffmpeg");
    let script = format!(
        "#!/bin/sh\necho \"$@\" > \"{}/args\"\nif [ {code} -ne 0 ]; then echo \"Unknown encoder 'libx264'\" >&2; exit {code}; fi\n: > \"$(eval echo \\${{$#}})\"\n",
        dir.display()
    );
    std::fs::write(&path, script).unwrap();
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).unwrap();
    path
}

#[test]
fn mp4_through_ffmpeg_on_path_and_its_failure_reported() {
    let dir = tempfile::tempdir().unwrap();
    write_frames(&dir.path().join("frames"), 2);
    let bin = tempfile::tempdir().unwrap();
    fake_ffmpeg(bin.path(), 0);
    let path_var = std::env::join_paths([Path::new("/nonexistent"), bin.path()]).unwrap();
    let ffmpeg = video::find_ffmpeg(Some(&path_var)).unwrap();
    let v = video::write(&dir.path().join("frames"), 2, 4, 30, dir.path(), Some(&ffmpeg)).unwrap();
    assert_eq!(v.path, dir.path().join("video.mp4"));
    assert!(v.note.is_none() && v.path.is_file());
    let args = std::fs::read_to_string(bin.path().join("args")).unwrap();
    assert!(args.contains("-framerate 30 -i"), "{args}");
    assert!(args.contains("frames/frame_%04d.png"), "{args}");
    assert!(args.contains("-c:v libx264 -pix_fmt yuv420p"), "{args}");

    fake_ffmpeg(bin.path(), 1);
    let err = video::write(&dir.path().join("frames"), 2, 4, 30, dir.path(), Some(&ffmpeg)).unwrap_err().to_string();
    assert!(err.contains("failed (exit status: 1): Unknown encoder 'libx264'"), "{err}");
}
