//! Final image assembly: `rgb + (1 − opacity)·background`, clamped to [0, 1]; 8-bit by
//! round(255·x) (ties to even, like numpy).

use super::chunks::RawView;

pub fn composite(raw: &RawView, background: [f32; 3]) -> Vec<f32> {
    raw.rgb
        .chunks_exact(3)
        .zip(&raw.opacity)
        .flat_map(|(rgb, &a)| (0..3).map(move |c| (rgb[c] + (1.0 - a) * background[c]).clamp(0.0, 1.0)))
        .collect()
}

pub fn quantize(rgb: &[f32]) -> Vec<u8> {
    rgb.iter().map(|&x| (x * 255.0).round_ties_even().clamp(0.0, 255.0) as u8).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn composites_and_quantises() {
        let raw = RawView { rgb: vec![0.5, 0.0, 0.0, 0.2, 0.2, 0.2], depth: vec![1.0, 2.0], opacity: vec![0.5, 1.0] };
        let rgb = composite(&raw, [1.0, 1.0, 0.0]);
        assert_eq!(rgb, vec![1.0, 0.5, 0.0, 0.2, 0.2, 0.2]);
        assert_eq!(quantize(&rgb), vec![255, 128, 0, 51, 51, 51]);
        assert_eq!(quantize(&[1.5, -0.1]), vec![255, 0]);
    }
}
