//! The depth range the poses give, on the real scenes of `../shared/data` whose range is known
//! (lego 2 to 6, DTU scan37 2.125 to 4.525, LLFF horns 11.2 to 169, each from its own files): it
//! must contain the known range and be at most twice as wide.

use std::path::{Path, PathBuf};

use scnerf_capture::camera::Camera;
use scnerf_capture::depth_range::from_poses;
use scnerf_capture::files::Disk;
use scnerf_capture::image_sets::{load_picked, Pick};
use scnerf_capture::readers::{self, DepthSource, ReadOptions};

fn shared(scene: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data").join(scene)
}

/// The range the poses give, and the dataset's own.
fn ranges(scene: &str) -> ((f64, f64), (f64, f64)) {
    // the largest image set there is (horns keeps images_8 only)
    let every_set = Pick::Fit { max_pixels: u64::MAX };
    let (capture, _) = load_picked(&Disk, &shared(scene), None, ReadOptions::default(), every_set).unwrap();
    assert_eq!(capture.depth_source, DepthSource::Dataset);
    let cameras: Vec<&Camera> = capture.views.iter().map(|v| &v.camera).collect();
    (from_poses(&cameras).unwrap(), (capture.near, capture.far))
}

fn assert_contains_and_at_most_twice_as_wide(scene: &str, known: (f64, f64)) {
    let ((near, far), from_files) = ranges(scene);
    assert!((from_files.0 - known.0).abs() < 0.01 && (from_files.1 - known.1).abs() < 0.5, "{scene}: {from_files:?}");
    assert!(near <= from_files.0 && far >= from_files.1, "{scene}: {near}..{far} misses {from_files:?}");
    let width = (far - near) / (from_files.1 - from_files.0);
    assert!(width <= 2.0, "{scene}: {near}..{far} is {width:.2} times as wide as {from_files:?}");
    println!("{scene}: from the poses {near:.3}..{far:.3}, {width:.2} x the width of {from_files:?}");
}

#[test]
#[cfg_attr(not(shared_data), ignore = "../shared/data is absent: no scene of known depth range")]
fn lego_an_object_seen_from_around() {
    assert_contains_and_at_most_twice_as_wide("nerf_synthetic_lego", (2.0, 6.0));
}

#[test]
#[cfg_attr(not(shared_data), ignore = "../shared/data is absent: no scene of known depth range")]
fn dtu_scan37_an_object_seen_from_one_side() {
    assert_contains_and_at_most_twice_as_wide("dtu_scan37", (2.125, 4.525));
}

#[test]
#[cfg_attr(not(shared_data), ignore = "../shared/data is absent: no scene of known depth range")]
fn llff_horns_a_forward_facing_capture() {
    assert_contains_and_at_most_twice_as_wide("llff_horns", (11.17, 168.95));
}

/// A nerfstudio file without near/far reads its range from the poses; the flags still win.
#[test]
#[cfg_attr(not(shared_data), ignore = "../shared/data is absent: no scene of known depth range")]
fn a_file_without_a_range_takes_the_poses_and_the_flags_override() {
    let lego = shared("nerf_synthetic_lego");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(lego.join("transforms_train.json")).unwrap()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (w, angle) = (800.0, json["camera_angle_x"].as_f64().unwrap());
    let focal = 0.5 * w / (0.5 * angle).tan();
    let frames: Vec<serde_json::Value> = json["frames"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|f| {
            // the images the shared copy keeps (16 of 100)
            let name = format!("{}.png", f["file_path"].as_str().unwrap().trim_start_matches("./"));
            std::fs::create_dir_all(dir.path().join("train")).unwrap();
            std::fs::copy(lego.join(&name), dir.path().join(&name)).ok()?;
            Some(serde_json::json!({"file_path": name, "transform_matrix": f["transform_matrix"]}))
        })
        .collect();
    assert_eq!(frames.len(), 16);
    let transforms = serde_json::json!({"fl_x": focal, "fl_y": focal, "cx": 400.0, "cy": 400.0, "w": 800, "h": 800,
                                        "frames": frames});
    std::fs::write(dir.path().join("transforms.json"), transforms.to_string()).unwrap();
    let capture = readers::load(dir.path(), None, ReadOptions::default()).unwrap();
    assert_eq!(capture.depth_source, DepthSource::Poses);
    assert!(capture.near <= 2.0 && capture.far >= 6.0 && capture.far - capture.near <= 8.0, "{capture:?}");
    let flags = ReadOptions { near: Some(2.0), far: Some(6.0), ..Default::default() };
    let capture = readers::load(dir.path(), None, flags).unwrap();
    assert_eq!((capture.near, capture.far, capture.depth_source), (2.0, 6.0, DepthSource::Flags));
}
