//! The stages the worker runs, as library functions: each reads its inputs from local folders,
//! writes its outputs (and checkpoints) under its own output folder, reports progress through a
//! [`StageControl`] and can be cancelled, interrupted and resumed.

pub mod control;

pub use control::{Outcome, Progress, StageControl};
pub mod decoder_pretrain;
pub mod nerf_pretrain;
pub mod render_views;
