// The build script of the crates whose tests read `../shared/data` (included by tests/build.rs
// and client/build.rs): `cfg(shared_data)` when the real scenes sit beside the repository. Tests
// that need them are marked ignored without it, so a run without the data reports them as
// skipped (with the reason) instead of passing them.
use std::path::Path;

fn main() {
    println!("cargo::rustc-check-cfg=cfg(shared_data)");
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    println!("cargo::rerun-if-changed={}", data.display());
    if data.join("nerf_synthetic_lego/transforms_train.json").is_file() {
        println!("cargo::rustc-cfg=shared_data");
    }
}
