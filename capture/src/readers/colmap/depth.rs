//! The depth range from the model's 3D points.

use std::collections::HashMap;
use std::path::Path;

use super::records::{ImageRecord, Points};
use crate::camera::Pose;
use crate::error::{Error, Result};
use crate::percentile;

/// Most depths (a point's z in one image) ranked for the depth range: 32 MiB of them, more than
/// a 64 MiB points3D file of real tracks gives. A point without a track counts in every image,
/// so a file of them could ask for points x images.
pub const MAX_DEPTHS: usize = 1 << 22;

/// near = 0.9 x the 1st, far = 1.1 x the 99th percentile of the positive z-depths of each point
/// in the images that observe it (in every image for a point without a track);
/// `colmap.py::_points_near_far`. Images whose file is missing still count.
pub(super) fn points_near_far(points: &Points, images: &[ImageRecord], file: &Path) -> Result<Option<(f64, f64)>> {
    // Python keeps the last record of a repeated image id
    let poses: HashMap<i64, &Pose> = images.iter().map(|i| (i.id, &i.w2c)).collect();
    let mut observed: HashMap<i64, Vec<usize>> = HashMap::new();
    let mut untracked = Vec::new();
    for (k, track) in points.tracks.iter().enumerate() {
        if track.is_empty() {
            untracked.push(k);
        }
        for id in track {
            observed.entry(*id).or_default().push(k);
        }
    }
    let observations: usize = poses.keys().map(|id| observed.get(id).map_or(0, Vec::len)).sum();
    let depth_count = untracked.len().checked_mul(poses.len()).and_then(|n| n.checked_add(observations));
    if depth_count.is_none_or(|n| n > MAX_DEPTHS) {
        return Err(Error::dataset(
            file,
            format!(
                "{} points ({} without a track, seen from all {} images) give more than {MAX_DEPTHS} depths to \
                 rank for near/far: pass --near and --far",
                points.xyz.len(),
                untracked.len(),
                poses.len()
            ),
        ));
    }
    let mut depths = Vec::new();
    for (id, w2c) in &poses {
        let own = observed.get(id).map(Vec::as_slice).unwrap_or_default();
        for &k in own.iter().chain(&untracked) {
            let z = (*w2c * points.xyz[k]).z;
            if z > 1e-9 {
                depths.push(z);
            }
        }
    }
    if depths.is_empty() {
        return Ok(None);
    }
    depths.sort_by(f64::total_cmp);
    Ok(Some((0.9 * percentile(&depths, 1.0), 1.1 * percentile(&depths, 99.0))))
}
