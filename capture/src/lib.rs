//! What the `scnerf` client and `scnerf-server` share about captures of posed photos: the
//! canonical camera conventions and MVSNeRF's source-ranking rule ([`camera`]), the API's JSON
//! camera ([`wire`]), the dataset readers ([`readers`]) over a folder on disk or an in-memory set
//! of files ([`files`]), which image set of a capture to read ([`image_sets`]), how its photos
//! are read ([`images`]), lens distortion ([`undistort`]), the depth range a capture's poses give
//! ([`depth_range`]), the image and camera sent for a view ([`upload`]), which files of a capture
//! folder a client sends ([`plan`]), and the policy that thins a capture to a view budget
//! ([`thin_evenly`]).

pub mod camera;
pub mod depth_range;
mod error;
pub mod files;
pub mod image_sets;
pub mod images;
pub mod plan;
pub mod readers;
pub mod undistort;
pub mod upload;
pub mod wire;

pub use error::{Error, Result};

/// numpy's default (linear) percentile `q` in [0, 100] of sorted values.
pub fn percentile(sorted: &[f64], q: f64) -> f64 {
    let pos = q / 100.0 * (sorted.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = (lo + 1).min(sorted.len() - 1);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

/// Indices of at most `max` (>= 2) of `count` items, evenly spread over their order, first and
/// last included: how a capture larger than a scene's view budget is thinned (the client before
/// uploading, the server for `POST /v1/captures`).
pub fn thin_evenly(count: usize, max: usize) -> Vec<usize> {
    if count <= max {
        return (0..count).collect();
    }
    let max = max.max(2);
    (0..max).map(|i| (i * (count - 1) + (max - 1) / 2) / (max - 1)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentile_is_numpys_linear_rule() {
        // np.percentile([1, 2, 3, 4, 10], [1, 90, 99]) = [1.04, 7.6, 9.76]
        let v = [1.0, 2.0, 3.0, 4.0, 10.0];
        assert!((percentile(&v, 1.0) - 1.04).abs() < 1e-12);
        assert!((percentile(&v, 90.0) - 7.6).abs() < 1e-12);
        assert!((percentile(&v, 99.0) - 9.76).abs() < 1e-12);
    }

    #[test]
    fn thinning_keeps_the_ends_and_spreads_the_rest() {
        assert_eq!(thin_evenly(20, 3), vec![0, 10, 19]);
        assert_eq!(thin_evenly(20, 5), vec![0, 5, 10, 14, 19]);
        assert_eq!(thin_evenly(20, 64), (0..20).collect::<Vec<_>>());
    }
}
