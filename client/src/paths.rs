//! Camera paths through a capture: the poses of the frames to render.
//!
//! * `interpolate`: through the captured poses in capture order, rotations by slerp and centres
//!   by a Catmull-Rom spline (it passes through every captured centre);
//! * `orbit`: a horizontal circle around the point the cameras look at, at their mean height and
//!   horizontal distance, starting at the first view, for object captures (Blender, DTU,
//!   turntables); "horizontal" as level cameras define it (orthogonal to their right axes);
//! * `spiral`: LLFF's `render_path_spiral` for forward-facing captures: two turns of an ellipse
//!   around the mean camera, looking at a point at the capture's focus depth;
//! * a camera file: nerfstudio's `camera_path.json` (what its viewer exports and `ns-render
//!   camera-path` reads), or a JSON array of cameras in the API's form.

use std::f64::consts::PI;
use std::path::Path;

use nalgebra::{Matrix3, Point3, UnitQuaternion, Vector3};

use crate::error::{Error, Result};
use scnerf_capture::camera::{convergence, look_at, unit, w2c_from_api, Axes, Camera, Intrinsics, Pose, PoseKind};
use scnerf_capture::percentile;
use scnerf_capture::wire::{from_rows, WireCamera};
use serde::Deserialize;

/// `frames` poses through the captured ones (world-to-camera): frame j sits at parameter
/// t = j (n - 1) / (frames - 1) along the captured sequence, so with frames = k (n - 1) + 1
/// every k-th frame is a captured pose.
pub fn interpolate(captured: &[Pose], frames: usize) -> Vec<Pose> {
    let c2w: Vec<Pose> = captured.iter().map(Pose::inverse).collect();
    let centres: Vec<Vector3<f64>> = c2w.iter().map(|p| p.translation.vector).collect();
    let rotations: Vec<UnitQuaternion<f64>> =
        c2w.iter().map(|p| UnitQuaternion::from_rotation_matrix(&p.rotation)).collect();
    let last = captured.len() - 1;
    (0..frames)
        .map(|j| {
            let t = if frames > 1 { j as f64 * last as f64 / (frames - 1) as f64 } else { 0.0 };
            let seg = (t.floor() as usize).min(last.saturating_sub(1));
            let u = t - seg as f64;
            let next = (seg + 1).min(last);
            let at = |i: isize| centres[i.clamp(0, last as isize) as usize];
            let s = seg as isize;
            let centre = catmull_rom(at(s - 1), at(s), at(s + 1), at(s + 2), u);
            let rotation = rotations[seg].slerp(&rotations[next], u);
            Pose::from_parts(centre.into(), rotation.to_rotation_matrix()).inverse()
        })
        .collect()
}

/// Uniform Catmull-Rom segment from p1 (u = 0) to p2 (u = 1).
fn catmull_rom(p0: Vector3<f64>, p1: Vector3<f64>, p2: Vector3<f64>, p3: Vector3<f64>, u: f64) -> Vector3<f64> {
    let (u2, u3) = (u * u, u * u * u);
    ((2.0 * p1) + (p2 - p0) * u + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * u2 + (3.0 * p1 - p0 - 3.0 * p2 + p3) * u3)
        * 0.5
}

/// The capture's "up": the mean of the cameras' up vectors (-y in OpenCV axes).
fn mean_up(cameras: &[Camera]) -> Result<Vector3<f64>> {
    unit(cameras.iter().map(|c| -c.w2c.rotation.matrix().row(1).transpose()).sum())
        .ok_or_else(|| Error::Usage("the cameras have no common up direction".into()))
}

/// The world's vertical as level cameras see it (held without roll, on a turntable, rendered):
/// the direction orthogonal to every camera's right axis, on the side of their mean up; their
/// mean up when the right axes share no normal (rolled cameras).
fn vertical(cameras: &[Camera]) -> Result<Vector3<f64>> {
    let up = mean_up(cameras)?;
    let rights: Matrix3<f64> = cameras
        .iter()
        .map(|c| {
            let right = c.w2c.rotation.matrix().row(0).transpose();
            right * right.transpose()
        })
        .sum();
    let eigen = rights.symmetric_eigen();
    let mut order = [0, 1, 2];
    order.sort_by(|a, b| eigen.eigenvalues[*a].total_cmp(&eigen.eigenvalues[*b]));
    let (smallest, middle) = (eigen.eigenvalues[order[0]], eigen.eigenvalues[order[1]]);
    if smallest > 0.05 * middle {
        return Ok(up);
    }
    let normal = eigen.eigenvectors.column(order[0]).into_owned();
    Ok(if normal.dot(&up) < 0.0 { -normal } else { normal })
}

/// The point an object capture looks at ([`convergence`]).
fn look_at_point(cameras: &[Camera]) -> Result<Point3<f64>> {
    convergence(cameras).map(|c| c.point).ok_or_else(|| {
        Error::Usage("the cameras do not look at a common point (a forward-facing capture?): use --path spiral".into())
    })
}

/// A horizontal circle of `frames` poses (seamless: the last frame is one step before the first)
/// around the point the cameras look at, at their mean height and mean horizontal distance,
/// starting at the first captured view's azimuth.
pub fn orbit(cameras: &[Camera], frames: usize) -> Result<Vec<Pose>> {
    let centre = look_at_point(cameras)?;
    let up = vertical(cameras)?;
    let offsets: Vec<Vector3<f64>> = cameras.iter().map(|c| c.center() - centre).collect();
    let height = offsets.iter().map(|o| o.dot(&up)).sum::<f64>() / offsets.len() as f64;
    let horizontal = |o: &Vector3<f64>| o - up * o.dot(&up);
    let radius = offsets.iter().map(|o| horizontal(o).norm()).sum::<f64>() / offsets.len() as f64;
    let e1 = unit(horizontal(&offsets[0]))
        .ok_or_else(|| Error::Usage("the first view is straight above the object: cannot start an orbit".into()))?;
    let e2 = up.cross(&e1);
    Ok((0..frames)
        .map(|j| {
            let theta = 2.0 * PI * j as f64 / frames as f64;
            let eye = centre + up * height + (e1 * theta.cos() + e2 * theta.sin()) * radius;
            look_at(&eye, &centre, &up)
        })
        .collect())
}

/// LLFF's spiral (`render_path_spiral` with its defaults: 2 turns, zrate 0.5, focus at
/// 1 / (0.25 / (0.9 near) + 0.75 / (5 far)), radii the 90th percentile of the camera offsets
/// from their mean pose), written in OpenCV axes.
pub fn spiral(cameras: &[Camera], near: f64, far: f64, frames: usize) -> Result<Vec<Pose>> {
    let n = cameras.len() as f64;
    let centre = Point3::from(cameras.iter().map(|c| c.center().coords).sum::<Vector3<f64>>() / n);
    let forward = unit(cameras.iter().map(Camera::forward).sum())
        .ok_or_else(|| Error::Usage("the cameras face every way: use --path orbit".into()))?;
    let up = mean_up(cameras)?;
    let mean_c2w = look_at(&centre, &(centre + forward), &up).inverse();
    // offsets in the mean camera's frame: x right, y down, z forward
    let local: Vec<Vector3<f64>> =
        cameras.iter().map(|c| mean_c2w.inverse_transform_point(&c.center()).coords.abs()).collect();
    let radii = Vector3::from_fn(|axis, _| {
        let mut values: Vec<f64> = local.iter().map(|v| v[axis]).collect();
        values.sort_by(f64::total_cmp);
        percentile(&values, 90.0)
    });
    let focal = 1.0 / (0.25 / (0.9 * near) + 0.75 / (5.0 * far));
    let focus = centre + forward * focal;
    Ok((0..frames)
        .map(|j| {
            let theta = 2.0 * 2.0 * PI * j as f64 / frames as f64;
            let offset = Vector3::new(theta.cos(), theta.sin(), (0.5 * theta).sin()).component_mul(&radii);
            look_at(&mean_c2w.transform_point(&Point3::from(offset)), &focus, &up)
        })
        .collect())
}

/// A JSON array of cameras in the API's form (`{width, height, intrinsics: {fx, fy, cx, cy} |
/// K, pose: {matrix, kind, axes}}`), in the capture's world.
/// The cameras of a camera file, with what it says about time.
#[derive(Debug)]
pub struct PathFile {
    pub cameras: Vec<Camera>,
    /// Frames per second (nerfstudio's `fps`, else frames / `seconds`).
    pub fps: Option<f64>,
    pub warnings: Vec<String>,
}

/// A camera file: nerfstudio's `camera_path.json` (an object with `camera_path`), or a JSON
/// array of cameras in the API's form.
pub fn from_file(path: &Path) -> Result<PathFile> {
    let data = scnerf_capture::readers::read_json(&scnerf_capture::files::Disk, path)?;
    if data.get("camera_path").is_some() {
        return nerfstudio_path(&data, path);
    }
    let items = data.as_array().ok_or_else(|| {
        Error::dataset(path, "expected a JSON array of cameras or nerfstudio's camera_path.json (with camera_path)")
    })?;
    if items.is_empty() {
        return Err(Error::dataset(path, "the camera path is empty"));
    }
    let cameras: Result<Vec<Camera>> =
        items.iter().enumerate().map(|(i, v)| camera_from_json(v, path, &format!("[{i}]"))).collect();
    Ok(PathFile { cameras: cameras?, fps: None, warnings: Vec::new() })
}

/// nerfstudio's camera path (`ns-render camera-path`, its `get_path_from_json`): every entry of
/// `camera_path` is `camera_to_world` (16 numbers, row-major, OpenGL axes) and `fov`, the
/// vertical field of view in degrees, seen at `render_width` x `render_height`: f = (H / 2) /
/// tan(fov / 2) for both axes, principal point at the image centre (nerfstudio's (W/2, H/2), the
/// first pixel's centre at (0.5, 0.5): (W/2 - 0.5, H/2 - 0.5) here). `aspect` is the viewer's and
/// is not used, as in ns-render. Only `perspective` cameras.
fn nerfstudio_path(data: &serde_json::Value, path: &Path) -> Result<PathFile> {
    let bad = |msg: String| Error::dataset(path, msg);
    let camera_type = data.get("camera_type").and_then(|t| t.as_str()).unwrap_or("perspective");
    if camera_type != "perspective" {
        return Err(bad(format!("camera_type {camera_type:?}: only perspective camera paths can be rendered")));
    }
    let size = |key: &str| {
        data.get(key)
            .and_then(serde_json::Value::as_u64)
            .and_then(|v| u32::try_from(v).ok())
            .filter(|&v| v > 0)
            .ok_or_else(|| bad(format!("{key} must be a positive whole number")))
    };
    let (width, height) = (size("render_width")?, size("render_height")?);
    let entries = data["camera_path"]
        .as_array()
        .filter(|a| !a.is_empty())
        .ok_or_else(|| bad("camera_path must be a non-empty array of {camera_to_world, fov, aspect}".into()))?;
    let mut warnings = Vec::new();
    let mut cameras = Vec::with_capacity(entries.len());
    for (i, entry) in entries.iter().enumerate() {
        let at = format!("camera_path[{i}]");
        let m = nerfstudio_matrix(&entry["camera_to_world"])
            .ok_or_else(|| bad(format!("{at}.camera_to_world must be 16 finite numbers (4x4, row-major)")))?;
        let fov = entry["fov"].as_f64().filter(|f| *f > 0.0 && *f < 180.0);
        let fov =
            fov.ok_or_else(|| bad(format!("{at}.fov must be a vertical field of view in degrees, in (0, 180)")))?;
        let aspect = entry.get("aspect").and_then(serde_json::Value::as_f64);
        let render_aspect = f64::from(width) / f64::from(height);
        if aspect.is_some_and(|a| (a - render_aspect).abs() > 1e-3 * render_aspect) && warnings.is_empty() {
            warnings.push(format!(
                "{}: {at}.aspect {} differs from render_width / render_height ({width}x{height}); the frames keep \
                 {width}x{height}, as ns-render does",
                path.display(),
                aspect.unwrap_or_default()
            ));
        }
        let f = f64::from(height) / 2.0 / (fov.to_radians() / 2.0).tan();
        let intrinsics =
            Intrinsics { fx: f, fy: f, cx: f64::from(width) / 2.0 - 0.5, cy: f64::from(height) / 2.0 - 0.5 };
        let w2c = w2c_from_api(&m, PoseKind::CameraToWorld, Axes::Opengl)
            .ok_or_else(|| bad(format!("{at}.camera_to_world is not a rigid transform")))?;
        cameras.push(Camera { width, height, intrinsics, w2c });
    }
    let number = |key: &str| data.get(key).and_then(serde_json::Value::as_f64).filter(|v| *v > 0.0);
    let fps = number("fps").or_else(|| number("seconds").map(|s| cameras.len() as f64 / s));
    Ok(PathFile { cameras, fps, warnings })
}

/// A 4x4 matrix from 16 numbers in row-major order (nerfstudio's form) or 4 rows of 4.
fn nerfstudio_matrix(value: &serde_json::Value) -> Option<nalgebra::Matrix4<f64>> {
    let items = value.as_array()?;
    let flat: Vec<f64> = if items.len() == 4 && items.iter().all(serde_json::Value::is_array) {
        items.iter().flat_map(|row| row.as_array().into_iter().flatten()).map(|v| v.as_f64()).collect::<Option<_>>()?
    } else {
        items.iter().map(serde_json::Value::as_f64).collect::<Option<_>>()?
    };
    (flat.len() == 16 && flat.iter().all(|v| v.is_finite())).then(|| nalgebra::Matrix4::from_row_slice(&flat))
}

/// One camera in the API's JSON form, converted to the canonical one.
pub fn camera_from_json(value: &serde_json::Value, path: &Path, at: &str) -> Result<Camera> {
    let bad = |msg: String| Error::dataset(path, format!("{at}: {msg}"));
    let cam = WireCamera::deserialize(value).map_err(|e| bad(e.to_string()))?;
    let k = cam.intrinsic_matrix().map_err(|e| bad(e.to_string()))?;
    let intrinsics =
        Intrinsics::from_k(&k).ok_or_else(|| bad("K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]".into()))?;
    if cam.width == 0 || cam.height == 0 || !(intrinsics.fx > 0.0 && intrinsics.fy > 0.0) {
        return Err(bad("width, height, fx and fy must be positive".into()));
    }
    let w2c = w2c_from_api(&from_rows(&cam.pose.matrix), cam.pose.kind, cam.pose.axes)
        .ok_or_else(|| bad("pose.matrix is not a rigid transform".into()))?;
    Ok(Camera { width: cam.width, height: cam.height, intrinsics, w2c })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(eye: Point3<f64>, target: Point3<f64>) -> Camera {
        Camera {
            width: 8,
            height: 6,
            intrinsics: Intrinsics { fx: 8.0, fy: 8.0, cx: 4.0, cy: 3.0 },
            w2c: look_at(&eye, &target, &Vector3::z()),
        }
    }

    /// Six level cameras on part of a ring of radius 4 around (0.1, -0.2, 0.3), 1 to 2 above it
    /// (mean 1.5), looking at it.
    fn object_capture() -> Vec<Camera> {
        let target = Point3::new(0.1, -0.2, 0.3);
        (0..6)
            .map(|i| {
                let a = i as f64 * 0.9;
                camera(Point3::new(4.0 * a.cos(), 4.0 * a.sin(), 1.0 + 0.2 * i as f64) + target.coords, target)
            })
            .collect()
    }

    /// Five cameras in a plane, all looking roughly along +y: an LLFF-like capture.
    fn forward_capture() -> Vec<Camera> {
        [(-0.3, 0.0), (0.3, 0.05), (0.0, 0.2), (-0.2, -0.15), (0.25, -0.2)]
            .iter()
            .map(|&(x, z)| camera(Point3::new(x, 0.0, z), Point3::new(x * 0.1, 10.0, z * 0.1)))
            .collect()
    }

    fn same_pose(a: &Pose, b: &Pose) -> bool {
        (a.to_homogeneous() - b.to_homogeneous()).amax() < 1e-9
    }

    #[test]
    fn interpolate_passes_through_the_captured_poses() {
        let poses: Vec<Pose> = object_capture().iter().map(|c| c.w2c).collect();
        let path = interpolate(&poses, 3 * (poses.len() - 1) + 1);
        for (i, p) in poses.iter().enumerate() {
            assert!(same_pose(&path[3 * i], p), "frame {} is not view {i}", 3 * i);
        }
        // in between, rotations are slerps: halfway has the mean of the two endpoints' angles
        let q = |p: &Pose| UnitQuaternion::from_rotation_matrix(&p.rotation);
        let (a, b) = (q(&poses[0].inverse()), q(&poses[1].inverse()));
        let mid = interpolate(&poses[..2], 3)[1];
        assert!((q(&mid.inverse()).angle_to(&a) - a.angle_to(&b) / 2.0).abs() < 1e-9);
        assert_eq!(interpolate(&poses, 1).len(), 1);
    }

    #[test]
    fn slerp_endpoints_are_the_captured_rotations() {
        let poses: Vec<Pose> = object_capture().iter().map(|c| c.w2c).collect();
        let path = interpolate(&poses, 50);
        assert!(same_pose(&path[0], &poses[0]));
        assert!(same_pose(&path[49], &poses[5]));
    }

    #[test]
    fn orbit_circles_the_object_at_a_constant_radius() {
        let cams = object_capture();
        let target = Point3::new(0.1, -0.2, 0.3);
        let path = orbit(&cams, 24).unwrap();
        assert_eq!(path.len(), 24);
        for p in &path {
            let c = Camera { w2c: *p, ..cams[0].clone() };
            // 4 horizontally, mean height 1.5 above the target
            assert!(((c.center() - target).norm() - (16.0f64 + 1.5 * 1.5).sqrt()).abs() < 1e-9);
            assert!(((c.center().z - target.z) - 1.5).abs() < 1e-9);
            assert!(((target - c.center()).normalize() - c.forward()).norm() < 1e-9, "looks at the object");
        }
        // starts above the first view
        let first = Camera { w2c: path[0], ..cams[0].clone() };
        let (h0, h1) = ((first.center() - target).xy(), (cams[0].center() - target).xy());
        assert!((h0.normalize() - h1.normalize()).norm() < 1e-9);
    }

    #[test]
    fn orbit_refuses_a_forward_facing_capture() {
        let err = orbit(&forward_capture(), 10).unwrap_err().to_string();
        assert!(err.contains("use --path spiral"), "{err}");
    }

    #[test]
    fn spiral_stays_forward_facing() {
        let cams = forward_capture();
        let mean_forward = Vector3::y();
        let path = spiral(&cams, 1.0, 20.0, 40).unwrap();
        assert_eq!(path.len(), 40);
        for p in &path {
            let c = Camera { w2c: *p, ..cams[0].clone() };
            assert!(c.forward().dot(&mean_forward) > 0.99, "forward {:?}", c.forward());
            assert!(c.center().coords.norm() < 0.5, "stays near the captured cameras");
        }
    }

    #[test]
    fn file_cameras_in_any_convention() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("path.json");
        let c = camera(Point3::new(1.0, 2.0, 3.0), Point3::origin());
        let c2w_gl = c.w2c.inverse().to_homogeneous()
            * nalgebra::Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, -1.0, -1.0, 1.0));
        let rows = |m: nalgebra::Matrix4<f64>| -> Vec<Vec<f64>> {
            (0..4).map(|r| (0..4).map(|k| m[(r, k)]).collect()).collect()
        };
        let json = serde_json::json!([
            {"width": 8, "height": 6, "intrinsics": {"fx": 8.0, "fy": 8.0, "cx": 4.0, "cy": 3.0},
             "pose": {"matrix": rows(c.w2c.to_homogeneous()), "kind": "world_to_camera", "axes": "opencv"}},
            {"width": 8, "height": 6, "K": [[8.0, 0.0, 4.0], [0.0, 8.0, 3.0], [0.0, 0.0, 1.0]],
             "pose": {"matrix": rows(c2w_gl), "kind": "camera_to_world", "axes": "opengl"}}
        ]);
        std::fs::write(&file, json.to_string()).unwrap();
        let cams = from_file(&file).unwrap().cameras;
        for got in &cams {
            assert!(same_pose(&got.w2c, &c.w2c));
            assert_eq!(got.intrinsics, c.intrinsics);
        }
        std::fs::write(&file, r#"[{"width": 8, "height": 6, "pose": {}}]"#).unwrap();
        let err = from_file(&file).unwrap_err().to_string();
        assert!(err.contains("path.json: [0]: missing field `matrix`"), "{err}");
    }

    /// nerfstudio's camera_path.json gives the cameras that the same poses and lens give in the
    /// API's own form (fov -> focal, OpenGL camera-to-world, nerfstudio's principal point).
    #[test]
    fn nerfstudio_camera_paths_read_as_the_same_cameras_in_api_form() {
        let dir = tempfile::tempdir().unwrap();
        let c2w_gl = |c: &Camera| {
            let m = c.w2c.inverse().to_homogeneous()
                * nalgebra::Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, -1.0, -1.0, 1.0));
            (0..4).flat_map(|r| (0..4).map(move |k| m[(r, k)])).collect::<Vec<f64>>()
        };
        let cams = [
            camera(Point3::new(1.0, 2.0, 3.0), Point3::origin()),
            camera(Point3::new(-2.0, 1.0, 3.0), Point3::new(0.1, 0.0, 0.0)),
        ];
        // f = 8 at a height of 6: fov = 2 atan(3 / 8)
        let fov = 2.0 * (3.0f64 / 8.0).atan().to_degrees();
        let entries: Vec<_> = cams
            .iter()
            .map(|c| serde_json::json!({"camera_to_world": c2w_gl(c), "fov": fov, "aspect": 8.0 / 6.0}))
            .collect();
        let ns = serde_json::json!({"camera_type": "perspective", "render_width": 8, "render_height": 6,
                                    "camera_path": entries, "fps": 30, "seconds": 4, "keyframes": []});
        let ns_file = dir.path().join("camera_path.json");
        std::fs::write(&ns_file, ns.to_string()).unwrap();
        let nerfstudio_centre = Intrinsics { fx: 8.0, fy: 8.0, cx: 3.5, cy: 2.5 };
        let api: Vec<_> =
            cams.iter().map(|c| WireCamera::from(&Camera { intrinsics: nerfstudio_centre, ..c.clone() })).collect();
        let api_file = dir.path().join("cameras.json");
        std::fs::write(&api_file, serde_json::to_string(&api).unwrap()).unwrap();
        let (from_ns, from_api) = (from_file(&ns_file).unwrap(), from_file(&api_file).unwrap());
        assert_eq!((from_ns.fps, from_api.fps, from_ns.warnings.len()), (Some(30.0), None, 0));
        assert_eq!(from_ns.cameras.len(), 2);
        for (a, b) in from_ns.cameras.iter().zip(&from_api.cameras) {
            assert!(same_pose(&a.w2c, &b.w2c));
            assert_eq!((a.width, a.height), (b.width, b.height));
            let (ia, ib) = (a.intrinsics, b.intrinsics);
            assert!((ia.fx - ib.fx).abs() < 1e-12 && (ia.fy - ib.fy).abs() < 1e-12, "{ia:?}");
            assert_eq!((ia.cx, ia.cy), (ib.cx, ib.cy));
        }
        // without fps: frames / seconds; an aspect unlike the render size: one warning
        let mut ns2 = ns.clone();
        ns2.as_object_mut().unwrap().remove("fps");
        ns2["camera_path"][0]["aspect"] = serde_json::json!(2.0);
        std::fs::write(&ns_file, ns2.to_string()).unwrap();
        let read = from_file(&ns_file).unwrap();
        assert_eq!(read.fps, Some(0.5));
        assert!(read.warnings[0].contains("camera_path[0].aspect 2 differs"), "{:?}", read.warnings);
        // refusals name the field
        for (key, value, says) in [
            ("camera_type", serde_json::json!("equirectangular"), "only perspective"),
            ("render_width", serde_json::json!(0), "render_width must be a positive whole number"),
            (
                "camera_path",
                serde_json::json!([{"camera_to_world": [1, 2], "fov": 50}]),
                "camera_path[0].camera_to_world",
            ),
            ("camera_path", serde_json::json!([{"camera_to_world": c2w_gl(&cams[0])}]), "camera_path[0].fov"),
        ] {
            let mut bad = ns.clone();
            bad[key] = value;
            std::fs::write(&ns_file, bad.to_string()).unwrap();
            let err = from_file(&ns_file).unwrap_err().to_string();
            assert!(err.contains("camera_path.json: ") && err.contains(says), "{err}");
        }
    }
}
