//! The science of StylizedNeRF on candle, with no networking: scenes and cameras, the radiance
//! field and its renderer, the 2D stylization network, the stylized NeRF and mutual learning,
//! and the stages the worker runs.
//!
//! The front, in the order to read it:
//! - [`stages`]: every stage of a job, configured and run through `stages::dispatch` (what the
//!   worker and `stylenerf run` call), with the control (progress, stop, resume) they share;
//! - the inputs: [`scene`] (datasets in every supported format, and the scene generator),
//!   [`poses`] (camera poses from photos or a video with COLMAP), [`camera`], [`image_io`],
//!   [`device`] (`cpu`, `cuda:N` to a candle device);
//! - the models a tool may drive directly: [`field`] (the radiance field and its saved form),
//!   [`render`] (volume rendering of rays and images), [`style2d`] (the VGG encoder, AdaIN
//!   decoder, their weights and 2D training);
//! - what stages write and read back: [`views`] (rendered views with depth), [`checkpoint`],
//!   [`style_metrics`] (style fidelity measured outside the training encoder), [`sheet`]
//!   (contact sheets).
//!
//! Everything else (fused CPU ops, optimisers, the stylized NeRF's internals, warping, the
//! evaluation maths) is private; the few items of it other crates need are re-exported here.

pub mod camera;
pub mod checkpoint;
pub mod device;
pub mod error;
pub mod field;
pub mod image_io;
pub mod poses;
pub mod render;
pub mod scene;
pub mod sheet;
pub mod stages;
pub mod style2d;
pub mod style_metrics;
pub mod views;

mod cpu_ops;
mod curves;
mod depth_error;
mod eval;
mod malloc;
mod named;
mod optim;
mod per_view;
mod rays;
mod rng;
mod stylized;
mod warp;

pub use error::{EngineError, Result};
pub use malloc::{keep_freed_memory, one_arena_for_all_threads, release_free_memory};
pub use optim::LrSchedule;
pub use rng::Rng;
/// The catalogue's stages and presets, which every stage configuration is built from.
pub use stylenerf_plan::{Preset, Stage};
