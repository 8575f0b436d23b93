// Shared by the build scripts of the crates whose tests need `../shared/data` or belong to the
// full tier (tests/build.rs, capture/build.rs, client/build.rs include this file).

/// `cfg(shared_data)` when the real scenes sit beside the repository. Tests that need them are
/// marked ignored without it, so a run without the data reports them as skipped (with the reason)
/// instead of passing them.
#[allow(dead_code)]
fn emit_shared_data_cfg() {
    println!("cargo::rustc-check-cfg=cfg(shared_data)");
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    println!("cargo::rerun-if-changed={}", data.display());
    if data.join("nerf_synthetic_lego/transforms_train.json").is_file() {
        println!("cargo::rustc-cfg=shared_data");
    }
}

/// `cfg(full_tier)` under `SCNERF_TEST_TIER=full` (`scripts/test.sh --full`): the paper-size and
/// long tests run only then, and are reported as ignored, naming the tier, otherwise. Only test
/// crates emit it: a library's cfg change would rebuild everything above it.
#[allow(dead_code)]
fn emit_full_tier_cfg() {
    println!("cargo::rustc-check-cfg=cfg(full_tier)");
    println!("cargo::rerun-if-env-changed=SCNERF_TEST_TIER");
    if std::env::var("SCNERF_TEST_TIER").as_deref() == Ok("full") {
        println!("cargo::rustc-cfg=full_tier");
    }
}
