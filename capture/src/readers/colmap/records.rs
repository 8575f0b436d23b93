//! The records a COLMAP model holds, as both encodings' parsers return them.

use nalgebra::{Point3, Quaternion, Translation3, UnitQuaternion};

use crate::camera::Pose;

pub(super) struct CameraModel {
    pub(super) model: String,
    pub(super) width: u64,
    pub(super) height: u64,
    pub(super) params: Vec<f64>,
}

pub(super) struct ImageRecord {
    pub(super) id: i64,
    pub(super) name: String,
    pub(super) w2c: Pose,
    pub(super) camera_id: i64,
}

/// Point positions and, per point, the ids of the images that observe it.
pub(super) struct Points {
    pub(super) xyz: Vec<Point3<f64>>,
    pub(super) tracks: Vec<Vec<i64>>,
}

/// A world-to-camera pose from COLMAP's quaternion (qw qx qy qz) and translation; `None` when
/// either is zero or not finite.
pub(super) fn pose(q: [f64; 4], t: [f64; 3]) -> Option<Pose> {
    let q = Quaternion::new(q[0], q[1], q[2], q[3]);
    let n = q.norm();
    if !(n.is_finite() && n >= 1e-12 && t.iter().all(|v| v.is_finite())) {
        return None;
    }
    let rotation = UnitQuaternion::from_quaternion(q).to_rotation_matrix();
    Some(Pose::from_parts(Translation3::new(t[0], t[1], t[2]), rotation))
}
