//! The plane sweep: the cost volume, a row of one depth plane at a time, computed here rather than
//! in a graph (docs/bundle.md, "cost_conv.onnx"). For each fronto-parallel plane of the reference
//! view (view 0) and each source view, a homography takes every cell of the padded reference
//! feature grid to a point of the source's feature grid; the point's four bilinear taps are
//! computed once and read for all 35 channels (the quarter-size image and the 32 features), which
//! are stored channels last. A cell's cost is `[images of every view warped onto it (3V),
//! variance of the features over the views (C)]`.
//!
//! It computes `build_cost_volume` of the exporter (PyTorch's definition, `grid_sample` with
//! `align_corners=True` and zero padding) with the same float32 formulas in the same order; the
//! exporter's `runtime/plane_sweep.py` is this module in numpy. ONNX Runtime's GridSample computed
//! the taps once per channel and wrote the warped features of every view before their variance.

use ndarray::{s, Array4, ArrayView2, ArrayView3, ArrayView4, Axis};

/// The image channels of the cost volume are ImageNet-normalised (as the encoder's input).
const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// What the sweep reads, prepared once per volume.
pub struct PlaneSweep {
    /// Per view, each cell's quarter-size normalised image and then its features, channels last:
    /// (V, h, w, 3 + C), so that a tap reads all channels of a cell at once.
    maps: Array4<f32>,
    /// Per source view (views 1..V), `[R | t]`: source pixel·depth = R·[x, y, 1] + t / z for the
    /// reference cell (x, y) of the plane at depth z.
    homographies: Vec<[[f32; 4]; 3]>,
    pad: usize,
}

impl PlaneSweep {
    /// `features` (V, C, h, w), `images` (V, 3, 4h, 4w) in [0, 1], `projections` (V, 4, 4) onto
    /// the feature grid.
    pub fn new(features: ArrayView4<f32>, images: ArrayView4<f32>, projections: ArrayView3<f32>, pad: usize) -> Self {
        let (views, channels, h, w) = features.dim();
        let mut maps = Array4::zeros((views, h, w, 3 + channels));
        maps.slice_mut(s![.., .., .., ..3]).assign(&quarter_images(images, h, w).permuted_axes([0, 2, 3, 1]));
        maps.slice_mut(s![.., .., .., 3..]).assign(&features.permuted_axes([0, 2, 3, 1]));
        let reference = affine_inverse(projections.index_axis(Axis(0), 0));
        let homographies =
            (1..views).map(|i| relative_homography(projections.index_axis(Axis(0), i), &reference)).collect();
        PlaneSweep { maps, homographies, pad }
    }

    /// Channels of the cost volume: three per view's image, then the features' variance.
    pub fn cost_channels(&self) -> usize {
        let (views, _, _, stride) = self.maps.dim();
        3 * views + stride - 3
    }

    /// Size of the padded grid (Hp, Wp): the feature grid with `pad` cells on each side.
    pub fn grid(&self) -> (usize, usize) {
        let (_, h, w, _) = self.maps.dim();
        (h + 2 * self.pad, w + 2 * self.pad)
    }

    /// Per-thread buffers of `cost_row`.
    pub fn scratch(&self) -> CellScratch {
        let stride = self.maps.dim().3;
        let (total, squares, warped) = (vec![0.0; stride - 3], vec![0.0; stride - 3], vec![0.0; stride]);
        CellScratch { total, squares, warped, shifts: Vec::new() }
    }

    /// Row `y` of the padded grid on the plane at `depth`: each cell's cost, channels last, in
    /// `row` (Wp · (3V + C) values).
    pub fn cost_row(&self, depth: f32, y: usize, row: &mut [f32], scratch: &mut CellScratch) {
        scratch.shifts.clear();
        scratch.shifts.extend(self.homographies.iter().map(|m| m.map(|r| r[3] / depth)));
        for (x, cost) in row.chunks_exact_mut(self.cost_channels()).enumerate() {
            self.cell(x, y, cost, scratch);
        }
    }

    /// The cost of cell (x, y) of the padded grid on the plane whose homographies' translations
    /// divided by its depth are `scratch.shifts`, channels last.
    fn cell(&self, x: usize, y: usize, cost: &mut [f32], scratch: &mut CellScratch) {
        let views = self.homographies.len() + 1;
        let (images, variance) = cost.split_at_mut(3 * views);
        let mut seen = match self.reference_cell(x, y) {
            Some(reference) => {
                images[..3].copy_from_slice(&reference[..3]);
                scratch.total.copy_from_slice(&reference[3..]);
                scratch.squares.iter_mut().zip(&reference[3..]).for_each(|(q, &f)| *q = f * f);
                true
            }
            None => {
                images[..3].fill(0.0);
                scratch.total.fill(0.0);
                scratch.squares.fill(0.0);
                false
            }
        };
        let mut count = 1.0;
        let (px, py) = (x as f32 - self.pad as f32, y as f32 - self.pad as f32);
        for (v, (m, shift)) in self.homographies.iter().zip(&scratch.shifts).enumerate() {
            let (taps, inside) = self.taps(m, shift, px, py);
            if inside {
                count += 1.0;
            }
            let image = &mut images[3 * (v + 1)..3 * (v + 2)];
            if taps.weight == [0.0; 4] {
                // The cell sees nothing of the view: its zeros would add nothing.
                image.fill(0.0);
                continue;
            }
            seen = true;
            taps.read(self.maps.index_axis(Axis(0), v + 1).as_slice().expect("contiguous"), &mut scratch.warped);
            image.copy_from_slice(&scratch.warped[..3]);
            let warped = &scratch.warped[3..];
            for ((t, q), &f) in scratch.total.iter_mut().zip(scratch.squares.iter_mut()).zip(warped) {
                *t += f;
                *q += f * f;
            }
        }
        if !seen {
            // In the padding, seen by no view (a quarter of the cells at paper size): all zeros.
            variance.fill(0.0);
            return;
        }
        for ((out, &t), &q) in variance.iter_mut().zip(&scratch.total).zip(&scratch.squares) {
            let mean = t / count;
            *out = q / count - mean * mean;
        }
    }

    /// The reference view's channels at cell (x, y) of the padded grid (`None` in the padding,
    /// where they are zeros).
    fn reference_cell(&self, x: usize, y: usize) -> Option<&[f32]> {
        let (_, h, w, stride) = self.maps.dim();
        let (col, row) = (x.checked_sub(self.pad)?, y.checked_sub(self.pad)?);
        let map = self.maps.as_slice().expect("contiguous");
        (col < w && row < h).then(|| &map[(row * w + col) * stride..][..stride])
    }

    /// The taps of reference cell (px, py) (unpadded grid coordinates) in the source view of
    /// homography `m` on the plane where its translation over the depth is `shift`, and whether
    /// the point falls strictly inside the source's grid.
    fn taps(&self, m: &[[f32; 4]; 3], shift: &[f32; 3], px: f32, py: f32) -> (Taps, bool) {
        let (_, h, w, _) = self.maps.dim();
        let (half_w, half_h) = ((w - 1) as f32 / 2.0, (h - 1) as f32 / 2.0);
        let [u, v, z] = std::array::from_fn(|k| m[k][0] * px + m[k][1] * py + m[k][2] + shift[k]);
        let (gx, gy) = (u / z / half_w - 1.0, v / z / half_h - 1.0);
        let inside = gx > -1.0 && gx < 1.0 && gy > -1.0 && gy < 1.0;
        (Taps::at((gx + 1.0) * half_w, (gy + 1.0) * half_h, h, w), inside)
    }
}

/// Per-thread buffers of `PlaneSweep::cost_row`: one cell's sums over the views, one view's
/// warped channels, and the plane's translations over its depth.
pub struct CellScratch {
    total: Vec<f32>,
    squares: Vec<f32>,
    warped: Vec<f32>,
    shifts: Vec<[f32; 3]>,
}

/// The bilinear taps of a point of an h x w map: cell indices and weights of its north-west,
/// north-east, south-west and south-east neighbours. A neighbour outside the map reads cell 0
/// with weight 0 (`grid_sample` reads a zero there: the same sum).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Taps {
    index: [u32; 4],
    weight: [f32; 4],
}

impl Taps {
    /// At map coordinates (x, y) (pixel centres at integers), as `grid_sample`'s CPU kernel.
    fn at(x: f32, y: f32, h: usize, w: usize) -> Taps {
        let (x_w, y_n) = (x.floor(), y.floor());
        let (e, n) = (x - x_w, y - y_n);
        let (west, s) = (1.0 - e, 1.0 - n);
        let weights = [s * west, s * e, n * west, n * e];
        let mut taps = Taps::default();
        for (k, (dy, dx)) in [(0.0, 0.0), (0.0, 1.0), (1.0, 0.0), (1.0, 1.0)].into_iter().enumerate() {
            let (col, row) = (x_w + dx, y_n + dy);
            // NaN (a point at infinity) fails every comparison: no tap.
            if col >= 0.0 && col <= (w - 1) as f32 && row >= 0.0 && row <= (h - 1) as f32 {
                taps.index[k] = (row as usize * w + col as usize) as u32;
                taps.weight[k] = weights[k];
            }
        }
        taps
    }

    /// The channels of a channels-last map (cells of `out.len()` channels) at the taps.
    fn read(&self, map: &[f32], out: &mut [f32]) {
        let stride = out.len();
        let [a, b, c, d] = self.index.map(|i| &map[i as usize * stride..][..stride]);
        let [wa, wb, wc, wd] = self.weight;
        for ((((o, &a), &b), &c), &d) in out.iter_mut().zip(a).zip(b).zip(c).zip(d) {
            *o = a * wa + b * wb + c * wc + d * wd;
        }
    }
}

/// (V, 3, H, W) images in [0, 1] -> (V, 3, h, w): ImageNet-normalised, then bilinear at a quarter
/// of the size (`F.interpolate(align_corners=False)`: each cell the mean of pixels 1 and 2 of its
/// 4 x 4 block in both directions, summed in PyTorch's order for large images).
fn quarter_images(images: ArrayView4<f32>, h: usize, w: usize) -> Array4<f32> {
    let views = images.dim().0;
    Array4::from_shape_fn((views, 3, h, w), |(v, c, y, x)| {
        let at = |dy: usize, dx: usize| (images[[v, c, 4 * y + dy, 4 * x + dx]] - IMAGENET_MEAN[c]) / IMAGENET_STD[c];
        ((at(1, 1) + at(1, 2)) + (at(2, 1) + at(2, 2))) * 0.25
    })
}

/// The inverse of `[[A, b], [0, 1]]` by A's adjugate, in float32 (as the exporter's
/// `affine_inverse`).
fn affine_inverse(m: ArrayView2<f32>) -> [[f32; 4]; 4] {
    let row = |i: usize| [m[[i, 0]], m[[i, 1]], m[[i, 2]]];
    let (r0, r1, r2) = (row(0), row(1), row(2));
    let cofactor_t = [cross(r1, r2), cross(r2, r0), cross(r0, r1)]; // columns of adj(A)
    let c = cofactor_t[0];
    let det = r0[0] * c[0] + r0[1] * c[1] + r0[2] * c[2];
    let a: [[f32; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| cofactor_t[j][i] / det));
    let b = a.map(|r| -(r[0] * m[[0, 3]] + r[1] * m[[1, 3]] + r[2] * m[[2, 3]]));
    std::array::from_fn(|i| match i {
        3 => [0.0, 0.0, 0.0, 1.0],
        _ => [a[i][0], a[i][1], a[i][2], b[i]],
    })
}

fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// Rows 0..3 of `projection · reference_inverse`.
fn relative_homography(projection: ArrayView2<f32>, reference_inverse: &[[f32; 4]; 4]) -> [[f32; 4]; 3] {
    std::array::from_fn(|i| {
        std::array::from_fn(|j| (0..4).fold(0.0, |sum, k| sum + projection[[i, k]] * reference_inverse[k][j]))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    #[test]
    fn taps_weigh_the_four_neighbours_and_drop_those_outside() {
        let t = Taps::at(1.25, 2.5, 4, 5);
        assert_eq!(t.index, [11, 12, 16, 17]);
        assert_eq!(t.weight, [0.375, 0.125, 0.375, 0.125]);
        // On the last column: the east neighbours are outside.
        let t = Taps::at(4.0, 0.0, 4, 5);
        assert_eq!((t.index, t.weight), ([4, 0, 9, 0], [1.0, 0.0, 0.0, 0.0]));
        // Far outside, or at infinity: nothing.
        assert_eq!(Taps::at(-3.0, 1.0, 4, 5), Taps::default());
        assert_eq!(Taps::at(f32::NAN, 1.0, 4, 5), Taps::default());
        assert_eq!(Taps::at(f32::INFINITY, 1.0, 4, 5), Taps::default());
    }

    #[test]
    fn the_affine_inverse_inverts() {
        let m =
            ndarray::arr2(&[[2.0, 0.5, 0.0, 1.0], [0.0, 1.0, 0.25, -2.0], [0.5, 0.0, 4.0, 3.0], [0.0, 0.0, 0.0, 1.0]]);
        let inverse = affine_inverse(m.view());
        let inverse = Array3::from_shape_fn((1, 4, 4), |(_, i, j)| inverse[i][j]);
        let product = m.dot(&inverse.index_axis(Axis(0), 0));
        for ((i, j), v) in product.indexed_iter() {
            assert!((v - if i == j { 1.0 } else { 0.0 }).abs() < 1e-6, "{product}");
        }
    }

    /// A reference view and two sources that are the same camera: every plane maps each cell
    /// onto itself, so the sources' warped maps are the reference's and the variance is 0 where
    /// the cells fall strictly inside the grid; in the padding the reference reads 0 and the
    /// sources nothing.
    #[test]
    fn identical_views_have_no_variance_and_their_own_images() {
        let (h, w, pad) = (4, 6, 2);
        let features = Array4::from_shape_fn((3, 2, h, w), |(_, c, y, x)| (c * 31 + y * 7 + x) as f32 * 0.1);
        let images = Array4::from_shape_fn((3, 3, 4 * h, 4 * w), |(_, c, y, x)| ((c + y + 2 * x) % 11) as f32 / 10.0);
        let projection = [[2.0, 0.0, 1.0, 0.5], [0.0, 2.0, 1.5, -0.25], [0.0, 0.0, 1.0, 0.125], [0.0, 0.0, 0.0, 1.0]];
        let projections = Array3::from_shape_fn((3, 4, 4), |(_, i, j)| projection[i][j] as f32);
        let sweep = PlaneSweep::new(features.view(), images.view(), projections.view(), pad);
        assert_eq!((sweep.cost_channels(), sweep.grid()), (11, (h + 4, w + 4)));
        let mut scratch = sweep.scratch();
        let mut row = vec![f32::NAN; (w + 4) * 11];
        for depth in [2.0, 3.0] {
            sweep.cost_row(depth, 0, &mut row, &mut scratch);
            assert!(row.iter().all(|&v| v == 0.0), "the padding reads zeros");
            for y in pad + 1..pad + h - 1 {
                sweep.cost_row(depth, y, &mut row, &mut scratch);
                for x in pad + 1..pad + w - 1 {
                    let cost = &row[x * 11..(x + 1) * 11];
                    let own = sweep.maps.slice(s![0, y - pad, x - pad, ..3]);
                    for v in 0..3 {
                        let diff = (&ndarray::aview1(&cost[3 * v..3 * v + 3]) - &own).mapv(f32::abs);
                        assert!(diff.iter().all(|&d| d < 1e-5), "view {v} at ({x}, {y}): {diff}");
                    }
                    assert!(cost[9..].iter().all(|&v| v.abs() < 1e-4), "variance at ({x}, {y}): {cost:?}");
                }
            }
        }
    }
}
