//! G2's first convolution (3x3x3, no bias, zero padding) over the cost volume, computed here and
//! fused with the plane sweep (`pipeline::sweep`): the cost volume never exists as a whole, only
//! one row of one plane per thread at a time.
//!
//! Each row of a plane, channels last with one cell of zeros at each end, is read in windows of
//! three cells (3·C values, consecutive in memory) and multiplied by the kernel, whose rows are the
//! 9 (dz, dy) taps times the output channels: the product gives the row's terms of the three
//! output planes and three output rows it reaches, added into place. One product takes 8 rows laid
//! end to end, cut to the cells that hold anything (`Band`). The products run in `matrixmultiply`
//! (through ndarray) with the CPU's widest vectors, chosen at run time; ONNX Runtime's 3-D
//! convolution copied every cost value 27 times before a product with 8 output channels.
//!
//! The kernel comes from the bundle's `cost_conv.onnx` (the convolution as a graph, what ONNX
//! Runtime runs in the exporter's pipeline): [`probe`] is an input of impulses whose output is the
//! kernel, and [`FirstConvolution::check`] compares the two on another input before the kernel is
//! used.

use std::ops::Range;

use ndarray::linalg::general_mat_mul;
use ndarray::{s, Array2, Array5, ArrayView2, ArrayView5, ArrayViewMut4, Axis, ShapeBuilder};

/// The spacing of the probe's impulses: each impulse's response covers the 3 x 3 cells around it,
/// so impulses 3 cells apart do not overlap.
const PROBE_SPACING: usize = 3;

/// The first convolution, its kernel laid out for products with rows of the cost.
#[derive(Debug, Clone)]
pub struct FirstConvolution {
    /// (9·Co, 3·C): row (dz, dy, o), column (dx, c) holds weight[o, c, dz, dy, dx].
    kernel: Array2<f32>,
    outputs: usize,
    channels: usize,
}

impl FirstConvolution {
    /// From the weight (Co, C, 3, 3, 3).
    pub fn new(weight: ArrayView5<f32>) -> FirstConvolution {
        let (outputs, channels, _, _, _) = weight.dim();
        let kernel = Array2::from_shape_fn((9 * outputs, 3 * channels), |(row, col)| {
            let (dz, dy, o) = (row / (3 * outputs), row / outputs % 3, row % outputs);
            weight[[o, col % channels, dz, dy, col / channels]]
        });
        FirstConvolution { kernel, outputs, channels }
    }

    /// From the output of the convolution graph on [`probe`]`(channels)`: (1, Co, 1, Hp, Wp).
    pub fn from_probe(response: ArrayView5<f32>, channels: usize) -> FirstConvolution {
        let outputs = response.dim().1;
        let weight = Array5::from_shape_fn((outputs, channels, 3, 3, 3), |(o, c, dz, dy, dx)| {
            let (y, x) = impulse_at(c * 3 + dz, channels);
            response[[0, o, 0, y + 1 - dy, x + 1 - dx]]
        });
        FirstConvolution::new(weight.view())
    }

    pub fn outputs(&self) -> usize {
        self.outputs
    }

    /// The convolution of a cost volume (1, C, D, Hp, Wp), not padded along the planes:
    /// (1, Co, D − 2, Hp, Wp), as the graph's output for a slab with its halo.
    pub fn of_cost(&self, cost: ArrayView5<f32>) -> Array5<f32> {
        let (_, channels, planes, hp, wp) = cost.dim();
        assert_eq!(channels, self.channels, "the cost's channels");
        let mut out = Array5::zeros((1, self.outputs, planes, hp, wp));
        let mut rows = |p: usize, y: usize, row: &mut [f32]| {
            row.iter_mut().zip(cost.slice(s![0, .., p, y, ..]).t().iter()).for_each(|(r, &v)| *r = v);
        };
        self.accumulate(0..planes, out.index_axis_mut(Axis(0), 0), 0, hp, &mut rows);
        out.slice_move(s![.., .., 1..planes - 1, .., ..])
    }

    /// Whether the graph's output `graph` on `cost` is this convolution's (to float rounding).
    pub fn check(&self, cost: ArrayView5<f32>, graph: ArrayView5<f32>) -> Result<(), String> {
        let mine = self.of_cost(cost);
        if mine.dim() != graph.dim() {
            return Err(format!("output of shape {:?}, expected {:?}", graph.dim(), mine.dim()));
        }
        let scale = graph.iter().fold(1.0f32, |m, v| m.max(v.abs()));
        let error = mine.iter().zip(&graph).fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        // A reordered sum of ~1000 float32 terms differs by ~1e-6 of the largest.
        if error.is_finite() && error <= 1e-4 * scale {
            Ok(())
        } else {
            Err(format!("differs from a 3x3x3 convolution without bias by {error:e} (outputs up to {scale:e})"))
        }
    }

    /// Adds the terms of input planes `planes` to `out`, (Co, D, rows, Wp): output rows
    /// `first_row..` of a grid of `grid_rows` rows, zero-padded along every axis. `rows(p, y, row)`
    /// writes row y of input plane p channels last (Wp·C values).
    pub fn accumulate(
        &self,
        planes: Range<usize>,
        mut out: ArrayViewMut4<f32>,
        first_row: usize,
        grid_rows: usize,
        rows: &mut dyn FnMut(usize, usize, &mut [f32]),
    ) {
        let (outputs, depth, out_rows, wp) = out.dim();
        let c = self.channels;
        let output_rows = first_row..first_row + out_rows;
        let input_rows = first_row.saturating_sub(1)..(output_rows.end + 1).min(grid_rows);
        let mut row = vec![0.0; wp * c];
        let mut band = Band::new(wp, c);
        let mut terms = Array2::zeros((self.kernel.nrows(), band.windows_max()));
        for p in planes {
            for group in input_rows.clone().step_by(ROWS_PER_PRODUCT) {
                band.clear();
                for y in group..(group + ROWS_PER_PRODUCT).min(input_rows.end) {
                    rows(p, y, &mut row);
                    band.push(y, &row);
                }
                if band.segments.is_empty() {
                    continue;
                }
                let n = band.windows();
                let windows =
                    ArrayView2::from_shape((3 * c, n).strides((1, c)), &band.cells).expect("windows in the band");
                let mut terms = terms.slice_mut(s![.., ..n]);
                general_mat_mul(1.0, &self.kernel, &windows, 0.0, &mut terms);
                for (k, term) in terms.outer_iter().enumerate() {
                    let (dz, dy, o) = (k / (3 * outputs), k / outputs % 3, k % outputs);
                    // Input plane p reaches output plane p + 1 - dz; input row y, row y + 1 - dy.
                    let Some(z) = (p + 1).checked_sub(dz).filter(|&z| z < depth) else { continue };
                    for segment in &band.segments {
                        let Some(oy) = (segment.y + 1).checked_sub(dy).filter(|oy| output_rows.contains(oy)) else {
                            continue;
                        };
                        let (xs, columns) = segment.outputs(wp);
                        let mut target = out.slice_mut(s![o, z, oy - first_row, xs]);
                        target.zip_mut_with(&term.slice(s![columns]), |t, &v| *t += v);
                    }
                }
            }
        }
    }
}

/// Rows of a plane that one matrix product convolves: the kernel is packed once per product.
const ROWS_PER_PRODUCT: usize = 32;

/// Rows of a plane laid end to end for one matrix product, each cut to its cells that hold
/// anything (a quarter of the cells at paper size lie in the padding where no view reaches:
/// their terms would be zeros) with a cell of zeros at each end. The windows of three cells of
/// consecutive segments follow each other without a gap: the band's windows are one matrix.
struct Band {
    /// Cells of `channels` values: one of zeros, then the segments.
    cells: Vec<f32>,
    channels: usize,
    segments: Vec<Segment>,
}

/// Cells `cells` of row `y`, whose windows are the band's columns from `first_column`.
struct Segment {
    y: usize,
    cells: Range<usize>,
    first_column: usize,
}

impl Segment {
    /// The output cells that the segment's windows reach within a row of `width` cells (one
    /// beyond each end of its cells), and their columns among the band's windows.
    fn outputs(&self, width: usize) -> (Range<usize>, Range<usize>) {
        let xs = self.cells.start.saturating_sub(1)..(self.cells.end + 1).min(width);
        // Window j of the segment is output cell cells.start - 1 + j.
        let first = self.first_column + xs.start + 1 - self.cells.start;
        (xs.clone(), first..first + xs.len())
    }
}

impl Band {
    fn new(width: usize, channels: usize) -> Band {
        Band { cells: vec![0.0; (ROWS_PER_PRODUCT * (width + 2) + 2) * channels], channels, segments: Vec::new() }
    }

    fn windows_max(&self) -> usize {
        self.cells.len() / self.channels - 2
    }

    /// Windows of the segments so far.
    fn windows(&self) -> usize {
        self.segments.last().map_or(0, |s| s.first_column + s.cells.len() + 2)
    }

    fn clear(&mut self) {
        self.segments.clear();
        self.cells[..self.channels].fill(0.0);
    }

    /// Adds row `y` (cells of `channels` values), cut to its cells that are not all zero.
    fn push(&mut self, y: usize, row: &[f32]) {
        let c = self.channels;
        let held = |cell: &[f32]| cell.iter().any(|&v| v != 0.0);
        let Some(first) = row.chunks_exact(c).position(held) else { return };
        let end = row.chunks_exact(c).rposition(held).expect("a cell is held") + 1;
        let first_column = self.windows();
        // Cell first_column is a zero (the band's first, or the previous segment's trailing one);
        // then the segment's leading zero, its cells, its trailing zero, and the zero cell that
        // its last window reads (the next segment's leading zero, if one follows).
        let at = (first_column + 2) * c;
        let len = (end - first) * c;
        self.cells[at - c..at].fill(0.0);
        self.cells[at..at + len].copy_from_slice(&row[first * c..end * c]);
        self.cells[at + len..at + len + 2 * c].fill(0.0);
        self.segments.push(Segment { y, cells: first..end, first_column });
    }
}

/// The probe's impulses per row.
fn probe_columns(channels: usize) -> usize {
    ((3 * channels) as f64).sqrt().ceil() as usize
}

/// Where the probe holds the impulse of input channel c and plane dz (`index` = 3c + dz).
fn impulse_at(index: usize, channels: usize) -> (usize, usize) {
    let columns = probe_columns(channels);
    (PROBE_SPACING * (index / columns) + 1, PROBE_SPACING * (index % columns) + 1)
}

/// An input (1, C, 3, Hp, Wp) of impulses: a 1 for every input channel c and plane dz, alone in
/// its 3 x 3 neighbourhood, so that the convolution's output around it holds weight[.., c, dz].
pub fn probe(channels: usize) -> Array5<f32> {
    let columns = probe_columns(channels);
    let rows = (3 * channels).div_ceil(columns);
    let mut input = Array5::zeros((1, channels, 3, rows * PROBE_SPACING, columns * PROBE_SPACING));
    for c in 0..channels {
        for dz in 0..3 {
            let (y, x) = impulse_at(c * 3 + dz, channels);
            input[[0, c, dz, y, x]] = 1.0;
        }
    }
    input
}

#[cfg(test)]
mod tests {
    use super::*;

    fn weight(outputs: usize, channels: usize) -> Array5<f32> {
        Array5::from_shape_fn((outputs, channels, 3, 3, 3), |(o, c, dz, dy, dx)| {
            ((o * 7 + c * 5 + dz * 3 + dy * 2 + dx) % 11) as f32 - 5.0
        })
    }

    /// The convolution by its definition, one output at a time.
    fn naive(weight: &Array5<f32>, cost: &Array5<f32>) -> Array5<f32> {
        let (outputs, channels, _, _, _) = weight.dim();
        let (_, _, planes, h, w) = cost.dim();
        Array5::from_shape_fn((1, outputs, planes - 2, h, w), |(_, o, z, y, x)| {
            let mut sum = 0.0;
            for (c, dz, dy, dx) in itertools(channels) {
                let (yy, xx) = ((y + dy).wrapping_sub(1), (x + dx).wrapping_sub(1));
                if yy < h && xx < w {
                    sum += weight[[o, c, dz, dy, dx]] * cost[[0, c, z + dz, yy, xx]];
                }
            }
            sum
        })
    }

    fn itertools(channels: usize) -> impl Iterator<Item = (usize, usize, usize, usize)> {
        (0..channels).flat_map(|c| (0..27).map(move |t| (c, t / 9, t / 3 % 3, t % 3)))
    }

    /// A cost with cells, rows and a plane of zeros (the padding no view reaches), more rows than
    /// one product takes.
    fn cost_with_zeros(channels: usize) -> Array5<f32> {
        Array5::from_shape_fn((1, channels, 6, 19, 7), |(_, c, p, y, x)| {
            let empty = p == 2 || y == 3 || y > 15 || x < 2 || (x + y) % 5 == 0;
            if empty {
                0.0
            } else {
                ((c + 2 * p + 3 * y + x) % 7) as f32 - 3.0
            }
        })
    }

    #[test]
    fn rows_by_products_are_the_convolution() {
        let (outputs, channels) = (3, 5);
        let w = weight(outputs, channels);
        let cost = cost_with_zeros(channels);
        let conv = FirstConvolution::new(w.view());
        let (got, want) = (conv.of_cost(cost.view()), naive(&w, &cost));
        assert_eq!(got.dim(), (1, 3, 4, 19, 7));
        assert!(got.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-3), "{got}\n{want}");
        conv.check(cost.view(), want.view()).unwrap();
        let mut wrong = want.clone();
        wrong[[0, 1, 2, 3, 4]] += 1.0;
        assert!(conv.check(cost.view(), wrong.view()).unwrap_err().contains("differs"));
    }

    /// Bands of output rows (as threads take them) add up to the whole, bit for bit.
    #[test]
    fn bands_of_rows_give_the_same_sums() {
        let channels = 4;
        let conv = FirstConvolution::new(weight(2, channels).view());
        let cost = cost_with_zeros(channels);
        let (_, _, planes, h, w) = cost.dim();
        let mut rows = |p: usize, y: usize, row: &mut [f32]| {
            row.iter_mut().zip(cost.slice(s![0, .., p, y, ..]).t().iter()).for_each(|(r, &v)| *r = v);
        };
        let mut whole = Array5::zeros((1, 2, planes, h, w));
        conv.accumulate(0..planes, whole.index_axis_mut(Axis(0), 0), 0, h, &mut rows);
        let mut banded = Array5::zeros((1, 2, planes, h, w));
        for (i, band) in banded.axis_chunks_iter_mut(Axis(3), 5).enumerate() {
            conv.accumulate(0..planes, band.index_axis_move(Axis(0), 0), 5 * i, h, &mut rows);
        }
        assert_eq!(whole, banded);
    }

    #[test]
    fn the_response_to_the_probe_is_the_kernel() {
        let (outputs, channels) = (2, 4);
        let w = weight(outputs, channels);
        let probe = probe(channels);
        let response = naive(&w, &probe);
        let read = FirstConvolution::from_probe(response.view(), channels);
        assert_eq!(read.kernel, FirstConvolution::new(w.view()).kernel);
    }
}
