//! G2's last step, when `volume_net.onnx` leaves it to the server (`VolumeTail::Server`,
//! docs/bundle.md): per channel c,
//!
//! `V = σ(conv0·skip_affine[0,c] + skip_affine[1,c]) + σ(interleave(phases)·phases_affine[0,c] + phases_affine[1,c])`
//!
//! with σ the leaky ReLU and `interleave` placing phase `8c + 4i + 2j + k` at the cells
//! (2z + i, 2y + j, 2x + k). One pass over the volume, written into `conv0`'s buffer, which the
//! run no longer needs: in ONNX Runtime each operator of the sum wrote a new tensor of the
//! volume's size.

use ndarray::{s, ArrayView2, ArrayView4, ArrayViewMut4, Axis, Ix2, Ix5};

use crate::backend::{BackendError, NamedTensors, Outputs};
use crate::bundle::GraphKind;

/// The volume from a `volume_net` run: its input `conv0` (1, C, D, Hp, Wp), taken back from
/// `inputs`, and the parts the graph output. `threads` threads each take a share of the planes.
pub fn finish(
    inputs: NamedTensors,
    mut outputs: Outputs,
    slope: f32,
    threads: usize,
) -> Result<NamedTensors, BackendError> {
    let bad = |message: String| BackendError::BadOutput { graph: GraphKind::VolumeNet, message };
    let conv0 =
        inputs.into_iter().find(|(name, _)| name == "conv0").map(|(_, t)| t).ok_or_else(|| bad("no conv0".into()))?;
    let mut volume = conv0.into_owned().into_dimensionality::<Ix5>().map_err(|e| bad(format!("conv0: {e}")))?;
    let (_, c, d, hp, wp) = volume.dim();
    if d % 2 + hp % 2 + wp % 2 != 0 {
        return Err(bad(format!("conv0 has shape {:?}: sub-pixel phases need even sizes", volume.shape())));
    }
    let phase_shape = [Some(1), Some(8 * c), Some(d / 2), Some(hp / 2), Some(wp / 2)];
    let phases = outputs.take::<Ix5>("phases", &phase_shape)?;
    let skip = outputs.take::<Ix2>("skip_affine", &[Some(2), Some(c)])?;
    let up = outputs.take::<Ix2>("phases_affine", &[Some(2), Some(c)])?;
    let tail = Tail { phases: phases.index_axis(Axis(0), 0), skip: skip.view(), up: up.view(), slope };
    tail.add_into(volume.index_axis_mut(Axis(0), 0), threads);
    Ok(vec![("volume".into(), volume.into_shared().into_dyn())])
}

/// What the last step reads besides conv0.
struct Tail<'a> {
    /// (8·C, D/2, Hp/2, Wp/2).
    phases: ArrayView4<'a, f32>,
    skip: ArrayView2<'a, f32>,
    up: ArrayView2<'a, f32>,
    slope: f32,
}

impl Tail<'_> {
    /// Turns conv0 (C, D, Hp, Wp) into the volume, planes split between `threads` threads.
    fn add_into(&self, mut conv0: ArrayViewMut4<f32>, threads: usize) {
        let planes = conv0.len_of(Axis(1)).div_ceil(threads.max(1)).max(1);
        std::thread::scope(|scope| {
            for (i, share) in conv0.axis_chunks_iter_mut(Axis(1), planes).enumerate() {
                scope.spawn(move || self.add_into_planes(share, i * planes));
            }
        });
    }

    /// The planes `first..` of conv0 (C, planes, Hp, Wp).
    fn add_into_planes(&self, mut planes: ArrayViewMut4<f32>, first: usize) {
        let slope = self.slope;
        let activated = move |x: f32| if x > 0.0 { x } else { x * slope };
        for (c, mut channel) in planes.outer_iter_mut().enumerate() {
            let (a0, b0, a1, b1) = (self.skip[[0, c]], self.skip[[1, c]], self.up[[0, c]], self.up[[1, c]]);
            for (dz, mut plane) in channel.outer_iter_mut().enumerate() {
                let z = first + dz;
                for (y, mut row) in plane.outer_iter_mut().enumerate() {
                    let phase = 8 * c + 4 * (z % 2) + 2 * (y % 2);
                    let even = self.phases.slice(s![phase, z / 2, y / 2, ..]);
                    let odd = self.phases.slice(s![phase + 1, z / 2, y / 2, ..]);
                    let cells = row.as_slice_mut().expect("conv0 in standard layout");
                    let phase_cells = even.iter().zip(odd.iter());
                    for (pair, (&e, &o)) in cells.chunks_exact_mut(2).zip(phase_cells) {
                        pair[0] = activated(pair[0] * a0 + b0) + activated(e * a1 + b1);
                        pair[1] = activated(pair[1] * a0 + b0) + activated(o * a1 + b1);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use ndarray::{Array2, Array5};

    use super::*;

    fn leaky(x: f32, slope: f32) -> f32 {
        if x > 0.0 {
            x
        } else {
            x * slope
        }
    }

    /// Each cell from its definition: the phase of its parities, the affine maps of its channel.
    #[test]
    fn every_cell_is_the_sum_of_its_two_activated_norms() {
        let (c, d, h, w, slope) = (3, 4, 6, 8, 0.1);
        let conv0 = Array5::from_shape_fn((1, c, d, h, w), |(_, c, z, y, x)| {
            ((c * 31 + z * 7 + y * 5 + x * 3) % 17) as f32 - 8.0
        });
        let phases = Array5::from_shape_fn((1, 8 * c, d / 2, h / 2, w / 2), |(_, p, z, y, x)| {
            ((p * 13 + z * 11 + y * 3 + x * 2) % 19) as f32 - 9.0
        });
        let skip = Array2::from_shape_fn((2, c), |(r, c)| if r == 0 { 0.5 + c as f32 } else { -1.0 + c as f32 });
        let up = Array2::from_shape_fn((2, c), |(r, c)| if r == 0 { 2.0 - c as f32 } else { 0.25 * c as f32 });
        let outputs = vec![
            ("phases".to_string(), phases.to_shared().into_dyn()),
            ("skip_affine".to_string(), skip.to_shared().into_dyn()),
            ("phases_affine".to_string(), up.to_shared().into_dyn()),
        ];
        for threads in [1, 3] {
            let inputs = vec![("conv0".to_string(), conv0.to_shared().into_dyn())];
            let mut got = finish(inputs, Outputs::new(GraphKind::VolumeNet, outputs.clone()), slope, threads).unwrap();
            let (name, volume) = got.remove(0);
            assert_eq!((name.as_str(), volume.shape()), ("volume", conv0.shape()));
            for ((_, ch, z, y, x), &v) in volume.into_dimensionality::<Ix5>().unwrap().indexed_iter() {
                let phase = 8 * ch + 4 * (z % 2) + 2 * (y % 2) + x % 2;
                let skip_term = leaky(conv0[[0, ch, z, y, x]] * skip[[0, ch]] + skip[[1, ch]], slope);
                let up_term = leaky(phases[[0, phase, z / 2, y / 2, x / 2]] * up[[0, ch]] + up[[1, ch]], slope);
                assert_eq!(v, skip_term + up_term, "cell ({ch}, {z}, {y}, {x}) with {threads} threads");
            }
        }
    }

    #[test]
    fn phases_of_the_wrong_shape_are_a_bad_output() {
        let conv0 = Array5::<f32>::zeros((1, 2, 4, 4, 4));
        let outputs = vec![
            ("phases".to_string(), Array5::<f32>::zeros((1, 16, 2, 2, 3)).into_shared().into_dyn()),
            ("skip_affine".to_string(), Array2::<f32>::zeros((2, 2)).into_shared().into_dyn()),
            ("phases_affine".to_string(), Array2::<f32>::zeros((2, 2)).into_shared().into_dyn()),
        ];
        let inputs = vec![("conv0".to_string(), conv0.into_shared().into_dyn())];
        let err = finish(inputs, Outputs::new(GraphKind::VolumeNet, outputs), 0.01, 2).unwrap_err();
        assert!(matches!(&err, BackendError::BadOutput { message, .. } if message.contains("\"phases\"")), "{err}");
    }
}
