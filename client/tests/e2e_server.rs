//! End to end: `scnerf render` of the lego capture (20 views) against the real `scnerf-server`
//! with the default bundle, as the acceptance command, at a small size. Needs the
//! server's capture scenes (3..=N views per scene): today's server takes exactly 3 views per
//! scene, so this is ignored until that lands (`cargo test -p scnerf-client --test e2e_server
//! -- --ignored`). Skipped with a message when ../shared (the dataset) is absent.

use std::process::Command;
use std::time::Duration;

use scnerf_e2e::{repo_root, server_binary, ServerProcess};

#[test]
#[ignore = "needs capture scenes in the server"]
fn render_lego_orbit_to_frames_and_video() {
    let lego = repo_root().join("../shared/data/nerf_synthetic_lego");
    if !lego.is_dir() {
        eprintln!("skipped: {} is absent", lego.display());
        return;
    }
    let bundle = repo_root().join("bundles/default");
    let mut server = ServerProcess::start(&server_binary(), &["--bundle", bundle.to_str().unwrap()]);
    server.wait_ready(Duration::from_secs(600));
    let out = tempfile::tempdir().unwrap();
    let url = format!("http://{}", server.addr);
    let args = [
        "render",
        lego.to_str().unwrap(),
        "--server",
        &url,
        "--path",
        "orbit",
        "--frames",
        "24",
        "--size",
        "200x200",
        "--out",
        out.path().to_str().unwrap(),
    ];
    let run = Command::new(env!("CARGO_BIN_EXE_scnerf")).args(args).output().unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&run.stderr));
    for i in 0..24 {
        let frame = out.path().join(format!("frames/frame_{i:04}.png"));
        assert_eq!(image::image_dimensions(&frame).unwrap(), (200, 200));
        assert!(out.path().join(format!("depth/frame_{i:04}.npy")).is_file());
    }
    assert!(out.path().join("video.mp4").is_file() || out.path().join("video.gif").is_file(), "{stdout}");
}
