//! The science of StylizedNeRF on candle, with no networking: scenes and cameras, the radiance
//! field and its renderer, the 2D stylization network, the stylized NeRF and mutual learning,
//! and the stages the worker runs.

pub mod camera;
pub mod error;
pub mod scene;

pub use error::{EngineError, Result};
