//! The stages the worker runs, as library functions: each reads its inputs from local folders,
//! writes its outputs (and checkpoints) under its own output folder, reports progress through a
//! [`StageControl`] and can be cancelled, interrupted and resumed. [`dispatch`] is the one
//! entry point that configures and runs any stage of the catalogue ([`stylenerf_plan::Stage`]).

pub mod control;

pub use control::{Outcome, Progress, StageControl};

pub mod camera_paths;
pub mod decoder_pretrain;
pub mod dispatch;
pub mod mutual_learning;
pub mod nerf_pretrain;
pub mod pose_consistency;
pub mod render_stylized;
pub mod render_views;
pub mod training;
pub mod window;
