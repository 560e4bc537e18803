//! The stylized NeRF: the pretrained field's frozen density with a style module in place of
//! its colour head, conditioned on learnable latent codes. Used by the `mutual_learning` and
//! `render_stylized` stages.

pub mod latents;
pub mod style_module;
pub mod surface;
