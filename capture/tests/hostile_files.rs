//! Capture files made to hurt the reader (what `POST /v1/captures` may receive): each is refused
//! with a message naming the file, never a panic, and read without materialising what it
//! declares.

use std::path::{Path, PathBuf};

use scnerf_capture::files::{Files, MemoryFiles};
use scnerf_capture::readers::{self, ReadOptions, MAX_JSON_VALUES};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/datasets")
}

/// Every file of a fixture folder, in memory, with `replace` swapped in (path, bytes).
fn fixture_with(folder: &str, replace: &[(&str, Vec<u8>)]) -> MemoryFiles {
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
    let root = fixtures().join(folder);
    let mut files = MemoryFiles::new();
    walk(&root, &root, &mut files);
    for (path, bytes) in replace {
        files.remove(Path::new(path));
        assert!(files.insert(path, bytes.clone()));
    }
    files
}

fn error(files: &MemoryFiles, opts: ReadOptions) -> String {
    readers::load_from(files, Path::new(""), None, opts).unwrap_err().to_string()
}

#[test]
fn duplicate_keys_in_a_transforms_file_are_refused() {
    let text = std::fs::read_to_string(fixtures().join("nerfstudio/transforms.json")).unwrap();
    // Top level: a second fl_x after the first would have won.
    let doubled = text.replacen("\"fl_x\"", "\"fl_x\": 1.0, \"fl_x\"", 1);
    let err = error(&fixture_with("nerfstudio", &[("transforms.json", doubled.into_bytes())]), ReadOptions::default());
    assert!(err.starts_with("transforms.json: invalid JSON: key \"fl_x\" appears twice"), "{err}");
    // Inside a frame.
    let doubled = text.replacen("\"file_path\"", "\"file_path\": \"x.png\", \"file_path\"", 1);
    let err = error(&fixture_with("nerfstudio", &[("transforms.json", doubled.into_bytes())]), ReadOptions::default());
    assert!(err.contains("key \"file_path\" appears twice"), "{err}");
    // The same key in two objects is no duplicate: the fixture itself reads.
    assert!(readers::load_from(&fixture_with("nerfstudio", &[]), Path::new(""), None, ReadOptions::default()).is_ok());
}

#[test]
fn a_json_file_of_more_values_than_a_capture_has_is_refused_before_it_is_built() {
    let mut text = String::from("{\"camera_angle_x\": 0.7, \"frames\": [], \"junk\": [0");
    text.push_str(&",0".repeat(MAX_JSON_VALUES));
    text.push_str("]}");
    let err = error(&fixture_with("blender", &[("transforms_train.json", text.into_bytes())]), ReadOptions::default());
    assert!(err.contains(&format!("transforms_train.json: invalid JSON: more than {MAX_JSON_VALUES} values")), "{err}");
}

#[test]
fn an_npy_header_declaring_more_rows_than_the_file_holds_is_refused() {
    let npy = |shape: &str, data: usize| {
        let header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}");
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
        bytes.extend_from_slice(header.as_bytes());
        bytes.extend(std::iter::repeat_n(0u8, data));
        bytes
    };
    // 1085102592571150096 x 17 wraps u64 to 16 elements: a "capacity overflow" panic before.
    for shape in ["(1085102592571150096, 17)", "(18446744073709551615, 17)", "(4, 17)"] {
        let files = fixture_with("llff", &[("poses_bounds.npy", npy(shape, 16 * 8))]);
        let err = error(&files, ReadOptions::default());
        assert!(err.starts_with("poses_bounds.npy: the header declares"), "{shape}: {err}");
    }
    let files = fixture_with("llff", &[("poses_bounds.npy", npy("(3, 17, 1)", 51 * 8))]);
    assert!(error(&files, ReadOptions::default()).contains("expected an N x 17 array"));
}

#[test]
fn untracked_colmap_points_seen_from_every_image_are_bounded() {
    // 2^16 points without a track, each seen from all images: 4 x 2^16 depths are fine,
    // 264 x 2^16 (more than MAX_DEPTHS, 2^22) are not.
    let points: String = (0..1 << 16).map(|i| format!("{i} 0 0 1 0 0 0 0\n")).collect();
    let images = std::fs::read_to_string(fixtures().join("colmap/sparse/0/images.txt")).unwrap();
    let mut many = images.clone();
    for id in 100..360 {
        many.push_str(&format!("{id} 1 0 0 0 0 0 0 1 other{id}.png\n\n"));
    }
    let replace = |images: &str| {
        fixture_with(
            "colmap",
            &[("sparse/0/points3D.txt", points.clone().into_bytes()), ("sparse/0/images.txt", images.into())],
        )
    };
    let files = replace(&images);
    assert!(readers::load_from(&files, Path::new(""), None, ReadOptions::default()).is_ok());
    let files = replace(&many);
    let err = error(&files, ReadOptions::default());
    assert!(err.starts_with("sparse/0/points3D.txt: 65536 points (65536 without a track"), "{err}");
    assert!(err.contains("pass --near and --far"), "{err}");
    // With the depth range given, the points are not read at all.
    let given = ReadOptions { near: Some(0.5), far: Some(9.0), ..Default::default() };
    assert!(readers::load_from(&files, Path::new(""), None, given).is_ok());
}

#[test]
fn malformed_colmap_lines_are_quoted_short() {
    let line = format!("1 PINHOLE 8 6 {}\n", "9 ".repeat(100_000));
    let files = fixture_with("colmap", &[("sparse/0/cameras.txt", line.into_bytes())]);
    let err = error(&files, ReadOptions::default());
    assert!(err.contains("line 1: malformed camera line"), "{err}");
    assert!(err.len() < 300, "{} bytes", err.len());
}

#[test]
fn dtu_files_with_odd_numbers_and_letters_do_not_panic() {
    let cam = std::fs::read_to_string(fixtures().join("dtu/Cameras/train/00000000_cam.txt")).unwrap();
    // A letter whose lowercase is longer in UTF-8 ('İ': 2 bytes, 'i̇': 3) ahead of a section
    // moved the indices found in the lowercased copy into the 'é' of the original: a panic.
    let odd = cam.replacen("extrinsic", "İextrinsicé", 1);
    let files = fixture_with("dtu", &[("Cameras/train/00000000_cam.txt", odd.into_bytes())]);
    let err = error(&files, ReadOptions::default());
    assert!(err.contains("00000000_cam.txt: malformed number in cam.txt: \"é"), "{err}");
    // The largest view number: its image number (number + 1) must not overflow.
    let files = fixture_with("dtu", &[("Cameras/train/4294967295_cam.txt", cam.into_bytes())]);
    assert!(readers::load_from(&files, Path::new(""), None, ReadOptions::default()).is_ok());
}

#[test]
fn folders_in_memory_are_told_apart_from_their_neighbours() {
    let mut files = MemoryFiles::new();
    for path in ["a", "a b/x", "a.b/y", "a/b/c", "ab", "b/z"] {
        assert!(files.insert(path, vec![0]));
    }
    let (dir, not) = (|p: &str| files.is_dir(Path::new(p)), |p: &str| !files.is_dir(Path::new(p)));
    assert!(dir("a") && dir("a/b") && dir("a b") && dir("a.b") && dir("b") && dir(""));
    assert!(not("a/b/c") && not("ab") && not("c") && not("a/c"));
    let mut listed = files.list(Path::new("a")).unwrap();
    listed.sort();
    assert_eq!(listed, [Path::new("a/b")]);
}

/// An infinite depth, or one whose far end overflows, is refused naming the camera file that
/// holds it (not, later, the capture's folder).
#[test]
fn dtu_depths_that_are_not_finite_name_their_camera_file() {
    let cam = std::fs::read_to_string(fixtures().join("dtu/Cameras/train/00000000_cam.txt")).unwrap();
    for depths in ["inf 2.5", "425.0 inf", "425.0 1e308", "NaN 2.5"] {
        let bad = cam.replace("425.0 2.5", depths);
        assert_ne!(bad, cam);
        let files = fixture_with("dtu", &[("Cameras/train/00000000_cam.txt", bad.into_bytes())]);
        let err = readers::load_from(&files, Path::new(""), None, ReadOptions::default()).unwrap_err();
        assert_eq!(err.path(), Some(Path::new("Cameras/train/00000000_cam.txt")), "{depths}: {err}");
    }
}
