//! PSNR and SSIM against exporter/scnerf_export/evaluate/metrics.py on the fixed arrays of
//! tests/fixtures/datasets/metrics.json (written by scripts/make-dataset-fixtures.py with
//! metrics.py; exporter/tests/data/test_dataset_fixtures.py checks the Python side).

use scnerf_client::metrics::{psnr, ssim, Image};
use serde_json::Value;

fn image(data: &Value, key: &str) -> Image {
    let shape: Vec<usize> = serde_json::from_value(data["shape"].clone()).unwrap();
    let values: Vec<f64> = serde_json::from_value(data[key].clone()).unwrap();
    Image { height: shape[0], width: shape[1], channels: shape[2], data: values }
}

#[test]
fn psnr_and_ssim_match_metrics_py() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/datasets/metrics.json");
    let data: Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let (pred, gt) = (image(&data, "pred"), image(&data, "gt"));
    let (want_psnr, want_ssim) = (data["psnr"].as_f64().unwrap(), data["ssim"].as_f64().unwrap());
    let got_psnr = psnr(&pred, &gt).unwrap();
    let got_ssim = ssim(&pred, &gt).unwrap();
    assert!((got_psnr - want_psnr).abs() < 1e-9 * want_psnr.abs(), "psnr {got_psnr} vs {want_psnr}");
    assert!((got_ssim - want_ssim).abs() < 1e-9, "ssim {got_ssim} vs {want_ssim}");
    assert!(psnr(&gt, &gt).unwrap().is_infinite());
    assert!((ssim(&gt, &gt).unwrap() - 1.0).abs() < 1e-12);
}

#[test]
fn mismatched_or_tiny_images_are_errors_not_panics() {
    let small = Image { width: 4, height: 4, channels: 3, data: vec![0.5; 48] };
    assert!(ssim(&small, &small).unwrap_err().to_string().contains("at least 11x11"));
    let other = Image { width: 2, height: 8, channels: 3, data: vec![0.5; 48] };
    assert!(psnr(&small, &other).unwrap_err().to_string().contains("differ in size"));
}
