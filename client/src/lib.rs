//! `scnerf`, the command-line client of scnerf-serve: reads a capture (COLMAP, nerfstudio,
//! Blender, LLFF, DTU), uploads it once as a scene, renders camera paths to frames and video, and
//! scores held-out views.

pub mod api;
pub mod camera;
pub mod cli;
pub mod error;
pub mod eval;
pub mod metrics;
pub mod paths;
pub mod readers;
pub mod render;
pub mod video;
