//! `cfg(shared_data)` and `cfg(full_tier)` for this crate's tests (see the included file).
include!("../tests/test_cfg.rs");

fn main() {
    emit_shared_data_cfg();
    emit_full_tier_cfg();
}
