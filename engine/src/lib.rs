//! The science of StylizedNeRF on candle, with no networking: scenes and cameras, the radiance
//! field and its renderer, the 2D stylization network, the stylized NeRF and mutual learning,
//! and the stages the worker runs.

pub mod camera;
pub mod checkpoint;
pub mod cpu_ops;
pub mod curves;
pub mod device;
pub mod error;
pub mod eval;
pub mod field;
pub mod image_io;
pub mod malloc;
pub mod named;
pub mod optim;
pub mod poses;
pub mod rays;
pub mod render;
pub mod rng;
pub mod scene;
pub mod sheet;
pub mod stages;
pub mod style2d;
pub mod style_metrics;
pub mod stylized;
pub mod views;
pub mod warp;

pub use error::{EngineError, Result};
/// The catalogue's stages and presets, which every stage configuration is built from.
pub use stylenerf_plan::{Preset, Stage};
