//! `scnerf`, the command-line client of scnerf-serve: reads a capture (COLMAP, nerfstudio,
//! Blender, LLFF, DTU), uploads it once as a scene, renders camera paths to frames and video, and
//! scores held-out views.

pub mod camera;
pub mod error;
pub mod readers;
