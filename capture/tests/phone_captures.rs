//! Captures as phone-capture tools leave them: instant-ngp's layout (one transforms.json with
//! top-level fl_x, fl_y, cx, cy, w, h, k1, k2, p1, p2, aabb_scale and no depth range, portrait
//! photos), and COLMAP folders with SIMPLE_RADIAL and OPENCV cameras. They are undistorted on
//! load, get a depth range from their poses or points, and the photos on disk stay as they are.

use std::path::Path;

use nalgebra::{Point3, Vector3};
use scnerf_capture::camera::{look_at, Intrinsics};
use scnerf_capture::readers::{self, DepthSource, ReadOptions};
use scnerf_capture::undistort::{pinhole_for, Distortion, Fit};
use scnerf_capture::upload::image_bytes;
use serde_json::json;

const W: u32 = 54;
const H: u32 = 96;
const FOCAL: f64 = 80.0;
const LENS: Distortion = Distortion { fisheye: false, k: [-0.2, 0.05, 0.0, 0.0, 0.0, 0.0], p: [0.001, -0.0005] };

/// What the scene looks like at undistorted normalised coordinates: smooth, so that bilinear
/// sampling errs by little, and varying fast enough that misplaced pixels show.
fn pattern(x: f64, y: f64) -> [u8; 3] {
    let v = |s: f64| (128.0 + 100.0 * s).round() as u8;
    [v((20.0 * x).sin()), v((20.0 * y).cos()), v((15.0 * (x + y)).sin())]
}

/// The photo a camera with `LENS` takes of [`pattern`] (principal point at the centre).
fn photo() -> image::RgbImage {
    let k = photo_k();
    image::RgbImage::from_fn(W, H, |u, v| {
        let (x, y) = LENS.undistort((f64::from(u) - k.cx) / k.fx, (f64::from(v) - k.cy) / k.fy).unwrap();
        image::Rgb(pattern(x, y))
    })
}

/// The camera of the photos (nerfstudio's cx, cy less half a pixel).
fn photo_k() -> Intrinsics {
    Intrinsics { fx: FOCAL, fy: FOCAL, cx: f64::from(W) / 2.0 - 0.5, cy: f64::from(H) / 2.0 - 0.5 }
}

/// Camera centres on a ring of radius 5 around the origin, at heights 1 to 2, looking at it.
fn ring(count: usize) -> Vec<Point3<f64>> {
    (0..count)
        .map(|i| {
            let a = i as f64 * 0.35;
            Point3::new(5.0 * a.cos(), 5.0 * a.sin(), 1.0 + (i % 3) as f64 * 0.5)
        })
        .collect()
}

/// instant-ngp's layout: `transforms.json` with the camera at the top level, frames
/// `images/NNNN.jpg` with OpenGL camera-to-world matrices.
fn instant_ngp(dir: &Path, count: usize) {
    std::fs::create_dir_all(dir.join("images")).unwrap();
    let frames: Vec<_> = ring(count)
        .iter()
        .enumerate()
        .map(|(i, eye)| {
            let name = format!("images/{i:04}.jpg");
            photo().save(dir.join(&name)).unwrap();
            let c2w_gl = look_at(eye, &Point3::origin(), &Vector3::z()).inverse().to_homogeneous()
                * scnerf_capture::camera::gl_to_cv();
            let rows: Vec<Vec<f64>> = (0..4).map(|r| (0..4).map(|c| c2w_gl[(r, c)]).collect()).collect();
            json!({"file_path": name, "transform_matrix": rows, "sharpness": 120.0})
        })
        .collect();
    let [k1, k2, ..] = LENS.k;
    let transforms = json!({"fl_x": FOCAL, "fl_y": FOCAL, "cx": f64::from(W) / 2.0, "cy": f64::from(H) / 2.0,
        "w": W, "h": H, "k1": k1, "k2": k2, "p1": LENS.p[0], "p2": LENS.p[1], "aabb_scale": 4, "frames": frames});
    std::fs::write(dir.join("transforms.json"), transforms.to_string()).unwrap();
}

#[test]
fn an_instant_ngp_phone_capture_reads_without_flags() {
    let dir = tempfile::tempdir().unwrap();
    instant_ngp(dir.path(), 8);
    let capture = readers::load(dir.path(), None, ReadOptions::default()).unwrap();
    assert_eq!((capture.format.name(), capture.views.len()), ("nerfstudio", 8));
    let photo_k = photo_k();
    let pinhole = pinhole_for(&photo_k, &LENS, W, H, Fit::LargestRectangle).unwrap();
    for view in &capture.views {
        let lens = view.lens.expect("every view is undistorted");
        assert_eq!((lens.distortion, lens.distorted, lens.pinhole), (LENS, photo_k, pinhole));
        assert_eq!((view.camera.width, view.camera.height, view.camera.intrinsics), (W, H, pinhole));
    }
    // the cameras are 5 away horizontally from what they look at, 1 to 2 above it
    assert_eq!(capture.depth_source, DepthSource::Poses);
    let (nearest, farthest) = (5.0_f64.hypot(1.0), 5.0_f64.hypot(2.0));
    assert!((capture.near - 0.4 * nearest).abs() < 1e-6 && (capture.far - 1.6 * farthest).abs() < 1e-6, "{capture:?}");
    assert!(capture.warnings.is_empty(), "{:?}", capture.warnings);
}

#[test]
fn flags_choose_the_rectangle_use_the_photos_as_pinhole_or_give_the_range() {
    let dir = tempfile::tempdir().unwrap();
    instant_ngp(dir.path(), 4);
    let rect = readers::load(dir.path(), None, ReadOptions::default()).unwrap();
    let all = ReadOptions { undistort: Fit::AllPixels, ..Default::default() };
    let all = readers::load(dir.path(), None, all).unwrap();
    // the largest rectangle of valid pixels sees less of the scene than all of them, and barrel
    // distortion (k1 < 0) squeezed a wider view into the photo than its focal length says
    let (rect_f, all_f) = (rect.views[0].camera.intrinsics.fx, all.views[0].camera.intrinsics.fx);
    assert!(all_f < rect_f && rect_f < FOCAL, "{all_f} {rect_f}");
    let ignored = ReadOptions { ignore_distortion: true, near: Some(2.0), far: Some(8.0), ..Default::default() };
    let ignored = readers::load(dir.path(), None, ignored).unwrap();
    assert!(ignored.views.iter().all(|v| v.lens.is_none() && v.camera.intrinsics.fx == FOCAL));
    assert!(ignored.warnings[0].contains("lens distortion ignored"), "{:?}", ignored.warnings);
    assert_eq!((ignored.near, ignored.far, ignored.depth_source), (2.0, 8.0, DepthSource::Flags));
}

/// The undistorted image shows the scene where its pinhole camera says, to within bilinear
/// sampling's error; the photo as it is (what --ignore-distortion sends) does not.
#[test]
fn undistorted_images_put_the_scene_where_the_pinhole_camera_says() {
    let dir = tempfile::tempdir().unwrap();
    instant_ngp(dir.path(), 4);
    let capture = readers::load(dir.path(), None, ReadOptions::default()).unwrap();
    let view = &capture.views[0];
    let on_disk = std::fs::read(&view.image_path).unwrap();
    let sent = image_bytes(view, &on_disk, capture.background).unwrap();
    assert_eq!(std::fs::read(&view.image_path).unwrap(), on_disk, "the photo on disk is left as it is");
    assert_eq!(image::guess_format(&sent).unwrap(), image::ImageFormat::Jpeg, "a JPEG stays a JPEG");
    let sent = image::load_from_memory(&sent).unwrap().to_rgb8();
    let as_taken = image::load_from_memory(&on_disk).unwrap().to_rgb8();
    assert_eq!(sent.dimensions(), (W, H));
    let mean_error = |image: &image::RgbImage, k: Intrinsics| {
        let (mut sum, mut count) = (0.0, 0);
        // the pixels that a photo pixel reaches (inside the lens's valid area)
        for v in 4..H - 4 {
            for u in 4..W - 4 {
                let want = pattern((f64::from(u) - k.cx) / k.fx, (f64::from(v) - k.cy) / k.fy);
                let got = image.get_pixel(u, v).0;
                sum += (0..3).map(|c| (f64::from(got[c]) - f64::from(want[c])).abs()).sum::<f64>() / 3.0;
                count += 1;
            }
        }
        sum / f64::from(count)
    };
    let (undistorted, ignored) = (mean_error(&sent, view.camera.intrinsics), mean_error(&as_taken, photo_k()));
    println!("mean error: undistorted {undistorted:.2}, as taken {ignored:.2} levels");
    assert!(undistorted < 4.0, "mean error {undistorted} levels");
    assert!(ignored > 3.0 * undistorted, "the photo itself errs by {ignored}, the undistorted by {undistorted}");
}

/// A COLMAP text model with one SIMPLE_RADIAL (phone) and one OPENCV camera, and points.
fn colmap(dir: &Path) {
    let sparse = dir.join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::write(
        sparse.join("cameras.txt"),
        format!("1 SIMPLE_RADIAL {W} {H} {FOCAL} 27 48 0.058\n2 OPENCV {W} {H} {FOCAL} 81 27 48 -0.05 0.01 0.001 0\n"),
    )
    .unwrap();
    let mut images = String::new();
    for (i, eye) in ring(6).iter().enumerate() {
        let w2c = look_at(eye, &Point3::origin(), &Vector3::z());
        let q = nalgebra::UnitQuaternion::from_rotation_matrix(&w2c.rotation);
        let t = w2c.translation.vector;
        let camera = 1 + i % 2;
        images += &format!("{} {} {} {} {} {} {} {} {camera} {i}.png\n\n", i + 1, q.w, q.i, q.j, q.k, t.x, t.y, t.z);
        photo().save(dir.join(format!("images/{i}.png"))).unwrap();
    }
    std::fs::write(sparse.join("images.txt"), images).unwrap();
    // points on a sphere of radius 1 around the origin, without tracks (seen from every image)
    let points: String = (0..50)
        .map(|i| {
            let (a, b) = (i as f64 * 0.7, i as f64 * 0.3);
            format!("{i} {} {} {} 128 128 128 0.5\n", a.cos() * b.sin(), a.sin() * b.sin(), b.cos())
        })
        .collect();
    std::fs::write(sparse.join("points3D.txt"), points).unwrap();
}

#[test]
fn colmap_simple_radial_and_opencv_cameras_are_undistorted_each_by_its_own() {
    let dir = tempfile::tempdir().unwrap();
    colmap(dir.path());
    let capture = readers::load(dir.path(), None, ReadOptions::default()).unwrap();
    assert_eq!(capture.views.len(), 6);
    let lenses: Vec<Distortion> = capture.views.iter().map(|v| v.lens.unwrap().distortion).collect();
    assert_eq!(lenses[0].k[0], 0.058);
    assert_eq!((lenses[1].k[0], lenses[1].k[1], lenses[1].p), (-0.05, 0.01, [0.001, 0.0]));
    assert_eq!(lenses[2], lenses[0]);
    // pincushion (k > 0) stretched a narrower view over the photo: the focal length grows
    assert!(capture.views[0].camera.intrinsics.fx > FOCAL && capture.views[1].camera.intrinsics.fx < FOCAL);
    assert_eq!(capture.depth_source, DepthSource::Points);
    // the points lie within 1 of the origin, whose depth is about 5.1 to 5.4 from the cameras
    assert!(capture.near > 0.9 * 3.5 && capture.near < 0.9 * 4.6, "{}", capture.near);
    assert!(capture.far > 1.1 * 5.6 && capture.far < 1.1 * 6.4, "{}", capture.far);
}

#[test]
fn lens_models_that_cannot_be_undistorted_are_named() {
    let dir = tempfile::tempdir().unwrap();
    colmap(dir.path());
    let cameras = dir.path().join("sparse/0/cameras.txt");
    std::fs::write(&cameras, format!("1 FOV {W} {H} 80 80 27 48 0.9\n2 PINHOLE {W} {H} 80 80 27 48\n")).unwrap();
    let err = readers::load(dir.path(), None, ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("cameras.txt: camera 1 uses the FOV model, which cannot be undistorted here"), "{err}");
    // coefficients whose distortion folds over within the image
    std::fs::write(&cameras, format!("1 SIMPLE_RADIAL {W} {H} 80 27 48 -3\n2 PINHOLE {W} {H} 80 80 27 48\n")).unwrap();
    let err = readers::load(dir.path(), None, ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("camera 1 (SIMPLE_RADIAL): its lens distortion (k1=-3) cannot be inverted"), "{err}");

    let ngp = tempfile::tempdir().unwrap();
    instant_ngp(ngp.path(), 4);
    let file = ngp.path().join("transforms.json");
    let text = std::fs::read_to_string(&file).unwrap();
    std::fs::write(&file, text.replacen("\"k1\":", "\"k4\":0.1,\"k1\":", 1)).unwrap();
    let err = readers::load(ngp.path(), None, ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("frames[0].k4 is not zero"), "{err}");
    std::fs::write(&file, text.replacen("\"k1\":", "\"k1\":\"-0.1\",\"k0\":", 1)).unwrap();
    let err = readers::load(ngp.path(), None, ReadOptions::default()).unwrap_err().to_string();
    assert!(err.contains("frames[0].k1 is not a number"), "{err}");
}
