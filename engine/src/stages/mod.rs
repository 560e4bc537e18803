//! The stages the worker runs, as library functions: each reads its inputs from local folders,
//! writes its outputs (and checkpoints) under its own output folder, reports progress through a
//! [`StageControl`] and can be cancelled, interrupted and resumed.

pub mod control;

pub use control::{Outcome, Progress, StageControl};

/// The stages of a job, in order.
pub const STAGES: [&str; 5] = [
    "nerf_pretrain",
    "render_views",
    "decoder_pretrain",
    "mutual_learning",
    "render_stylized",
];
pub mod camera_paths;
pub mod decoder_pretrain;
pub mod limits;
pub mod mutual_learning;
pub mod nerf_pretrain;
pub mod render_stylized;
pub mod render_views;
pub mod window;
