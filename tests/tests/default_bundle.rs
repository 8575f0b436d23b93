//! Regression: the real binary with no `--bundle` serves the committed default bundle, and its
//! render of the committed example (a photo-like procedural tabletop scene from a validation
//! seed), with the server's default sampling, scores within `tolerance_db` of `psnr_guided` in
//! examples/tabletop/regression.json (the exporter's pytest twin holds full sampling to
//! `psnr_full`).

use std::time::Duration;

use scnerf_e2e::{http_request, multipart, post_render_png, psnr, repo_root, server_binary, ServerProcess};
use serde_json::Value;

#[test]
fn default_bundle_renders_the_example_above_its_floor() {
    let example = repo_root().join("examples/tabletop");
    let read = |name: &str| std::fs::read(example.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    let expected: Value = serde_json::from_slice(&read("regression.json")).unwrap();
    let (request, s0, s1, s2) =
        (read("request.json"), read("source_0.png"), read("source_1.png"), read("source_2.png"));
    let (ctype, body) = multipart(&[
        ("request", None, "application/json", &request),
        ("source_0", Some("source_0.png"), "image/png", &s0),
        ("source_1", Some("source_1.png"), "image/png", &s1),
        ("source_2", Some("source_2.png"), "image/png", &s2),
    ]);

    let mut server = ServerProcess::start(&server_binary(), &[]);
    server.wait_ready(Duration::from_secs(600));
    let model =
        http_request(server.addr, "GET", "/v1/model", &[], &[], Duration::from_secs(10)).expect("GET /v1/model");
    let model: Value = serde_json::from_slice(&model.body).unwrap();
    assert_eq!(model["model_id"], expected["model_id"], "default bundle changed: re-measure the floor");

    let resp = post_render_png(server.addr, &ctype, &body, Duration::from_secs(1800));
    let rendered = image::load_from_memory(&resp.body).expect("PNG").into_rgb8();
    let truth = image::load_from_memory(&read("target_truth.png")).expect("truth PNG").into_rgb8();
    assert_eq!(rendered.dimensions(), truth.dimensions());
    let to_f32 = |img: &image::RgbImage| img.as_raw().iter().map(|&b| f32::from(b) / 255.0).collect::<Vec<f32>>();
    let score = psnr(&to_f32(&rendered), &to_f32(&truth));
    let (measured, tolerance) = (expected["psnr_guided"].as_f64().unwrap(), expected["tolerance_db"].as_f64().unwrap());
    eprintln!("default bundle on the example: PSNR {score:.3} dB (measured {measured}, tolerance {tolerance})");
    assert!((score - measured).abs() <= tolerance, "PSNR {score:.3} dB, {measured} dB measured");
}
