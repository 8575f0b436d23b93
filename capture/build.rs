//! `cfg(shared_data)` for this crate's tests (see the included file).
include!("../tests/test_cfg.rs");

fn main() {
    emit_shared_data_cfg();
}
