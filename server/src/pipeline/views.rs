//! The views of a scene and the choice, per target, of the ones it is rendered from.
//!
//! A scene keeps every view it was created with, decoded and padded once ([`Views`]). The model
//! renders from a fixed number of them (`config.views`, three): its encoder normalises by the
//! batch statistics of the views it encodes together (docs/bundle.md), so a view's features
//! depend on the other two, and features and cost volume are a property of the triple, built
//! and cached together (`cache::SceneCache::volume`).
//!
//! Which views ([`choose`]): pinned by the request, else for a scene of exactly three views
//! those three in upload order (view 0 the reference, as scenes always were), else MVSNeRF's
//! rule, `scnerf_capture::camera::rank_sources` (the one home of it, shared with the client):
//! the nearest by camera-centre distance, ties to the lower index, views whose optical axis is
//! 90 degrees or more from the target's left out; the nearest is the reference.

use ndarray::{ArcArray4, Axis};
use scnerf_capture::camera::{rank_sources, Viewpoint};

use crate::camera::CanonicalCamera;
use crate::error::ApiError;

/// Every view of a scene: images decoded and padded, cameras canonical.
#[derive(Debug, Clone)]
pub struct Views {
    /// (N, 3, H, W) padded source images in [0, 1].
    pub images: ArcArray4<f32>,
    pub cameras: Vec<CanonicalCamera>,
    pub near: f64,
    pub far: f64,
}

impl Views {
    pub fn len(&self) -> usize {
        self.cameras.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cameras.is_empty()
    }

    /// Memory held (for cache accounting).
    pub fn bytes(&self) -> usize {
        4 * self.images.len()
    }

    pub fn cameras_of(&self, sources: &[usize]) -> Vec<CanonicalCamera> {
        sources.iter().map(|&i| self.cameras[i].clone()).collect()
    }

    /// The images of `sources`, in that order; shared, not copied, when that is every view in
    /// upload order.
    pub fn images_of(&self, sources: &[usize]) -> ArcArray4<f32> {
        if sources.iter().copied().eq(0..self.len()) {
            return self.images.clone();
        }
        self.images.select(Axis(0), sources).into_shared()
    }
}

/// The `per_volume` views (the model's view count) that `target` is rendered from, the volume's
/// reference first: `pinned` when given, else the scene's rule (module doc). Refusals are 422
/// naming the field: `sources` / `sources[i]` for a bad pin, `target.pose.matrix` when too few
/// views face the target's way.
pub fn choose(
    cameras: &[CanonicalCamera],
    target: &CanonicalCamera,
    pinned: Option<&[u32]>,
    per_volume: usize,
) -> Result<Vec<usize>, ApiError> {
    if let Some(pinned) = pinned {
        return check_pinned(pinned, cameras.len(), per_volume);
    }
    if cameras.len() == per_volume {
        return Ok((0..per_volume).collect());
    }
    let candidates: Vec<Viewpoint> = cameras.iter().map(CanonicalCamera::viewpoint).collect();
    let ranked = rank_sources(&target.viewpoint(), &candidates);
    if ranked.len() < per_volume {
        return Err(ApiError::invalid(
            "target.pose.matrix",
            format!(
                "only {} of the scene's {} views face the target's way (optical axes less than 90 degrees \
                 apart), {per_volume} are needed: choose the views with \"sources\"",
                ranked.len(),
                cameras.len()
            ),
        ));
    }
    Ok(ranked[..per_volume].to_vec())
}

fn check_pinned(pinned: &[u32], views: usize, per_volume: usize) -> Result<Vec<usize>, ApiError> {
    if pinned.len() != per_volume {
        return Err(ApiError::invalid(
            "sources",
            format!("sources names exactly {per_volume} views (the first is the reference), got {}", pinned.len()),
        ));
    }
    for (i, &view) in pinned.iter().enumerate() {
        let field = format!("sources[{i}]");
        if view as usize >= views {
            return Err(ApiError::invalid(
                field,
                format!("view {view} is not in the scene: its views are 0 to {}", views - 1),
            ));
        }
        if pinned[..i].contains(&view) {
            return Err(ApiError::invalid(field, format!("view {view} is named twice")));
        }
    }
    Ok(pinned.iter().map(|&v| v as usize).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Matrix4, Point3, Vector3, Vector4};

    /// A camera at `eye` looking at `at` (OpenCV axes, world up +z).
    fn looking(eye: [f64; 3], at: [f64; 3]) -> CanonicalCamera {
        let iso = nalgebra::Isometry3::look_at_rh(&Point3::from(eye), &Point3::from(at), &Vector3::z());
        // look_at_rh looks down its -z, with y up: flip y and z for OpenCV's axes.
        let flip = Matrix4::from_diagonal(&Vector4::new(1.0, -1.0, -1.0, 1.0));
        let k = Matrix3::new(8.0, 0.0, 4.0, 0.0, 8.0, 3.0, 0.0, 0.0, 1.0);
        CanonicalCamera { width: 8, height: 6, k, w2c: flip * iso.to_homogeneous() }
    }

    /// `n` views on a circle of radius 4 around the origin (view 0 on +x), looking at it. (The
    /// rule's own cases, ties and exactly 90 degrees, are tested exactly in scnerf-capture.)
    fn ring(n: u32) -> Vec<CanonicalCamera> {
        (0..n)
            .map(|k| {
                let a = std::f64::consts::TAU * f64::from(k) / f64::from(n);
                looking([4.0 * a.cos(), 4.0 * a.sin(), 1.0], [0.0; 3])
            })
            .collect()
    }

    #[test]
    fn nearest_views_are_chosen_nearest_first() {
        let views = ring(8);
        // At 100 degrees: view 2 (90), then 3 (135), then 1 (45).
        let a = 100f64.to_radians();
        let target = looking([4.0 * a.cos(), 4.0 * a.sin(), 1.0], [0.0; 3]);
        assert_eq!(choose(&views, &target, None, 3).unwrap(), vec![2, 3, 1]);
        assert_eq!(choose(&views, &views[6], None, 3).unwrap()[0], 6);
    }

    #[test]
    fn views_facing_away_are_left_out() {
        let views = ring(6);
        // Beside view 0 but looking outwards (+x): views 0, 1, 5 look the other way; of 2, 3, 4
        // the nearest first, though all are farther than those three.
        let outwards = looking([3.0, 0.5, 1.0], [10.0, 0.5, 1.0]);
        assert_eq!(choose(&views, &outwards, None, 3).unwrap(), vec![2, 4, 3]);
        let err = choose(&views[..4], &outwards, None, 3).unwrap_err();
        assert_eq!((err.status().as_u16(), err.field()), (422, Some("target.pose.matrix")));
        assert!(err.to_string().contains("only 2 of the scene's 4 views face the target's way"), "{err}");
    }

    #[test]
    fn three_views_keep_their_upload_order_and_pins_win() {
        let views = ring(8);
        assert_eq!(choose(&views[..3], &views[2], None, 3).unwrap(), vec![0, 1, 2]);
        assert_eq!(choose(&views, &views[2], Some(&[7, 0, 4]), 3).unwrap(), vec![7, 0, 4]);
    }

    #[test]
    fn bad_pins_name_the_field() {
        let views = ring(8);
        let field = |pinned: &[u32]| {
            let e = choose(&views, &views[0], Some(pinned), 3).unwrap_err();
            (e.status().as_u16(), e.field().map(str::to_string))
        };
        assert_eq!(field(&[0, 1]), (422, Some("sources".into())));
        assert_eq!(field(&[0, 1, 2, 3]), (422, Some("sources".into())));
        assert_eq!(field(&[0, 8, 2]), (422, Some("sources[1]".into())));
        assert_eq!(field(&[0, 1, 0]), (422, Some("sources[2]".into())));
    }

    #[test]
    fn images_of_a_subset_are_in_its_order() {
        let images = ndarray::Array4::from_shape_fn((4, 3, 2, 2), |(v, _, _, _)| v as f32).into_shared();
        let views = Views { images, cameras: ring(8)[..4].to_vec(), near: 1.0, far: 2.0 };
        let picked = views.images_of(&[3, 0, 2]);
        assert_eq!(picked.shape(), &[3, 3, 2, 2]);
        assert_eq!(picked.index_axis(Axis(0), 0)[[0, 0, 0]], 3.0);
        assert_eq!(picked.index_axis(Axis(0), 2)[[0, 0, 0]], 2.0);
        assert_eq!(views.images_of(&[0, 1, 2, 3]).as_ptr(), views.images.as_ptr(), "shared, not copied");
    }
}
