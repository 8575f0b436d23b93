//! Parity of the volume built from the server's plane sweep: the parity fixture bundle with its
//! `volume.onnx` split into `cost_conv.onnx` and `volume_net.onnx` (written by `scnerf-export
//! fixtures` into tests/fixtures/parity-sweep) renders every parity case within the PyTorch
//! tolerances, and its volume does not depend on how many threads sweep the planes. A test binary
//! of its own: ONNX Runtime's environment is process-wide, one bundle per process.

mod split_volume;

use scnerf_server::bundle::VolumeBuild;
use scnerf_server::pipeline::chunks::ChunkPolicy;
use scnerf_server::pipeline::volume::SlabPolicy;
use scnerf_server::pipeline::Pipeline;
use scnerf_server::request::Limits;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn swept_volume_matches_pytorch_whatever_the_threads() {
    let p = split_volume::split_pipeline("parity-sweep");
    assert_eq!(p.bundle().volume_build(), VolumeBuild::Sweep);
    // The same graphs and executor, the sweep on `threads` threads; a pipeline of its own reads
    // the first convolution's kernel from cost_conv.onnx again.
    let with_threads = |threads: usize| {
        let p = p.clone();
        move |_cells: usize| {
            let policy = SlabPolicy { threads, ..SlabPolicy::default() };
            Pipeline::new(p.executor().clone(), p.bundle().clone(), ChunkPolicy::default(), policy, Limits::default())
        }
    };
    let (one, two, five) = (with_threads(1), with_threads(2), with_threads(5));
    split_volume::volumes_match_pytorch(&p, &[("1 thread", &one), ("2 threads", &two), ("5 threads", &five)]).await;
}
