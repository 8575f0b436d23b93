//! The band: pixels whose surface a source does not see, coloured from the sources that do.
//!
//! The model's appearance mean (F_a) divides by all V sources, a source that does not see a point
//! counting as zero (as it was trained). On some captures (LLFF horns, not DTU or Blender) the
//! network then renders a surface outside one source's image too dark: the dark band along the
//! edges of forward-facing views. Such a view is recognised by the ratio of the network's colours
//! to its sources' (each pixel's surface point, on its ray at the rendered depth, sampled
//! bilinearly in the sources that see it, times the pixel's opacity): lower in the band, by more
//! than [`DARKER`], than over the pixels every source sees. Its band's pixels then take their
//! sources' colour, and a pixel no source sees that of the sources' nearest pixels (their
//! images' borders), as dark as the band in the network's render. docs/results.md, "The band",
//! measures the rule. Its Python twin is exporter/scnerf_export/runtime/band.py (the band fixture
//! holds the two together).

use ndarray::{ArrayView2, ArrayView3, ArrayView4, Axis};

use super::chunks::RawView;
use super::rays::Rays;
use super::scene::Scene;
use crate::bundle::BandRule;

/// What colours the band's pixels (`--band`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum BandFill {
    /// Where the band is dark, the colour of the sources that see each pixel's surface.
    #[default]
    Sources,
    /// The network's own colour, as the paper renders it.
    Network,
}

/// The sources as the band reads them: images (V, 3, H, W) padded right and bottom, each view's
/// own width and height, K (V, 3, 3) and world-to-camera (V, 4, 4).
pub struct Sources<'a> {
    pub images: ArrayView4<'a, f32>,
    pub sizes: &'a [(usize, usize)],
    pub intrinsics: ArrayView3<'a, f32>,
    pub extrinsics: ArrayView3<'a, f32>,
}

impl<'a> Sources<'a> {
    pub fn of(scene: &'a Scene) -> Sources<'a> {
        Sources {
            images: scene.images.view(),
            sizes: &scene.source_sizes,
            intrinsics: scene.intrinsics.view(),
            extrinsics: scene.extrinsics.view(),
        }
    }

    /// Image coordinates of world point `p` in view `v` where it lies in front of the camera, and
    /// whether they are inside the image (pixel centres at integers: [0, W − 1] x [0, H − 1]).
    fn project(&self, v: usize, p: [f64; 3]) -> Option<((f64, f64), bool)> {
        let (e, k) = (self.extrinsics.index_axis(Axis(0), v), self.intrinsics.index_axis(Axis(0), v));
        let x: [f64; 3] =
            std::array::from_fn(|r| (0..3).map(|c| e[(r, c)] as f64 * p[c]).sum::<f64>() + e[(r, 3)] as f64);
        if x[2] <= 0.0 {
            return None;
        }
        let image: [f64; 3] = std::array::from_fn(|r| (0..3).map(|c| k[(r, c)] as f64 * x[c]).sum());
        let (col, row) = (image[0] / image[2], image[1] / image[2]);
        let (width, height) = self.sizes[v];
        let inside = col >= 0.0 && row >= 0.0 && col <= (width - 1) as f64 && row <= (height - 1) as f64;
        Some(((col, row), inside))
    }

    /// What the sources show of world point `p`: the mean colour of those that see it or, where
    /// none does, of the nearest pixels of those it lies in front of (their images' borders).
    fn sight(&self, p: [f64; 3]) -> Sighting {
        let (mut seen, mut border) = (Mean::default(), Mean::default());
        for v in 0..self.sizes.len() {
            if let Some((at, inside)) = self.project(v, p) {
                let colour = self.sample(v, at);
                border.add(colour);
                if inside {
                    seen.add(colour);
                }
            }
        }
        let colour = if seen.count > 0 { seen.mean() } else { border.mean() };
        Sighting { views: seen.count, colour }
    }

    /// View `v`'s colour at image coordinates (col, row), bilinearly, clamped into the image.
    fn sample(&self, v: usize, (col, row): (f64, f64)) -> [f64; 3] {
        let (width, height) = self.sizes[v];
        let (col, row) = (col.clamp(0.0, (width - 1) as f64), row.clamp(0.0, (height - 1) as f64));
        let (x0, y0) = (col.floor() as usize, row.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(width - 1), (y0 + 1).min(height - 1));
        let (a, b) = (col - x0 as f64, row - y0 as f64);
        let image = self.images.index_axis(Axis(0), v);
        std::array::from_fn(|c| {
            let at = |y: usize, x: usize| image[(c, y, x)] as f64;
            at(y0, x0) * (1.0 - a) * (1.0 - b)
                + at(y0, x1) * a * (1.0 - b)
                + at(y1, x0) * (1.0 - a) * b
                + at(y1, x1) * a * b
        })
    }
}

/// A band whose colours, against its sources', are below this fraction of the same ratio over
/// the pixels every source sees is dark. Between the horns views whose band is visibly dark
/// (0.72-0.88) and every other validation view (0.92-1.17).
pub const DARKER: f64 = 0.9;

/// What the sources show of a pixel's surface point: how many see it, and its colour (none
/// where it lies in front of no source).
struct Sighting {
    views: usize,
    colour: Option<[f64; 3]>,
}

/// A running mean of colours.
#[derive(Default)]
struct Mean {
    sum: [f64; 3],
    count: usize,
}

impl Mean {
    fn add(&mut self, colour: [f64; 3]) {
        (0..3).for_each(|c| self.sum[c] += colour[c]);
        self.count += 1;
    }

    fn mean(&self) -> Option<[f64; 3]> {
        (self.count > 0).then(|| self.sum.map(|c| c / self.count as f64))
    }
}

/// Recolours the band's pixels of `raw` (rays `rays`) from `sources` when the band is dark (or
/// always, by the bundle's `rule`), and with them the pixels no source sees (from the nearest
/// pixels of the sources, which keeps the band's edge at the image's edge continuous); returns
/// how many it recoloured.
pub fn fill_from_sources(raw: &mut RawView, rays: &Rays, sources: &Sources, rule: BandRule) -> usize {
    let views = sources.sizes.len();
    let sightings: Vec<Sighting> = (0..raw.depth.len())
        .map(|i| sources.sight(surface_point(rays.origins.view(), rays.directions.view(), i, raw.depth[i])))
        .collect();
    let band = colour_ratio(raw, &sightings, |s| s.views > 0 && s.views < views);
    let everywhere = colour_ratio(raw, &sightings, |s| s.views == views);
    let dark = matches!((band, everywhere), (Some(band), Some(everywhere)) if band < DARKER * everywhere);
    if !(dark || rule == BandRule::Always) {
        return 0;
    }
    let mut filled = 0;
    for ((mut rgb, sighting), &opacity) in raw.rgb.rows_mut().into_iter().zip(&sightings).zip(&raw.opacity) {
        if let Some(colour) = sighting.colour.filter(|_| sighting.views < views) {
            rgb.iter_mut().zip(colour).for_each(|(x, c)| *x = (opacity as f64 * c) as f32);
            filled += 1;
        }
    }
    filled
}

/// The sum of the network's colours over the sum of their sources' (times opacity), over the
/// pixels `which` selects; none where those show nothing.
fn colour_ratio(raw: &RawView, sightings: &[Sighting], which: impl Fn(&Sighting) -> bool) -> Option<f64> {
    let (mut network, mut seen) = (0.0, 0.0);
    for ((rgb, sighting), &opacity) in raw.rgb.rows().into_iter().zip(sightings).zip(&raw.opacity) {
        if let Some(colour) = sighting.colour.filter(|_| which(sighting)) {
            network += rgb.iter().map(|&x| x as f64).sum::<f64>();
            seen += opacity as f64 * colour.iter().sum::<f64>();
        }
    }
    (seen > 0.0).then(|| network / seen)
}

/// Ray `i`'s point at z-depth `depth` (its direction has unit z in the target camera).
fn surface_point(origins: ArrayView2<f32>, directions: ArrayView2<f32>, i: usize, depth: f32) -> [f64; 3] {
    std::array::from_fn(|c| origins[(i, c)] as f64 + directions[(i, c)] as f64 * depth as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{arr1, arr2, s, Array2, Array3, Array4};

    /// Two sources at the origin looking down +z (f = 1, centre (1.5, 1)), 4x3 and `second` wide
    /// (padded to the first's width): points with x/z + 1.5 in [0, second - 1] are seen by both.
    struct Rig {
        images: Array4<f32>,
        intrinsics: Array3<f32>,
        extrinsics: Array3<f32>,
        sizes: [(usize, usize); 2],
    }

    impl Rig {
        fn new(width: usize, second: usize) -> Rig {
            let k = arr2(&[[1.0f32, 0.0, 1.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]]);
            let (mut intrinsics, mut extrinsics) = (Array3::zeros((2, 3, 3)), Array3::zeros((2, 4, 4)));
            for v in 0..2 {
                intrinsics.index_axis_mut(Axis(0), v).assign(&k);
                extrinsics.index_axis_mut(Axis(0), v).assign(&Array2::eye(4));
            }
            let images = Array4::zeros((2, 3, 3, width.max(second)));
            Rig { images, intrinsics, extrinsics, sizes: [(width, 3), (second, 3)] }
        }

        fn sources(&self) -> Sources<'_> {
            Sources {
                images: self.images.view(),
                sizes: &self.sizes,
                intrinsics: self.intrinsics.view(),
                extrinsics: self.extrinsics.view(),
            }
        }
    }

    /// Rays from the origin along (x, 0, 1).
    fn rays(xs: &[f32]) -> Rays {
        let origins = Array2::zeros((xs.len(), 3));
        let directions = Array2::from_shape_fn((xs.len(), 3), |(i, c)| [xs[i], 0.0, 1.0][c]);
        Rays { origins: origins.into_shared(), directions: directions.into_shared() }
    }

    /// Source 0 a red ramp along x (x / 4) over green 0.9, source 1 (2 wide) grey 0.5; pixel 0 at
    /// image x = 1 (seen by both: red 0.375, green 0.7), pixel 1 at x = 1.75 (source 0 alone: red
    /// 0.4375, green 0.9), both at depth 2 and opacity 0.5.
    fn ramp_rig() -> Rig {
        let mut rig = Rig::new(4, 2);
        for x in 0..4 {
            rig.images.slice_mut(s![0, 0, .., x]).fill(x as f32 / 4.0);
        }
        rig.images.slice_mut(s![0, 1..3, .., ..]).fill(0.9);
        rig.images.slice_mut(s![1, .., .., ..2]).fill(0.5);
        rig
    }

    fn view(rgb: [[f32; 3]; 2]) -> RawView {
        RawView { rgb: arr2(&rgb), depth: arr1(&[2.0, 2.0]), opacity: arr1(&[0.5, 0.5]) }
    }

    fn assert_close(got: &RawView, want: [[f32; 3]; 2]) {
        for (g, w) in got.rgb.iter().zip(want.iter().flatten()) {
            assert!((g - w).abs() < 1e-6, "{:?} vs {want:?}", got.rgb);
        }
    }

    const EVERY: [f32; 3] = [0.5 * 0.375, 0.5 * 0.7, 0.5 * 0.7];
    const SEEN_BY_ONE: [f32; 3] = [0.5 * 0.4375, 0.5 * 0.9, 0.5 * 0.9];
    const RAYS: [f32; 2] = [-0.5, 0.25];

    #[test]
    fn a_dark_band_takes_the_colour_of_the_sources_that_see_it_times_opacity() {
        let rig = ramp_rig();
        // The pixel both sources see as they show it; the other at half its source's colour.
        let mut raw = view([EVERY, SEEN_BY_ONE.map(|c| 0.5 * c)]);
        assert_eq!(fill_from_sources(&mut raw, &rays(&RAYS), &rig.sources(), BandRule::WhenDark), 1);
        assert_close(&raw, [EVERY, SEEN_BY_ONE]);
    }

    #[test]
    fn a_band_within_the_ratio_of_the_rest_keeps_the_networks_colour_unless_the_bundle_always_fills() {
        let rig = ramp_rig();
        let network = [EVERY, SEEN_BY_ONE.map(|c| 0.95 * c)];
        let mut raw = view(network);
        assert_eq!(fill_from_sources(&mut raw, &rays(&RAYS), &rig.sources(), BandRule::WhenDark), 0);
        assert_close(&raw, network);
        assert_eq!(fill_from_sources(&mut raw, &rays(&RAYS), &rig.sources(), BandRule::Always), 1);
        assert_close(&raw, [EVERY, SEEN_BY_ONE]);
    }

    #[test]
    fn without_pixels_every_source_sees_nothing_is_recoloured() {
        let rig = ramp_rig();
        let network = [[0.0; 3], SEEN_BY_ONE.map(|c| 0.5 * c)];
        // Pixel 0 behind both cameras: no source sees it, and no pixel is seen by all.
        let mut raw = RawView { depth: arr1(&[-1.0, 2.0]), ..view(network) };
        assert_eq!(fill_from_sources(&mut raw, &rays(&RAYS), &rig.sources(), BandRule::WhenDark), 0);
        assert_close(&raw, network);
    }

    #[test]
    fn a_pixel_no_source_sees_takes_the_nearest_pixels_of_the_sources_in_a_dark_band() {
        let rig = ramp_rig();
        // Pixel 2 at image x = 3.5: outside both images, in front of both. Their nearest pixels:
        // source 0's last column (red 0.75, green 0.9), source 1's (grey 0.5).
        let mut raw = RawView {
            rgb: arr2(&[EVERY, SEEN_BY_ONE.map(|c| 0.5 * c), [0.0; 3]]),
            depth: arr1(&[2.0, 2.0, 2.0]),
            opacity: arr1(&[0.5, 0.5, 0.5]),
        };
        assert_eq!(fill_from_sources(&mut raw, &rays(&[-0.5, 0.25, 2.0]), &rig.sources(), BandRule::WhenDark), 2);
        let nearest = [0.5 * 0.625, 0.5 * 0.7, 0.5 * 0.7];
        for (got, want) in raw.rgb.iter().zip([EVERY, SEEN_BY_ONE, nearest].iter().flatten()) {
            assert!((got - want).abs() < 1e-6, "{:?}", raw.rgb);
        }
    }

    #[test]
    fn padding_beyond_a_sources_size_is_outside_it() {
        // Source 1 is 2 wide in a stack padded to 4 with a bright 1.0: x = 2 in it is not seen.
        let mut rig = ramp_rig();
        rig.images.slice_mut(s![1, .., .., 2..]).fill(1.0);
        let mut raw = view([EVERY, [0.0; 3]]);
        assert_eq!(fill_from_sources(&mut raw, &rays(&[-0.5, 0.5]), &rig.sources(), BandRule::WhenDark), 1);
        assert_close(&raw, [EVERY, [0.5 * 0.5, 0.5 * 0.9, 0.5 * 0.9]]);
    }
}
