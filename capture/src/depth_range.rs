//! Where a capture's depth range comes from, and the range its poses give when its files have
//! none (nerfstudio and instant-ngp files never carry one).
//!
//! From the poses: the point the optical axes converge on ([`convergence`]) and its depth z in
//! each camera. near = [`NEAR_MARGIN`] x the smallest depth; far = [`OBJECT_FAR_MARGIN`] x the
//! largest when the axes spread by more than [`OBJECT_SPREAD`] (an object captured from around
//! it lies between the cameras and the far side of the ring), else [`FORWARD_FAR_MARGIN`] x the
//! largest (a forward-facing capture: the scene reaches far behind the point looked at). The
//! margins are set so that the range contains the known one, and is at most twice as wide, on
//! the scenes of `tests/depth_range.rs`: lego (2 to 6; depths 4.03), DTU scan37 (2.125 to 4.525;
//! depths 3.04) and LLFF horns (11.2 to 169; depths 26.3 to 29.0).
//!
//! The exporter computes the same range (`data/depth_range.py`); both are held to
//! `tests/fixtures/rules/depth_range.json` (`tests/rules.rs`).

use std::path::Path;

use crate::camera::{convergence, Camera};
use crate::error::{Error, Result};

/// Where `near` and `far` come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DepthSource {
    /// `--near` and `--far` (the query's `near` and `far` on the server).
    Flags,
    /// The dataset's files (nerfstudio's near/far keys, LLFF's bounds, DTU's depth range,
    /// Blender's convention).
    Dataset,
    /// COLMAP's 3D points.
    Points,
    /// The cameras' poses ([`from_poses`]).
    Poses,
}

impl DepthSource {
    /// What `scnerf info` prints after the range.
    pub fn describe(self) -> &'static str {
        match self {
            DepthSource::Flags => "from --near/--far",
            DepthSource::Dataset => "from the dataset",
            DepthSource::Points => "from COLMAP's points (0.9 x 1st, 1.1 x 99th percentile of their depths)",
            DepthSource::Poses => {
                "from the poses (0.4 x the nearest, 1.6 x (forward-facing: 8 x) the farthest depth of the point \
                 the cameras look at)"
            }
        }
    }
}

pub const NEAR_MARGIN: f64 = 0.4;
pub const OBJECT_FAR_MARGIN: f64 = 1.6;
pub const FORWARD_FAR_MARGIN: f64 = 8.0;
/// [`crate::camera::Convergence::spread`] above which the cameras surround what they look at
/// (about 13 degrees between the axes): lego spreads 0.77, scan37 0.16, horns 0.018.
pub const OBJECT_SPREAD: f64 = 0.05;

/// (near, far) from the cameras' poses; `None` when their axes meet at no point in front of
/// them (see [`convergence`]), or the point is in front of none of them.
pub fn from_poses(cameras: &[&Camera]) -> Option<(f64, f64)> {
    let meet = convergence(cameras.iter().copied())?;
    let depths: Vec<f64> = cameras.iter().map(|c| (c.w2c * meet.point).z).filter(|z| *z > 0.0).collect();
    let nearest = depths.iter().copied().fold(f64::INFINITY, f64::min);
    let farthest = depths.iter().copied().fold(0.0, f64::max);
    let far_margin = if meet.spread > OBJECT_SPREAD { OBJECT_FAR_MARGIN } else { FORWARD_FAR_MARGIN };
    (!depths.is_empty()).then_some((NEAR_MARGIN * nearest, far_margin * farthest))
}

/// `near`/`far`: each from the command line (`flags`) if given, else from the dataset, else both from the
/// views' poses ([`from_poses`]); checked as the Python loaders do
/// (`data/scene.py::check_near_far`). `from_data` is the dataset's, with where it comes from.
pub fn resolve(
    flags: (Option<f64>, Option<f64>),
    from_data: (Option<f64>, Option<f64>, DepthSource),
    cameras: &[&Camera],
    source: &Path,
) -> Result<(f64, f64, DepthSource)> {
    let (data_near, data_far, data_source) = from_data;
    let (near, far, from) = match (flags.0.or(data_near), flags.1.or(data_far)) {
        (Some(near), Some(far)) => {
            let from = if flags.0.is_some() && flags.1.is_some() { DepthSource::Flags } else { data_source };
            (near, far, from)
        }
        (near, far) => {
            let (pose_near, pose_far) = from_poses(cameras).ok_or_else(|| {
                Error::dataset(
                    source,
                    "no near/far in the dataset (COLMAP: from points3D; nerfstudio: near/far keys), and the \
                     poses do not give one (the cameras look at no common point in front of them): pass --near \
                     and --far",
                )
            })?;
            (near.unwrap_or(pose_near), far.unwrap_or(pose_far), DepthSource::Poses)
        }
    };
    if !(near.is_finite() && far.is_finite() && 0.0 <= near && near < far) {
        return Err(Error::dataset(source, format!("invalid near/far {near}/{far}: need 0 <= near < far")));
    }
    // Depths are rendered in f32: a range empty there renders NaN.
    if near as f32 >= far as f32 {
        return Err(Error::dataset(
            source,
            format!(
                "invalid near/far {near}/{far}: equal in 32-bit floating point, the precision depths are rendered in"
            ),
        ));
    }
    Ok((near, far, from))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_range_empty_in_f32_is_refused_though_not_in_f64() {
        let none = (None, None, DepthSource::Dataset);
        let err = resolve((Some(2.0), Some(2.000_000_1)), none, &[], Path::new("transforms.json")).unwrap_err();
        assert!(err.to_string().contains("32-bit"), "{err}");
        let (near, far, from) = resolve((Some(2.0), Some(2.000_001)), none, &[], Path::new("x")).unwrap();
        assert_eq!((near, far, from), (2.0, 2.000_001, DepthSource::Flags));
    }
}
