//! `cfg(shared_data)` when the real scenes of `../shared/data` sit beside the repository (as in
//! tests/build.rs): the test that renders the lego capture is marked ignored without them, so a
//! run without the data reports it as skipped instead of passing it.
use std::path::Path;

fn main() {
    println!("cargo::rustc-check-cfg=cfg(shared_data)");
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    println!("cargo::rerun-if-changed={}", data.display());
    if data.join("nerf_synthetic_lego/transforms_train.json").is_file() {
        println!("cargo::rustc-cfg=shared_data");
    }
}
