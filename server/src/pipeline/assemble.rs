//! Final image assembly: `rgb + (1 − opacity)·background`, clamped to [0, 1]; 8-bit by
//! round(255·x) (ties to even, like numpy).

use ndarray::{Array2, ArrayView1, Axis};

use super::chunks::RawView;

/// (N, 3) colours composited on `background`.
pub fn composite(raw: &RawView, background: [f32; 3]) -> Array2<f32> {
    let transparency = (1.0 - &raw.opacity).insert_axis(Axis(1));
    let background = ArrayView1::from(&background);
    (&raw.rgb + &(transparency * background)).mapv_into(|x| x.clamp(0.0, 1.0))
}

pub fn quantize<'a>(rgb: impl IntoIterator<Item = &'a f32>) -> Vec<u8> {
    rgb.into_iter().map(|&x| (x * 255.0).round_ties_even().clamp(0.0, 255.0) as u8).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{arr1, arr2};

    #[test]
    fn composites_and_quantises() {
        let raw = RawView {
            rgb: arr2(&[[0.5, 0.0, 0.0], [0.2, 0.2, 0.2]]),
            depth: arr1(&[1.0, 2.0]),
            opacity: arr1(&[0.5, 1.0]),
        };
        let rgb = composite(&raw, [1.0, 1.0, 0.0]);
        assert_eq!(rgb, arr2(&[[1.0, 0.5, 0.0], [0.2, 0.2, 0.2]]));
        assert_eq!(quantize(&rgb), vec![255, 128, 0, 51, 51, 51]);
        assert_eq!(quantize(&[1.5, -0.1]), vec![255, 0]);
    }
}
