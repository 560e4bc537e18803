//! Training a decoder on one content/style pair: what `stylenerf stylize image` does when no
//! pretrained decoder is given. It optimises AdaIN's own losses (content + λ_s · style) for a
//! fixed number of Adam steps on that single pair, so it is a per-image optimisation rather
//! than a general-purpose decoder.

use candle_core::Tensor;

use super::network::{AdaInNet, StyleTarget};
use crate::optim::{Adam, AdamConfig};
use crate::Result;

/// Hyper-parameters of [`fit_pair`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitConfig {
    pub steps: usize,
    pub lr: f64,
    /// λ_s: weight of the style loss against the content loss.
    pub style_weight: f64,
}

impl Default for FitConfig {
    fn default() -> Self {
        Self {
            steps: 300,
            lr: 1e-4,
            style_weight: 1.0,
        }
    }
}

/// Loss values after a step, for progress reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    pub step: usize,
    pub content: f32,
    pub style: f32,
}

/// Trains `net.decoder` on `content` `[1, 3, H, W]` with `style`; calls `report` after every
/// step.
pub fn fit_pair(
    net: &AdaInNet,
    content: &Tensor,
    style: &StyleTarget,
    cfg: FitConfig,
    mut report: impl FnMut(StepReport),
) -> Result<()> {
    let mut adam = Adam::new(net.decoder.vars(), AdamConfig::default())?;
    for step in 0..cfg.steps {
        let l = net.losses(content, style)?;
        let total = (&l.content + (&l.style * cfg.style_weight)?)?;
        adam.step(&total.backward()?, cfg.lr)?;
        report(StepReport {
            step,
            content: l.content.to_scalar::<f32>()?,
            style: l.style.to_scalar::<f32>()?,
        });
    }
    Ok(())
}
