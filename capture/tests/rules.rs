//! The rules this crate shares with the Python side, against tests/fixtures/rules/ (written by
//! scripts/make-rule-fixtures.py from the Python code; exporter/tests/data/test_rule_fixtures.py
//! holds the Python side to the same files): which files are images and which image set a capture
//! is read from (image_files.json), the API's pose conventions, look_at and resized cameras
//! (cameras.json), the depth range from the poses (depth_range.json) and source ranking
//! (source_ranking.json). A rule changed on one side alone fails that side's tests.

use std::path::Path;

use nalgebra::{Matrix4, Point3, Vector3};
use scnerf_capture::camera::{self, Axes, Camera, Intrinsics, PoseKind, Viewpoint};
use scnerf_capture::depth_range;
use scnerf_capture::files::MemoryFiles;
use scnerf_capture::image_sets::{self, Pick};
use scnerf_capture::readers::{has_image_extension, list_images, Format};
use serde_json::{json, Value};

fn fixture(name: &str) -> Value {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/rules").join(name);
    serde_json::from_str(&std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))).unwrap()
}

fn png(width: u32, height: u32) -> Vec<u8> {
    let mut out = Vec::new();
    image::DynamicImage::ImageRgb8(image::RgbImage::new(width, height))
        .write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
        .unwrap();
    out
}

fn file_names(fs: &MemoryFiles, dir: &str) -> Vec<String> {
    let listed = list_images(fs, Path::new(dir)).unwrap();
    listed.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect()
}

#[test]
fn which_files_are_images() {
    let f = fixture("image_files.json");
    let mut fs = MemoryFiles::new();
    let mut images = Vec::new();
    for case in f["names"].as_array().unwrap() {
        let name = case["name"].as_str().unwrap();
        assert_eq!(has_image_extension(Path::new(name)), case["image_extension"], "{name}");
        assert!(fs.insert(&format!("names/{name}"), vec![1]));
        if case["image"] == true {
            images.push(name.to_string());
        }
    }
    images.sort();
    assert_eq!(file_names(&fs, "names"), images);
}

#[test]
fn image_sets_and_the_set_a_pick_takes() {
    let f = fixture("image_files.json");
    for case in f["captures"].as_array().unwrap() {
        let what = case["name"].as_str().unwrap();
        let mut fs = MemoryFiles::new();
        for (rel, size) in case["files"].as_object().unwrap() {
            let bytes = match size.as_array() {
                Some(wh) => png(wh[0].as_u64().unwrap() as u32, wh[1].as_u64().unwrap() as u32),
                None => b"x".to_vec(),
            };
            assert!(fs.insert(&format!("cap/{rel}"), bytes));
        }
        for (folder, images) in case["images"].as_object().unwrap() {
            assert_eq!(json!(file_names(&fs, &format!("cap/{folder}"))), *images, "{what}: {folder}");
        }
        let sets = image_sets::image_sets(&fs, Path::new("cap"), Format::Llff).unwrap();
        let described: Vec<Value> = sets
            .iter()
            .map(|s| {
                let folder = s.folder.file_name().unwrap().to_string_lossy();
                json!({"folder": folder, "factor": s.factor, "width": s.width, "height": s.height})
            })
            .collect();
        assert_eq!(json!(described), case["sets"], "{what}");
        for want in case["picks"].as_array().unwrap() {
            let rule = match (want["fit"].as_u64(), want["downscale"].as_u64()) {
                (Some(max_pixels), None) => Pick::Fit { max_pixels },
                (None, Some(factor)) => Pick::Downscale(factor as u32),
                _ => panic!("{what}: a pick is a fit or a downscale: {want}"),
            };
            let mut got = want.clone();
            let answer = got.as_object_mut().unwrap();
            answer.retain(|k, _| k == "fit" || k == "downscale");
            match image_sets::pick(&sets, rule) {
                Err(_) => drop(answer.insert("error".into(), json!(true))),
                Ok(None) => drop(answer.insert("set".into(), Value::Null)),
                Ok(Some(picked)) => {
                    answer.insert("set".into(), json!(picked.set.folder.file_name().unwrap().to_string_lossy()));
                    answer.insert("fits".into(), json!(picked.fits));
                }
            }
            assert_eq!(&got, want, "{what}");
        }
    }
}

fn matrix(v: &Value) -> Matrix4<f64> {
    let rows: Vec<Vec<f64>> = serde_json::from_value(v.clone()).unwrap();
    Matrix4::from_fn(|r, c| rows[r][c])
}

fn point(v: &Value) -> [f64; 3] {
    serde_json::from_value(v.clone()).unwrap()
}

#[test]
fn every_pose_convention_gives_the_canonical_pose() {
    let f = fixture("cameras.json");
    for case in f["poses"].as_array().unwrap() {
        let (m, want) = (matrix(&case["matrix"]), matrix(&case["w2c"]));
        let kind: PoseKind = serde_json::from_value(case["kind"].clone()).unwrap();
        let axes: Axes = serde_json::from_value(case["axes"].clone()).unwrap();
        // The server's decoding of a request, and the client's of a camera file.
        let server = camera::canonical_w2c(&m, kind, axes).unwrap();
        assert!((server - want).amax() < 1e-12, "{kind:?} {axes:?}: {server} vs {want}");
        let client = camera::w2c_from_api(&m, kind, axes).unwrap().to_homogeneous();
        assert!((client - want).amax() < 1e-12, "{kind:?} {axes:?}: {client} vs {want}");
    }
}

#[test]
fn look_at_is_the_fixtures() {
    let f = fixture("cameras.json");
    for case in f["look_at"].as_array().unwrap() {
        let (eye, target, up) = (point(&case["eye"]), point(&case["target"]), point(&case["up"]));
        let w2c = camera::look_at(&Point3::from(eye), &Point3::from(target), &Vector3::from(up)).to_homogeneous();
        assert!((w2c - matrix(&case["w2c"])).amax() < 1e-12, "{case}: {w2c}");
    }
}

#[test]
fn resized_cameras_are_the_fixtures() {
    let f = fixture("cameras.json");
    for case in f["resized"].as_array().unwrap() {
        let (from, to) = (&case["camera"], &case["resized"]);
        let size = |c: &Value| (c["width"].as_u64().unwrap() as u32, c["height"].as_u64().unwrap() as u32);
        let intrinsics = |c: &Value| -> Intrinsics {
            serde_json::from_value(json!({"fx": c["fx"], "fy": c["fy"], "cx": c["cx"], "cy": c["cy"]})).unwrap()
        };
        let (width, height) = size(from);
        let camera = Camera { width, height, intrinsics: intrinsics(from), w2c: camera::Pose::identity() };
        let (w, h) = size(to);
        let got = camera.resized(w, h);
        let want = intrinsics(to);
        assert_eq!((got.width, got.height), (w, h));
        let diff = [
            got.intrinsics.fx - want.fx,
            got.intrinsics.fy - want.fy,
            got.intrinsics.cx - want.cx,
            got.intrinsics.cy - want.cy,
        ];
        assert!(diff.iter().all(|d| d.abs() < 1e-9), "{case}: {:?}", got.intrinsics);
    }
}

/// A camera of the fixture's world-to-camera matrix (the intrinsics play no part in the rules).
fn camera_of(w2c: &Value) -> Camera {
    let pose = camera::pose_from_matrix(&matrix(w2c)).unwrap_or_else(|| panic!("not a pose: {w2c}"));
    Camera { width: 8, height: 6, intrinsics: Intrinsics { fx: 10.0, fy: 10.0, cx: 4.0, cy: 3.0 }, w2c: pose }
}

fn close(got: f64, want: &Value) -> bool {
    let want = want.as_f64().unwrap();
    (got - want).abs() <= 1e-9 * want.abs().max(1.0)
}

#[test]
fn the_depth_range_of_each_rig_is_the_fixtures() {
    let f = fixture("depth_range.json");
    for rig in f["rigs"].as_array().unwrap() {
        let what = rig["name"].as_str().unwrap();
        let cameras: Vec<Camera> = rig["w2c"].as_array().unwrap().iter().map(camera_of).collect();
        let meet = camera::convergence(&cameras);
        assert_eq!(meet.is_some(), !rig["convergence"].is_null(), "{what}: {meet:?}");
        if let Some(meet) = meet {
            let want = &rig["convergence"];
            assert!((meet.point - Point3::from(point(&want["point"]))).norm() < 1e-9, "{what}: {meet:?}");
            assert!(close(meet.spread, &want["spread"]), "{what}: {meet:?}");
        }
        let refs: Vec<&Camera> = cameras.iter().collect();
        let range = depth_range::from_poses(&refs);
        match (range, rig["range"].as_array()) {
            (None, None) => {}
            (Some((near, far)), Some(want)) => {
                assert!(close(near, &want[0]) && close(far, &want[1]), "{what}: {near}..{far} vs {want:?}")
            }
            (got, _) => panic!("{what}: {got:?} vs {}", rig["range"]),
        }
    }
}

#[test]
fn source_ranking_is_the_fixtures() {
    let f = fixture("source_ranking.json");
    for case in f["cases"].as_array().unwrap() {
        let what = case["name"].as_str().unwrap();
        let want: Vec<usize> = serde_json::from_value(case["ranked"].clone()).unwrap();
        let candidates = case["candidates"].as_array().unwrap();
        // The server ranks its requests' matrices, the client's evaluation the cameras it read.
        let of_matrices: Vec<Viewpoint> = candidates.iter().map(|m| Viewpoint::of_w2c(&matrix(m))).collect();
        let target = Viewpoint::of_w2c(&matrix(&case["target"]));
        assert_eq!(camera::rank_sources(&target, &of_matrices), want, "{what}");
        let of_cameras: Vec<Viewpoint> = candidates.iter().map(|m| camera_of(m).viewpoint()).collect();
        let target = camera_of(&case["target"]).viewpoint();
        assert_eq!(camera::rank_sources(&target, &of_cameras), want, "{what}");
    }
}
