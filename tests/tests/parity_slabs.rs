//! Parity of the slab-by-slab volume build: the parity fixture bundle with its `volume.onnx`
//! split into `cost_slab.onnx` and `volume_net.onnx` (tests/fixtures/parity-slabs) renders every
//! parity case within the PyTorch tolerances, and its volume does not depend on how many planes a
//! slab run takes. A test binary of its own: ONNX Runtime's environment is process-wide, one
//! bundle per process.

mod split_volume;

use scnerf_server::bundle::VolumeBuild;
use scnerf_server::pipeline::chunks::ChunkPolicy;
use scnerf_server::pipeline::volume::{SlabPolicy, SLAB_BYTES_PER_CELL};
use scnerf_server::pipeline::Pipeline;
use scnerf_server::request::Limits;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slab_built_volume_matches_pytorch_whatever_the_slab_size() {
    let p = split_volume::split_pipeline("parity-slabs");
    assert_eq!(p.bundle().volume_build(), VolumeBuild::Slabs);
    // The same graphs and executor, `planes` depth planes per cost slab run.
    let with_slabs = |planes: usize| {
        let p = p.clone();
        move |cells: usize| {
            let policy = SlabPolicy { memory_budget_bytes: (planes + 2) * SLAB_BYTES_PER_CELL * cells, threads: 2 };
            Pipeline::new(p.executor().clone(), p.bundle().clone(), ChunkPolicy::default(), policy, Limits::default())
        }
    };
    // One plane per run, five (the last slab shorter), and all planes in one run.
    let (one, five, all) = (with_slabs(1), with_slabs(5), with_slabs(p.config().depth_planes));
    split_volume::volumes_match_pytorch(&p, &[("1 plane per slab", &one), ("5 planes", &five), ("all planes", &all)])
        .await;
}
