//! scnerf-server: SC-NeRF novel-view rendering over HTTP with ONNX Runtime.
//!
//! Data path: `http` (router, body, negotiation) -> `request` (wire -> domain -> validate; a
//! capture folder's files by `captures`) -> `camera` (canonical cameras) -> `pipeline`: `sources`
//! (decode, pad) -> `encoder` -> `volume` (cost volume) -> `rays` -> `chunks` (renderer runs) ->
//! `assemble` (image) -> `http::respond`. The graphs run on one inference thread (`backend`,
//! ONNX Runtime in `backend::ort`); other CPU work runs on blocking threads and stops with its
//! request (`blocking`). `bundle` is the model contract, `models` the models served (a pipeline
//! per bundle, all on the one executor; a request names its model), `cache` keeps scenes, `error`
//! maps every refusal to HTTP, `config` is the one configuration struct.

pub mod auth;
pub mod backend;
pub mod blocking;
pub mod bundle;
pub mod cache;
pub mod camera;
pub mod captures;
pub mod config;
pub mod error;
pub mod http;
pub mod image_io;
pub mod logging;
pub mod metrics;
pub mod models;
pub mod pipeline;
pub mod request;
pub mod server;
pub mod sysmem;
#[cfg(any(test, feature = "testing"))]
#[doc(hidden)]
pub mod testing;
