//! Captures as LLFF and nerfstudio distribute them, written at test time: full-size photos in
//! `images/` and the same views downscaled in `images_N/`, forward-facing cameras on a small grid
//! looking down the world's -z, the scene between depths 2 and 6.

use std::path::Path;

use serde_json::json;

/// Camera centres (x, y, 0) of the views.
const CENTRES: [(f64, f64); 5] = [(0.0, 0.0), (0.3, 0.1), (-0.3, 0.1), (0.1, -0.3), (-0.1, 0.3)];

/// A colourful image of `w` x `h` that differs per view.
fn photo(view: usize, w: u32, h: u32) -> image::RgbImage {
    image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([(x * 255 / w) as u8, (y * 255 / h) as u8, (40 * view as u32 % 256) as u8])
    })
}

/// Writes view `i` of every set: `images/<name>.<full_ext>` at `full`, `images_N/<name>.png` at
/// `full / N`.
fn write_sets(dir: &Path, name: &str, full_ext: &str, i: usize, full: (u32, u32), factors: &[u32]) {
    std::fs::create_dir_all(dir.join("images")).unwrap();
    photo(i, full.0, full.1).save(dir.join("images").join(format!("{name}.{full_ext}"))).unwrap();
    for &n in factors {
        let folder = dir.join(format!("images_{n}"));
        std::fs::create_dir_all(&folder).unwrap();
        photo(i, full.0 / n, full.1 / n).save(folder.join(format!("{name}.png"))).unwrap();
    }
}

/// LLFF: `poses_bounds.npy` (hwf of the full-size images, focal = width), JPEGs in `images/`,
/// PNGs in `images_N/`, as the LLFF dataset is distributed.
pub fn llff(dir: &Path, full: (u32, u32), factors: &[u32]) {
    let (w, h) = (f64::from(full.0), f64::from(full.1));
    let mut values = Vec::new();
    for (i, (x, y)) in CENTRES.iter().enumerate() {
        // columns [down, right, back | centre | hwf]; rows x, y, z
        values.extend([0.0, 1.0, 0.0, *x, h]);
        values.extend([-1.0, 0.0, 0.0, *y, w]);
        values.extend([0.0, 0.0, 1.0, 0.0, w]);
        values.extend([2.0, 6.0]);
        write_sets(dir, &format!("IMG_{i:04}"), "jpg", i, full, factors);
    }
    std::fs::write(dir.join("poses_bounds.npy"), npy_f64(&values, CENTRES.len(), 17)).unwrap();
}

/// nerfstudio: `transforms.json` of the full-size images (with its `near_far`), frames
/// `images/frame_0000N.png`, and the downscaled sets nerfstudio's `--downscale-factor` reads.
pub fn nerfstudio(dir: &Path, full: (u32, u32), factors: &[u32]) {
    let (w, h) = (f64::from(full.0), f64::from(full.1));
    let frames: Vec<_> = CENTRES
        .iter()
        .enumerate()
        .map(|(i, (x, y))| {
            let name = format!("frame_{:05}", i + 1);
            write_sets(dir, &name, "png", i, full, factors);
            // OpenGL camera-to-world: x right, y up, z back
            let matrix = [[1.0, 0.0, 0.0, *x], [0.0, 1.0, 0.0, *y], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
            json!({"file_path": format!("images/{name}.png"), "transform_matrix": matrix})
        })
        .collect();
    let transforms = json!({"camera_model": "OPENCV", "fl_x": w, "fl_y": w, "cx": w / 2.0, "cy": h / 2.0,
                            "w": full.0, "h": full.1, "near_far": [2.0, 6.0], "frames": frames});
    std::fs::write(dir.join("transforms.json"), transforms.to_string()).unwrap();
}

/// A .npy file (format 1.0) of a C-order float64 array.
fn npy_f64(values: &[f64], rows: usize, cols: usize) -> Vec<u8> {
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({rows}, {cols}), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    out.extend(values.iter().flat_map(|v| v.to_le_bytes()));
    out
}

/// A phone capture as instant-ngp's `colmap2nerf` leaves it: one `transforms.json` with the
/// camera at the top level (fl_x, fl_y, cx, cy, w, h, k1, k2, p1, p2, aabb_scale), no depth
/// range, portrait JPEGs of `size` in `images/`, `count` views on a ring around the origin.
pub fn phone(dir: &Path, size: (u32, u32), count: usize) {
    use nalgebra::{Point3, Vector3};
    use scnerf_capture::camera::{gl_to_cv, look_at};
    std::fs::create_dir_all(dir.join("images")).unwrap();
    let (w, h) = (f64::from(size.0), f64::from(size.1));
    let frames: Vec<_> = (0..count)
        .map(|i| {
            let name = format!("images/{i:04}.jpg");
            photo(i, size.0, size.1).save(dir.join(&name)).unwrap();
            let a = i as f64 * 0.3;
            let eye = Point3::new(5.0 * a.cos(), 5.0 * a.sin(), 1.0);
            let c2w = look_at(&eye, &Point3::origin(), &Vector3::z()).inverse().to_homogeneous() * gl_to_cv();
            let rows: Vec<Vec<f64>> = (0..4).map(|r| (0..4).map(|c| c2w[(r, c)]).collect()).collect();
            json!({"file_path": name, "transform_matrix": rows})
        })
        .collect();
    let transforms = json!({"fl_x": 0.9 * h, "fl_y": 0.9 * h, "cx": w / 2.0, "cy": h / 2.0, "w": size.0, "h": size.1,
        "k1": -0.06, "k2": 0.01, "p1": 0.0005, "p2": -0.0003, "aabb_scale": 16, "frames": frames});
    std::fs::write(dir.join("transforms.json"), transforms.to_string()).unwrap();
}
