//! `cfg(shared_data)` for the tests that need `../shared/data` (see the included file).
include!("../tests/shared_data_cfg.rs");
