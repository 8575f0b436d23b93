//! `scnerf`, the command-line client of scnerf-serve: reads a capture (COLMAP, nerfstudio,
//! Blender, LLFF, DTU), uploads it once as a scene, renders camera paths to frames and video, and
//! scores held-out views. Cameras and dataset readers are `scnerf_capture`'s (shared with the
//! server), imported from there by their one name.

/// `println!` that stops quietly when stdout is closed (`scnerf info DATA | head`).
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}

pub mod api;
pub mod args;
pub mod cli;
pub mod error;
pub mod eval;
pub mod metrics;
pub mod paths;
pub mod render;
pub mod video;
