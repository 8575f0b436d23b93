//! scnerf-server: SC-NeRF novel-view rendering over HTTP with ONNX Runtime.
//!
//! Data path: request -> camera -> image_io -> pipeline::{encoder, volume, rays, chunks,
//! assemble} -> http response. The ONNX sessions run on one inference thread (`backend`).

pub mod auth;
pub mod backend;
pub mod bundle;
pub mod cache;
pub mod camera;
pub mod config;
pub mod error;
pub mod http;
pub mod image_io;
pub mod logging;
pub mod metrics;
pub mod pipeline;
pub mod request;
pub mod server;
#[doc(hidden)]
pub mod testing;
