//! The HTTP client against the in-process fake server: upload once under an id derived from the
//! capture (or the caller's), render, wait out 503 with Retry-After, upload again once under the
//! same id on a 404 with the hint `reupload` (and only then), server errors in plain words.

mod common;

use std::path::Path;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use common::FakeServer;
use scnerf_capture::readers::{self, CapturedView, ReadOptions};
use scnerf_client::api::{Client, Upload};

fn fixture_upload() -> (Upload, scnerf_capture::camera::Camera) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/datasets/blender");
    let capture = readers::load(&dir, None, ReadOptions::default()).unwrap();
    let views: Vec<_> = capture.views.iter().collect();
    (Upload::new(&capture, &views), capture.views[0].camera.resized(16, 12))
}

/// A client whose notices are kept for the test to read.
fn client(server: &FakeServer) -> (Client, Arc<Mutex<Vec<String>>>) {
    let notices = Arc::new(Mutex::new(Vec::new()));
    let sink = notices.clone();
    (Client::new(&server.url, None).with_notice(move |m| sink.lock().unwrap().push(m.to_string())), notices)
}

#[test]
fn uploads_the_capture_once_and_renders_views_of_it() {
    let server = FakeServer::start();
    let (client, notices) = client(&server);
    let (upload, target) = fixture_upload();
    let mut scene = client.create_scene(upload).unwrap();
    for _ in 0..2 {
        let r = client.render(&mut scene, &target, true).unwrap();
        let png = image::load_from_memory(&r.rgb_png).unwrap();
        assert_eq!((png.width(), png.height(), r.width, r.height), (16, 12, 16, 12));
        let depth = r.depth.unwrap();
        assert_eq!(depth.len(), 16 * 12);
        assert_eq!((depth[0], depth[1]), (2.0, 2.01));
        assert_eq!(r.timings_ms["renderer"], 12.5);
        assert_eq!(r.sources, Some(vec![0, 1, 2]));
    }
    assert_eq!(server.uploads(), vec![5]);
    assert_eq!(server.renders(), 2);
    assert!(scene.id.starts_with("cap-") && scene.id.len() == 36, "{}", scene.id);
    assert!(notices.lock().unwrap().is_empty());
    let rgb_only = client.render(&mut scene, &target, false).unwrap();
    assert!(rgb_only.depth.is_none());
}

#[test]
fn waits_out_503_for_its_retry_after() {
    let server = FakeServer::start();
    let (client, notices) = client(&server);
    let (upload, target) = fixture_upload();
    let mut scene = client.create_scene(upload).unwrap();
    server.state.busy.store(2, Ordering::SeqCst);
    let started = Instant::now();
    client.render(&mut scene, &target, false).unwrap();
    assert!(started.elapsed().as_secs_f64() >= 2.0, "waited Retry-After (1 s) twice");
    let notices = notices.lock().unwrap();
    assert_eq!(notices.len(), 2);
    assert!(
        notices[0].contains("(503 overloaded): the inference queue is full; retrying in 1 s (1/30)"),
        "{}",
        notices[0]
    );
}

#[test]
fn gives_up_after_max_retries() {
    let server = FakeServer::start();
    let (mut client, _) = client(&server);
    client.max_retries = 1;
    let (upload, target) = fixture_upload();
    let mut scene = client.create_scene(upload).unwrap();
    server.state.busy.store(2, Ordering::SeqCst);
    let err = client.render(&mut scene, &target, false).unwrap_err().to_string();
    assert_eq!(err, "the server refused the request (503 overloaded): the inference queue is full");
}

#[test]
fn uploads_again_once_when_the_server_lost_the_scene() {
    let server = FakeServer::start();
    let (client, notices) = client(&server);
    let (upload, target) = fixture_upload();
    let mut scene = client.create_scene(upload).unwrap();
    let first_id = scene.id.clone();
    server.state.forget.store(1, Ordering::SeqCst);
    client.render(&mut scene, &target, false).unwrap();
    assert_eq!(server.uploads(), vec![5, 5]);
    // The same id again: behind a proxy that routes by it, the same replica.
    assert_eq!(scene.id, first_id);
    assert_eq!(server.ids(), vec![first_id.clone(), first_id.clone()]);
    assert!(notices.lock().unwrap()[0].contains("uploading the capture again"));

    // lost again right after the new upload: not a loop
    server.state.forget.store(2, Ordering::SeqCst);
    let err = client.render(&mut scene, &target, false).unwrap_err().to_string();
    assert!(err.contains("(404 scene_not_found): no such scene (expired?) [field: scene_id]"), "{err}");
    assert_eq!(server.uploads().len(), 3);

    // a 404 without the hint is not about the scene: no upload
    server.state.unrouted.store(1, Ordering::SeqCst);
    let err = client.render(&mut scene, &target, false).unwrap_err().to_string();
    assert_eq!(err, "the server refused the request (404 not_found): no route [field: path]");
    assert_eq!(server.uploads().len(), 3);
}

#[test]
fn a_named_scene_keeps_its_name_through_a_reupload() {
    let server = FakeServer::start();
    let (client, _) = client(&server);
    let (upload, target) = fixture_upload();
    let mut scene = client.create_scene(Upload { scene_id: Some("lego.orbit-1".into()), ..upload }).unwrap();
    assert_eq!(scene.id, "lego.orbit-1");
    server.state.forget.store(1, Ordering::SeqCst);
    client.render(&mut scene, &target, false).unwrap();
    assert_eq!(server.ids(), vec!["lego.orbit-1", "lego.orbit-1"]);
    assert_eq!(scene.id, "lego.orbit-1");
}

#[test]
fn errors_are_plain_words() {
    let server = FakeServer::start();
    let (client, _) = client(&server);
    let (upload, target) = fixture_upload();
    let mut scene = client.create_scene(upload).unwrap();
    let err = client.render(&mut scene, &target.resized(5000, 10), false).unwrap_err().to_string();
    assert_eq!(err, "the server refused the request (422 invalid): target too large [field: target.width]");

    // refused from the request part while 9 x 4 MB of images are still on their way: the
    // server's answer, not a broken pipe, whether or not the connection closed mid-upload
    let big = tempfile::tempdir().unwrap();
    let (mut upload, _) = fixture_upload();
    let noise: Vec<u8> = (0..4u32 << 20).map(|i| (i.wrapping_mul(2654435761) >> 24) as u8).collect();
    let first = upload.sources[0].clone();
    upload.sources = (0..9)
        .map(|i| {
            let image_path = big.path().join(format!("{i}.png"));
            std::fs::write(&image_path, &noise).unwrap();
            CapturedView { image_path, ..first.clone() }
        })
        .collect();
    let err = client.create_scene(upload).unwrap_err().to_string();
    assert_eq!(
        err,
        "the server refused the request (422 invalid_request): a scene takes at most 8 views, got 9 [field: sources]"
    );

    let (upload, _) = fixture_upload();
    let err = Client::new("http://127.0.0.1:9", None).create_scene(upload).unwrap_err().to_string();
    assert!(err.starts_with("cannot reach the server at http://127.0.0.1:9/v1/scenes/cap-"), "{err}");
    assert!(err.contains("Connection refused"), "{err}");
}

#[test]
fn the_scene_id_names_the_capture() {
    let server = FakeServer::start();
    let (client, _) = client(&server);
    let (upload, _) = fixture_upload();
    let a = client.create_scene(upload.clone()).unwrap().id;
    assert_eq!(client.create_scene(upload.clone()).unwrap().id, a, "the same capture, the same id");
    let mut other = upload.clone();
    other.near += 0.5;
    assert_ne!(client.create_scene(other).unwrap().id, a, "another depth range, another id");
    let mut fewer = upload;
    fewer.sources.pop();
    assert_ne!(client.create_scene(fewer).unwrap().id, a, "other views, another id");
    assert_eq!(client.limits().unwrap().max_scene_views, common::MAX_VIEWS);
}
