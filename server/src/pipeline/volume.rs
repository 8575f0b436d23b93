//! Stage 2: cost volume + 3D U-Net G2 -> encoding volume in the reference (first) view's frustum.
//!
//! A bundle builds it one of three ways (`VolumeBuild`). `volume.onnx` computes the whole cost
//! volume at once: the warped features of every depth plane exist together (at paper size, 128
//! planes of 3 views x 32 channels: 3127 MiB measured at 640x512, ~8 GB at 1024x1024). A bundle
//! with `cost_slab.onnx` and `volume_net.onnx` builds it slab by slab: the cost volume's variance
//! is per plane, so each run of the slab graph warps only its planes (and one plane of halo on
//! each side, which G2's first 3x3x3 convolution reads) and returns that convolution's output for
//! its planes. The outputs are written into one (1, C0, D, Hp, Wp) tensor, 8 channels instead of
//! the cost volume's 41, and `volume_net.onnx` runs the rest of G2 over it, its norms with the
//! whole volume's statistics. A bundle with `cost_conv.onnx` and `volume_net.onnx` (the fastest)
//! has the server compute that first convolution itself, a row of a plane at a time: the plane
//! sweep (`sweep`) gives the row's cost, the convolution (`first_conv`, its kernel read from
//! `cost_conv.onnx`) adds the row's terms into place; this runs on the executor thread as the
//! preparation of the `volume_net` run (`Ticket::run_prepared`). A `volume_net.onnx` may leave
//! G2's last step to the server (`VolumeTail::Server`, `volume_tail`), which then computes it on
//! the executor thread right after the run. Every way gives the same volume up to float rounding
//! (the exporter checks each bundle's graphs against PyTorch's).

use std::ops::Range;

use futures_util::{stream, StreamExt, TryStreamExt};
use nalgebra::{Matrix4, Vector4};
use ndarray::{s, ArcArray4, ArcArray5, Array1, Array3, Array5, Axis, Ix5};
use tokio::sync::OnceCell;

use super::first_conv::{self, FirstConvolution};
use super::sweep::PlaneSweep;
use super::volume_tail;
use crate::backend::{BackendError, NamedTensors, Outputs, Ticket, Work};
use crate::bundle::{GraphKind, ModelConfig, VolumeBuild, VolumeTail};
use crate::camera::{stack_rows, CanonicalCamera};

/// Working memory of one cost slab run per cell of its planes (halo included), bytes: 660-730
/// with ONNX Runtime 1.31 on the CPU at paper size (41 cost channels, three views), measured as
/// the cost_slab stage's peak above the encoder's resident set, less the assembled conv0, at
/// 320x256-800x800 sources (docs/results.md, "Memory at paper size"); rounded up.
pub const SLAB_BYTES_PER_CELL: usize = 1024;

/// How many depth planes one cost slab run takes, and how many threads the plane sweep uses.
#[derive(Debug, Clone, Copy)]
pub struct SlabPolicy {
    /// Working memory a slab run may take (`--volume-slab-mb`).
    pub memory_budget_bytes: usize,
    /// Threads of the plane sweep and the first convolution: ONNX Runtime's (`--threads`), whose
    /// runs they take turns with on the executor.
    pub threads: usize,
}

impl Default for SlabPolicy {
    fn default() -> Self {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        SlabPolicy { memory_budget_bytes: 512 << 20, threads }
    }
}

impl SlabPolicy {
    /// Planes per slab for `cells` cells per plane: what the budget allows after the two halo
    /// planes, at least one, at most the volume's `depth_planes`.
    pub fn planes_per_slab(&self, depth_planes: usize, cells: usize) -> usize {
        let planes = self.memory_budget_bytes / (SLAB_BYTES_PER_CELL * cells.max(1));
        planes.saturating_sub(2).clamp(1, depth_planes.max(1))
    }

    /// The slabs of a volume of `depth_planes` planes of `cells` cells.
    pub fn slabs(&self, depth_planes: usize, cells: usize) -> Vec<Range<usize>> {
        let step = self.planes_per_slab(depth_planes, cells);
        (0..depth_planes).step_by(step).map(|start| start..(start + step).min(depth_planes)).collect()
    }
}

/// Cells of one plane of the volume for padded sources of `width` x `height`: the feature grid
/// (1/4 of the image) with `pad` cells on each side.
pub fn plane_cells(config: &ModelConfig, width: usize, height: usize) -> usize {
    (height / 4 + 2 * config.pad) * (width / 4 + 2 * config.pad)
}

/// `diag(1/4, 1/4, 1, 1) · [[K, 0], [0, 1]] · w2c` per view: projection onto the feature grid.
pub fn feature_projection(camera: &CanonicalCamera) -> Matrix4<f64> {
    Matrix4::from_diagonal(&Vector4::new(0.25, 0.25, 1.0, 1.0)) * camera.k.to_homogeneous() * camera.w2c
}

/// (V, 4, 4) feature-grid projections.
pub fn projections(cameras: &[CanonicalCamera]) -> Array3<f32> {
    stack_rows(&cameras.iter().map(feature_projection).collect::<Vec<_>>())
}

/// `linspace(near, far, D)`, computed like torch.linspace (from both ends towards the middle).
pub fn depth_planes(near: f64, far: f64, d: usize) -> Array1<f32> {
    let step = (far - near) / (d - 1) as f64;
    let half = d / 2;
    Array1::from_shape_fn(d, |i| if i < half { near + step * i as f64 } else { far - step * (d - 1 - i) as f64 } as f32)
}

/// The cost slab graph's `depth_planes` and `plane_inside` for `planes` of `depth`: those planes
/// with one plane of halo on each side, and 1/0 for each of them inside/outside the volume. A
/// halo plane outside the volume repeats the end plane's depth (a depth of 0 or below would
/// divide by zero in the warp; its cost is multiplied by 0 anyway). As the exporter's
/// `slab_halo`.
pub fn slab_planes(depth: &Array1<f32>, planes: Range<usize>) -> (Array1<f32>, Array1<f32>) {
    let d = depth.len() as isize;
    let index = (planes.start as isize - 1)..(planes.end as isize + 1);
    let at = index.clone().map(|i| depth[i.clamp(0, d - 1) as usize]).collect();
    let inside = index.map(|i| if (0..d).contains(&i) { 1.0 } else { 0.0 }).collect();
    (at, inside)
}

/// The inputs every volume graph takes: the sources' features and images, their feature-grid
/// projections and the volume's depth planes.
pub struct VolumeInputs {
    pub features: ArcArray4<f32>,
    pub images: ArcArray4<f32>,
    pub projections: Array3<f32>,
    pub depth_planes: Array1<f32>,
}

impl VolumeInputs {
    pub fn new(
        config: &ModelConfig,
        features: &ArcArray4<f32>,
        images: &ArcArray4<f32>,
        cameras: &[CanonicalCamera],
        near: f64,
        far: f64,
    ) -> VolumeInputs {
        VolumeInputs {
            features: features.clone(),
            images: images.clone(),
            projections: projections(cameras),
            depth_planes: depth_planes(near, far, config.depth_planes),
        }
    }

    /// Cells of one plane of the padded feature grid.
    fn cells(&self, pad: usize) -> usize {
        let (_, _, h, w) = self.features.dim();
        (h + 2 * pad) * (w + 2 * pad)
    }

    /// Named inputs, with `depth_planes` (and, for a slab, `plane_inside`) as given.
    fn named(&self, planes: Array1<f32>, inside: Option<Array1<f32>>) -> NamedTensors {
        let mut inputs: NamedTensors = vec![
            ("features".into(), self.features.clone().into_dyn()),
            ("images".into(), self.images.clone().into_dyn()),
            ("projections".into(), self.projections.clone().into_shared().into_dyn()),
            ("depth_planes".into(), planes.into_shared().into_dyn()),
        ];
        if let Some(inside) = inside {
            inputs.push(("plane_inside".into(), inside.into_shared().into_dyn()));
        }
        inputs
    }
}

/// How this server builds volumes: the bundle's way and who computes G2's last step, the slab
/// policy and, for the plane sweep, the first convolution's kernel, read from `cost_conv.onnx` by
/// the first build.
pub struct VolumeBuilder {
    build: VolumeBuild,
    tail: VolumeTail,
    policy: SlabPolicy,
    first_conv: OnceCell<FirstConvolution>,
}

impl VolumeBuilder {
    pub fn new(build: VolumeBuild, tail: VolumeTail, policy: SlabPolicy) -> VolumeBuilder {
        VolumeBuilder { build, tail, policy, first_conv: OnceCell::new() }
    }

    pub fn build(&self) -> VolumeBuild {
        self.build
    }

    pub fn policy(&self) -> &SlabPolicy {
        &self.policy
    }

    /// The work of building the volume of padded sources of `pixels` (V·H·W) pixels with `cells`
    /// cells per plane: the volume graph over the pixels, or each slab over its share of them
    /// (halo planes included) and G2 over the pixels, or the sweep and G2 (one run) over the
    /// pixels.
    pub fn work(&self, config: &ModelConfig, pixels: f64, cells: usize) -> Work {
        match self.build {
            VolumeBuild::Whole => Work::of(GraphKind::Volume, pixels),
            VolumeBuild::Slabs => {
                let d = config.depth_planes;
                let planes: usize = self.policy.slabs(d, cells).iter().map(|p| p.len() + 2).sum();
                Work::of(GraphKind::CostSlab, pixels * planes as f64 / d as f64)
                    .plus(Work::of(GraphKind::VolumeNet, pixels))
            }
            VolumeBuild::Sweep => Work::of(GraphKind::VolumeNet, pixels),
        }
    }

    /// features (V, C, h, w) + images + cameras -> volume (1, Cv, D, h + 2·pad, w + 2·pad).
    pub async fn run(
        &self,
        ticket: &Ticket,
        config: &ModelConfig,
        inputs: VolumeInputs,
    ) -> Result<ArcArray5<f32>, BackendError> {
        let (_, _, h, w) = inputs.features.dim();
        let pixels = super::pixel_units(&inputs.images);
        let mut out = match self.build {
            VolumeBuild::Whole => {
                let named = inputs.named(inputs.depth_planes.clone(), None);
                ticket.run(GraphKind::Volume, pixels, named).await?
            }
            VolumeBuild::Slabs => {
                let conv0 = first_convolution(ticket, config, &self.policy, &inputs).await?;
                self.run_volume_net(ticket, config, pixels, move || conv0).await?
            }
            VolumeBuild::Sweep => {
                let conv = self.first_conv.get_or_try_init(|| read_first_convolution(ticket, config)).await?.clone();
                let (pad, threads) = (config.pad, self.policy.threads);
                let sweep = move || swept_first_convolution(&inputs, &conv, pad, threads);
                self.run_volume_net(ticket, config, pixels, sweep).await?
            }
        };
        let (d, cv, p) = (config.depth_planes, config.volume_channels, config.pad);
        out.take("volume", &[Some(1), Some(cv), Some(d), Some(h + 2 * p), Some(w + 2 * p)])
    }

    /// G2 after its first convolution, which `conv0` makes on the executor thread, and its last
    /// step after the graph when the server computes it.
    async fn run_volume_net(
        &self,
        ticket: &Ticket,
        config: &ModelConfig,
        pixels: f64,
        conv0: impl FnOnce() -> Array5<f32> + Send + 'static,
    ) -> Result<Outputs, BackendError> {
        let named = move || vec![("conv0".to_string(), conv0().into_shared().into_dyn())];
        match (self.tail, config.activation_slope) {
            (VolumeTail::Server, Some(slope)) => {
                let threads = self.policy.threads;
                let finish = move |inputs, outputs| volume_tail::finish(inputs, outputs, slope, threads);
                ticket.run_prepared_then(GraphKind::VolumeNet, pixels, named, finish).await
            }
            _ => ticket.run_prepared(GraphKind::VolumeNet, pixels, named).await,
        }
    }
}

/// G2's first convolution over the cost volume of the plane sweep, (1, C0, D, Hp, Wp): each of
/// `threads` threads sweeps and convolves a band of rows of every plane (and the rows either side
/// of its band, which its rows' convolution reads).
fn swept_first_convolution(inputs: &VolumeInputs, conv: &FirstConvolution, pad: usize, threads: usize) -> Array5<f32> {
    let sweep = PlaneSweep::new(inputs.features.view(), inputs.images.view(), inputs.projections.view(), pad);
    let depths = inputs.depth_planes.as_slice().expect("a new array");
    let (hp, wp) = sweep.grid();
    let mut conv0 = written_zeros((1, conv.outputs(), depths.len(), hp, wp));
    let rows_per_thread = hp.div_ceil(threads.max(1)).max(1);
    std::thread::scope(|scope| {
        for (i, rows) in conv0.axis_chunks_iter_mut(Axis(3), rows_per_thread).enumerate() {
            let sweep = &sweep;
            scope.spawn(move || {
                let mut scratch = sweep.scratch();
                let mut cost_row =
                    |p: usize, y: usize, row: &mut [f32]| sweep.cost_row(depths[p], y, row, &mut scratch);
                let first_row = i * rows_per_thread;
                conv.accumulate(0..depths.len(), rows.index_axis_move(Axis(0), 0), first_row, hp, &mut cost_row);
            });
        }
    });
    conv0
}

/// Zeros that are in memory. `Array5::zeros` takes fresh pages from calloc: until written, each
/// maps the kernel's shared zero page, and the convolution reads before it writes (`+=`), so every
/// page cost a read fault, then a copy-on-write fault that flushed the page from every CPU's TLB
/// (a tenth of the server's CPU time while it built a 640x512 volume). Written once here, each
/// page faults once.
fn written_zeros(shape: (usize, usize, usize, usize, usize)) -> Array5<f32> {
    let (a, b, c, d, e) = shape;
    let len = a * b * c * d * e;
    let mut zeros = Vec::with_capacity(len);
    zeros.resize(len, 0.0);
    Array5::from_shape_vec(shape, zeros).expect("as many values as the shape holds")
}

/// The first convolution's kernel, read from the bundle's `cost_conv.onnx` by its response to
/// impulses, and checked against the graph on another input.
async fn read_first_convolution(ticket: &Ticket, config: &ModelConfig) -> Result<FirstConvolution, BackendError> {
    let channels = 3 * config.views + config.feature_channels;
    let conv0 = |cost: &Array5<f32>| {
        let (_, _, planes, h, w) = cost.dim();
        let run = ticket.run(GraphKind::CostConv, 0.0, vec![("cost".to_string(), cost.to_shared().into_dyn())]);
        let shape = [Some(1), Some(config.volume_channels), Some(planes - 2), Some(h), Some(w)];
        async move { run.await?.take::<Ix5>("conv0", &shape) }
    };
    let probe = first_conv::probe(channels);
    let conv = FirstConvolution::from_probe(conv0(&probe).await?.view(), channels);
    // Any values but impulses: a pattern that is not symmetric in any axis.
    let check = Array5::from_shape_fn((1, channels, 4, 5, 7), |(_, c, p, y, x)| {
        ((c * 7 + p * 5 + y * 3 + x * 2) % 13) as f32 - 6.0
    });
    conv.check(check.view(), conv0(&check).await?.view()).map_err(|message| BackendError::BadOutput {
        graph: GraphKind::CostConv,
        message: format!("not the first convolution the server computes: {message}"),
    })?;
    Ok(conv)
}

/// Cost slab runs that one request keeps queued: one runs while the previous one's output is
/// copied into place; more would only hold memory.
const SLABS_IN_FLIGHT: usize = 2;

/// G2's first convolution over the whole cost volume, (1, C0, D, Hp, Wp), slab by slab.
async fn first_convolution(
    ticket: &Ticket,
    config: &ModelConfig,
    policy: &SlabPolicy,
    inputs: &VolumeInputs,
) -> Result<Array5<f32>, BackendError> {
    let (d, cv, cells) = (config.depth_planes, config.volume_channels, inputs.cells(config.pad));
    let (_, _, h, w) = inputs.features.dim();
    let (hp, wp) = (h + 2 * config.pad, w + 2 * config.pad);
    let pixels = super::pixel_units(&inputs.images);
    let mut conv0 = Array5::zeros((1, cv, d, hp, wp));
    let mut runs = stream::iter(policy.slabs(d, cells))
        .map(|planes| {
            let (at, inside) = slab_planes(&inputs.depth_planes, planes.clone());
            let units = pixels * (planes.len() + 2) as f64 / d as f64;
            let run = ticket.run(GraphKind::CostSlab, units, inputs.named(at, Some(inside)));
            async move { run.await.map(|outputs| (planes, outputs)) }
        })
        .buffered(SLABS_IN_FLIGHT);
    while let Some((planes, mut outputs)) = runs.try_next().await? {
        let shape = [Some(1), Some(cv), Some(planes.len()), Some(hp), Some(wp)];
        let slab = outputs.take::<ndarray::Ix5>("conv0", &shape)?;
        conv0.slice_mut(s![.., .., planes, .., ..]).assign(&slab);
    }
    Ok(conv0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use scnerf_capture::wire::from_rows;

    #[test]
    fn linspace_hits_both_ends() {
        let t = depth_planes(2.0, 6.0, 5);
        assert_eq!(t.to_vec(), vec![2.0, 3.0, 4.0, 5.0, 6.0]);
        let t = depth_planes(2.125, 4.525, 128);
        assert_eq!(t[0], 2.125);
        assert_eq!(t[127], 4.525);
    }

    #[test]
    fn slabs_cover_the_planes_once_with_their_halo() {
        let depth = depth_planes(2.0, 6.0, 5);
        let (at, inside) = slab_planes(&depth, 0..2);
        assert_eq!(at.to_vec(), vec![2.0, 2.0, 3.0, 4.0]);
        assert_eq!(inside.to_vec(), vec![0.0, 1.0, 1.0, 1.0]);
        let (at, inside) = slab_planes(&depth, 4..5);
        assert_eq!((at.to_vec(), inside.to_vec()), (vec![5.0, 6.0, 6.0], vec![1.0, 1.0, 0.0]));
        // 1 MiB at 1024 bytes per cell of 64 cells: 16 planes, 14 after the halo.
        let policy = |memory_budget_bytes| SlabPolicy { memory_budget_bytes, threads: 1 };
        assert_eq!(policy(1 << 20).slabs(32, 64), vec![0..14, 14..28, 28..32]);
        assert_eq!(policy(0).slabs(3, 64), vec![0..1, 1..2, 2..3]);
        assert_eq!(policy(usize::MAX).slabs(3, 64), vec![0..3]);
    }

    #[test]
    fn projection_scales_intrinsics() {
        let cam = CanonicalCamera {
            width: 8,
            height: 8,
            k: from_rows(&[[100.0, 0.0, 40.0], [0.0, 80.0, 20.0], [0.0, 0.0, 1.0]]),
            w2c: from_rows(&[[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]),
        };
        let p = projections(&[cam]);
        assert_eq!(p.slice(ndarray::s![0, 0, ..]).to_vec(), [25.0, 0.0, 10.0, 25.0 + 30.0]);
        assert_eq!(p.slice(ndarray::s![0, 1, ..]).to_vec(), [0.0, 20.0, 5.0, 40.0 + 15.0]);
        assert_eq!(p.slice(ndarray::s![0, 2, ..]).to_vec(), [0.0, 0.0, 1.0, 3.0]);
        assert_eq!(p.slice(ndarray::s![0, 3, ..]).to_vec(), [0.0, 0.0, 0.0, 1.0]);
    }
}
