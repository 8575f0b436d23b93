//! Every reader against the fixtures of tests/fixtures/datasets/, whose expected.json the Python
//! loader wrote (scripts/make-dataset-fixtures.py; exporter/tests/data/test_dataset_fixtures.py checks
//! the Python side), so Rust and Python read the same files into the same cameras.

use std::path::{Path, PathBuf};

use scnerf_capture::files::{Disk, MemoryFiles};
use scnerf_capture::image_sets::{self, ImageSet, Pick};
use scnerf_capture::readers::{self, Capture, Format, ReadOptions};
use serde_json::Value;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/datasets")
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1e-3)
}

/// The capture equals expected.json: names and order, image files, sizes, K, w2c, near/far,
/// background.
fn assert_matches(capture: &Capture, folder: &Path, expected_folder: &str) {
    let expected: Value =
        serde_json::from_str(&std::fs::read_to_string(fixtures().join(expected_folder).join("expected.json")).unwrap())
            .unwrap();
    assert_eq!(capture.format.name(), expected["format"]);
    assert!(close(capture.near, expected["near"].as_f64().unwrap()), "near {}", capture.near);
    assert!(close(capture.far, expected["far"].as_f64().unwrap()), "far {}", capture.far);
    let bg: Vec<f64> = serde_json::from_value(expected["background"].clone()).unwrap();
    assert_eq!(capture.background.to_vec(), bg);
    let views = expected["views"].as_array().unwrap();
    let names: Vec<&str> = capture.views.iter().map(|v| v.name.as_str()).collect();
    let want: Vec<&str> = views.iter().map(|v| v["name"].as_str().unwrap()).collect();
    assert_eq!(names, want);
    for (view, want) in capture.views.iter().zip(views) {
        let at = &view.name;
        assert_eq!(
            view.image_path.canonicalize().unwrap(),
            folder.join(want["image"].as_str().unwrap()).canonicalize().unwrap()
        );
        let cam = &view.camera;
        assert_eq!(
            (u64::from(cam.width), u64::from(cam.height)),
            (want["width"].as_u64().unwrap(), want["height"].as_u64().unwrap())
        );
        let k: [[f64; 3]; 3] = serde_json::from_value(want["K"].clone()).unwrap();
        let k_rust = cam.k();
        for r in 0..3 {
            for c in 0..3 {
                assert!(close(k_rust[(r, c)], k[r][c]), "{at}: K[{r}][{c}] {} vs {}", k_rust[(r, c)], k[r][c]);
            }
        }
        let w2c: [[f64; 4]; 4] = serde_json::from_value(want["w2c"].clone()).unwrap();
        let m = cam.w2c.to_homogeneous();
        for r in 0..4 {
            for c in 0..4 {
                assert!(close(m[(r, c)], w2c[r][c]), "{at}: w2c[{r}][{c}] {} vs {}", m[(r, c)], w2c[r][c]);
            }
        }
    }
}

fn load(folder: &str, format: Option<Format>) -> Capture {
    readers::load(&fixtures().join(folder), format, ReadOptions::default()).unwrap()
}

#[test]
fn blender_matches_python() {
    let c = load("blender", Some(Format::Blender));
    assert_matches(&c, &fixtures().join("blender"), "blender");
    // two frames of transforms_train.json have no image: one warning that counts them
    assert_eq!(c.warnings.len(), 1, "{:?}", c.warnings);
    assert!(c.warnings[0].contains("2 of 7 frames have no image file; skipped"), "{}", c.warnings[0]);
}

#[test]
fn nerfstudio_matches_python() {
    let c = load("nerfstudio", Some(Format::Nerfstudio));
    assert_matches(&c, &fixtures().join("nerfstudio"), "nerfstudio");
    assert!(c.warnings[0].contains("1 of 5 frames"), "{:?}", c.warnings);
}

#[test]
fn llff_matches_python() {
    let c = load("llff", Some(Format::Llff));
    assert_matches(&c, &fixtures().join("llff"), "llff");
}

#[test]
fn colmap_text_matches_python() {
    let c = load("colmap", Some(Format::Colmap));
    assert_matches(&c, &fixtures().join("colmap"), "colmap");
    assert!(c.warnings[0].contains("1 of 5 images are missing"), "{:?}", c.warnings);
}

#[test]
fn colmap_binary_gives_the_same_cameras_as_text() {
    let c = load("colmap_binary", Some(Format::Colmap));
    assert_matches(&c, &fixtures().join("colmap_binary"), "colmap");
}

#[test]
fn dtu_matches_python() {
    let c = load("dtu", Some(Format::Dtu));
    assert_matches(&c, &fixtures().join("dtu"), "dtu");
    assert!(c.warnings[0].contains("1 of 5 cameras have no image"), "{:?}", c.warnings);
}

#[test]
fn auto_detects_every_format() {
    for (folder, format) in [
        ("blender", Format::Blender),
        ("nerfstudio", Format::Nerfstudio),
        ("llff", Format::Llff),
        ("colmap", Format::Colmap),
        ("colmap_binary", Format::Colmap),
        ("dtu", Format::Dtu),
    ] {
        assert_eq!(readers::detect(&Disk, &fixtures().join(folder)).unwrap(), format, "{folder}");
        assert_eq!(load(folder, None).format, format);
    }
    let file = fixtures().join("nerfstudio/transforms.json");
    assert_eq!(readers::detect(&Disk, &file).unwrap(), Format::Nerfstudio);
}

#[test]
fn near_far_flags_override_the_dataset() {
    let opts = ReadOptions { near: Some(0.25), far: None, ..Default::default() };
    let c = readers::load(&fixtures().join("blender"), None, opts).unwrap();
    assert_eq!((c.near, c.far), (0.25, 6.0));
    let bad = ReadOptions { near: Some(7.0), ..Default::default() };
    let err = readers::load(&fixtures().join("blender"), None, bad).unwrap_err().to_string();
    assert!(err.contains("invalid near/far 7/6"), "{err}");

    // each bound on its own, as the Python loaders take them: a file with far only and --near
    let dir = copy_fixture("nerfstudio");
    let file = dir.path().join("transforms.json");
    let mut data: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    data.as_object_mut().unwrap().remove("near_far");
    data["far"] = 9.5.into();
    std::fs::write(&file, data.to_string()).unwrap();
    let c = readers::load(dir.path(), None, ReadOptions { near: Some(0.1), ..Default::default() }).unwrap();
    assert_eq!((c.near, c.far), (0.1, 9.5));
}

/// A copy of a fixture folder to break.
fn copy_fixture(folder: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    copy_dir(&fixtures().join(folder), dir.path());
    dir
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.path().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

fn error_of(dir: &Path) -> String {
    readers::load(dir, None, ReadOptions::default()).unwrap_err().to_string()
}

#[test]
fn distorted_colmap_cameras_are_undistorted_unless_ignored() {
    let dir = copy_fixture("colmap");
    let cameras = dir.path().join("sparse/0/cameras.txt");
    let text = std::fs::read_to_string(&cameras)
        .unwrap()
        .replace("SIMPLE_RADIAL 8 6 9.5 4.0 3.0 0.0", "SIMPLE_RADIAL 8 6 9.5 4.0 3.0 0.02");
    std::fs::write(&cameras, text).unwrap();
    let c = readers::load(dir.path(), None, ReadOptions::default()).unwrap();
    let undistorted: Vec<_> = c.views.iter().filter_map(|v| v.lens).collect();
    assert!(!undistorted.is_empty() && undistorted.iter().all(|l| l.distortion.k[0] == 0.02), "{undistorted:?}");
    let opts = ReadOptions { ignore_distortion: true, ..Default::default() };
    let c = readers::load(dir.path(), None, opts).unwrap();
    assert!(c.views.iter().all(|v| v.lens.is_none()));
    assert!(c.warnings.iter().any(|w| w.contains("lens distortion ignored")), "{:?}", c.warnings);

    // a fisheye model without distortion is a pinhole camera
    let fisheye = std::fs::read_to_string(&cameras)
        .unwrap()
        .replace("SIMPLE_RADIAL 8 6 9.5 4.0 3.0 0.02", "OPENCV_FISHEYE 8 6 9 9 4 3 0 0 0 0");
    std::fs::write(&cameras, fisheye).unwrap();
    let c = readers::load(dir.path(), None, ReadOptions::default()).unwrap();
    assert!(c.views.iter().all(|v| v.lens.is_none()));
}

#[test]
fn distorted_nerfstudio_frames_are_undistorted() {
    let dir = copy_fixture("nerfstudio");
    let file = dir.path().join("transforms.json");
    let text = std::fs::read_to_string(&file).unwrap().replacen("\"k1\": 0.0", "\"k1\": -0.1", 1);
    std::fs::write(&file, text).unwrap();
    let c = readers::load(dir.path(), None, ReadOptions::default()).unwrap();
    assert!(c.views.iter().any(|v| v.lens.is_some_and(|l| l.distortion.k[0] == -0.1)));
}

#[test]
fn fewer_than_three_images_is_an_error() {
    let dir = copy_fixture("blender");
    for i in 0..3 {
        std::fs::remove_file(dir.path().join(format!("train/r_{i}.png"))).unwrap();
    }
    let err = error_of(dir.path());
    assert!(err.contains("only 2 view(s) have an image; a capture needs at least 3"), "{err}");
}

#[test]
fn malformed_files_name_the_file_and_field() {
    let dir = copy_fixture("blender");
    let file = dir.path().join("transforms_val.json");
    std::fs::write(
        &file,
        r#"{"camera_angle_x": 0.7, "frames": [{"file_path": "./val/r_0.png", "transform_matrix": [[1, 0]]}]}"#,
    )
    .unwrap();
    let err = error_of(dir.path());
    assert!(err.contains("transforms_val.json: frames[0].transform_matrix must be a finite 4x4"), "{err}");

    let dir = copy_fixture("dtu");
    std::fs::write(dir.path().join("Cameras/train/00000001_cam.txt"), "extrinsic\n1 0 0\nintrinsic\n").unwrap();
    let err = error_of(dir.path());
    assert!(err.contains("00000001_cam.txt: extrinsic must have 16 numbers, found 3"), "{err}");

    let dir = copy_fixture("colmap_binary");
    let images = dir.path().join("sparse/0/images.bin");
    let bytes = std::fs::read(&images).unwrap();
    std::fs::write(&images, &bytes[..bytes.len() / 2]).unwrap();
    let err = error_of(dir.path());
    assert!(err.contains("images.bin: truncated binary model"), "{err}");

    let err = error_of(&fixtures().join("no-such-folder"));
    assert!(err.contains("no such dataset folder"), "{err}");
}

/// Every file under `dir`, keyed by its path relative to `dir` (what a browser sends as the
/// filenames of a dropped folder).
fn in_memory(dir: &Path) -> MemoryFiles {
    fn walk(root: &Path, dir: &Path, files: &mut MemoryFiles) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                walk(root, &path, files);
            } else {
                let rel = path.strip_prefix(root).unwrap().to_str().unwrap().to_string();
                assert!(files.insert(&rel, std::fs::read(&path).unwrap()));
            }
        }
    }
    let mut files = MemoryFiles::new();
    walk(dir, dir, &mut files);
    files
}

/// The server reads uploaded captures from memory: every fixture gives the same capture as
/// from disk, with image paths relative to the capture's root.
#[test]
fn captures_in_memory_read_as_on_disk() {
    for folder in ["blender", "nerfstudio", "llff", "colmap", "colmap_binary", "dtu"] {
        let dir = fixtures().join(folder);
        let files = in_memory(&dir);
        let from_memory = readers::load_from(&files, Path::new(""), None, ReadOptions::default()).unwrap();
        let from_disk = load(folder, None);
        assert_eq!(from_memory.format, from_disk.format, "{folder}");
        assert_eq!((from_memory.near, from_memory.far), (from_disk.near, from_disk.far), "{folder}");
        assert_eq!(from_memory.background, from_disk.background, "{folder}");
        assert_eq!(from_memory.warnings.len(), from_disk.warnings.len(), "{folder}");
        assert_eq!(from_memory.views.len(), from_disk.views.len(), "{folder}");
        for (m, d) in from_memory.views.iter().zip(&from_disk.views) {
            assert_eq!((&m.name, &m.camera), (&d.name, &d.camera), "{folder}");
            assert_eq!(dir.join(&m.image_path).canonicalize().unwrap(), d.image_path.canonicalize().unwrap());
            assert!(files.get(&m.image_path).is_some(), "{folder}: {}", m.image_path.display());
        }
    }
}

#[test]
fn captures_in_memory_name_the_missing_file() {
    let mut files = in_memory(&fixtures().join("llff"));
    let err = readers::load_from(&MemoryFiles::new(), Path::new(""), None, ReadOptions::default()).unwrap_err();
    assert!(err.to_string().contains("no such dataset folder"), "{err}");
    // images without poses: nothing tells the format
    let mut images_only = MemoryFiles::new();
    assert!(images_only.insert("images/a.png", vec![0]));
    let err = readers::load_from(&images_only, Path::new(""), None, ReadOptions::default()).unwrap_err();
    assert!(err.to_string().contains("cannot tell the dataset format"), "{err}");
    // LLFF with one image more than its poses
    assert!(files.insert("images/zzz_extra.png", std::fs::read(fixtures().join("blender/train/r_0.png")).unwrap()));
    let err = readers::load_from(&files, Path::new(""), None, ReadOptions::default()).unwrap_err();
    assert!(err.to_string().starts_with("poses_bounds.npy: "), "{err}");
}

/// A copy of a fixture as LLFF, nerfstudio and COLMAP captures are distributed: its images also
/// in `images_2/`, at half size (rounded down, as LLFF's and nerfstudio's scripts write them).
fn with_half_size_set(folder: &str) -> tempfile::TempDir {
    let dir = copy_fixture(folder);
    let half = dir.path().join("images_2");
    std::fs::create_dir_all(&half).unwrap();
    for entry in std::fs::read_dir(dir.path().join("images")).unwrap() {
        let path = entry.unwrap().path();
        let image = image::open(&path).unwrap();
        let (w, h) = (image.width() / 2, image.height() / 2);
        image
            .resize_exact(w, h, image::imageops::FilterType::Triangle)
            .save(half.join(path.file_name().unwrap()))
            .unwrap();
    }
    dir
}

fn read_set(dir: &Path, downscale: Option<u32>) -> Capture {
    readers::load(dir, None, ReadOptions { downscale, ..Default::default() }).unwrap()
}

/// `images_N` gives the same views as `images/`, each camera scaled to its images.
#[test]
fn downscaled_sets_give_the_same_views_at_their_size() {
    for folder in ["nerfstudio", "colmap", "llff"] {
        let dir = with_half_size_set(folder);
        let (full, half) = (read_set(dir.path(), None), read_set(dir.path(), Some(2)));
        assert_eq!(full.views.len(), half.views.len(), "{folder}");
        assert_eq!((full.near, full.far), (half.near, half.far), "{folder}");
        for (f, h) in full.views.iter().zip(&half.views) {
            assert_eq!(f.name, h.name, "{folder}");
            assert!(h.image_path.starts_with(dir.path().join("images_2")), "{folder}: {}", h.image_path.display());
            assert_eq!((h.camera.width, h.camera.height), (f.camera.width / 2, f.camera.height / 2), "{folder}");
            assert_eq!(h.camera.w2c, f.camera.w2c, "{folder}");
            let (fi, hi) = (f.camera.intrinsics, h.camera.intrinsics);
            assert!((hi.fx - fi.fx / 2.0).abs() < 1e-12 && (hi.fy - fi.fy / 2.0).abs() < 1e-12, "{folder}: {hi:?}");
            if folder == "llff" {
                // LLFF: hwf describes the full-size images; the principal point is the centre
                assert_eq!((hi.cx, hi.cy), (f64::from(h.camera.width) / 2.0, f64::from(h.camera.height) / 2.0));
            } else {
                assert_eq!(h.camera, f.camera.resized(h.camera.width, h.camera.height), "{folder}");
            }
        }
    }
}

/// LLFF's poses_bounds.npy describes the full-size images: with `images/` absent (only the
/// downscaled sets were kept), `images_2` is read with f scaled from hwf, exactly as with it.
#[test]
fn llff_downscaled_set_reads_without_the_full_size_images() {
    let dir = with_half_size_set("llff");
    let with_full = read_set(dir.path(), Some(2));
    std::fs::remove_dir_all(dir.path().join("images")).unwrap();
    let (capture, picked) =
        image_sets::load_picked(&Disk, dir.path(), None, ReadOptions::default(), Pick::Fit { max_pixels: 1 << 20 })
            .unwrap();
    let picked = picked.unwrap();
    assert_eq!((picked.set.factor, picked.fits, picked.sets.len()), (2, true, 1));
    for (a, b) in capture.views.iter().zip(&with_full.views) {
        assert_eq!(a.camera, b.camera);
    }
    // the fixture's hwf is 24 x 32 with focal 28: images of 4x3 get f = 28 * 4 / 32
    assert_eq!(capture.views[0].camera.intrinsics.fx, 3.5);
}

/// The rule the CLI and the server apply: the largest set within the limit, or `--downscale N`.
#[test]
fn load_picked_takes_the_largest_set_that_fits_or_the_one_asked_for() {
    for folder in ["nerfstudio", "colmap", "llff"] {
        let dir = with_half_size_set(folder);
        let sets = image_sets::image_sets(&Disk, dir.path(), readers::detect(&Disk, dir.path()).unwrap()).unwrap();
        let described: Vec<String> = sets.iter().map(ImageSet::describe).collect();
        assert_eq!(described, ["images (8x6)", "images_2 (4x3)"], "{folder}");
        let load = |rule| image_sets::load_picked(&Disk, dir.path(), None, ReadOptions::default(), rule).unwrap();
        let (capture, picked) = load(Pick::Fit { max_pixels: 48 });
        assert_eq!((picked.unwrap().set.factor, capture.views[0].camera.width), (1, 8), "{folder}");
        let (capture, picked) = load(Pick::Fit { max_pixels: 47 });
        assert_eq!((picked.unwrap().set.factor, capture.views[0].camera.width), (2, 4), "{folder}");
        let (capture, picked) = load(Pick::Fit { max_pixels: 11 });
        let picked = picked.unwrap();
        assert_eq!((picked.set.factor, picked.fits, capture.views[0].camera.width), (2, false, 4), "{folder}");
        let (capture, _) = load(Pick::Downscale(2));
        assert_eq!(capture.views[0].camera.width, 4, "{folder}");
        let err = image_sets::load_picked(&Disk, dir.path(), None, ReadOptions::default(), Pick::Downscale(8))
            .unwrap_err()
            .to_string();
        assert!(err.contains("downscale 8: there is no images_8 folder"), "{folder}: {err}");
        // the server reads what a client sent: the same rule over files in memory
        let files = in_memory(dir.path());
        let (capture, picked) =
            image_sets::load_picked(&files, Path::new(""), None, ReadOptions::default(), Pick::Fit { max_pixels: 47 })
                .unwrap();
        assert_eq!((picked.unwrap().set.factor, capture.views[0].camera.width), (2, 4), "{folder}");
        assert!(capture.views[0].image_path.starts_with("images_2"), "{folder}");
    }
}

/// Blender and DTU keep no sets: they are read as they are, whatever the limit.
#[test]
fn formats_without_sets_are_read_as_they_are() {
    for folder in ["blender", "dtu"] {
        let dir = fixtures().join(folder);
        let (capture, picked) =
            image_sets::load_picked(&Disk, &dir, None, ReadOptions::default(), Pick::Fit { max_pixels: 1 }).unwrap();
        assert_eq!((picked, capture.views.len()), (None, load(folder, None).views.len()), "{folder}");
    }
}
