//! AdaIN assembled: the frozen encoder, the AdaIN layer and the decoder, with the forward pass
//! used at inference and the content/style losses used for training.

use candle_core::{Result, Tensor};

use super::adain::{adain, Stats};
use super::decoder::Decoder;
use super::encoder::VggEncoder;
use super::losses::{content_loss, feature_stats, style_loss};

/// A style as the network sees it: channel statistics of its four encoder features.
#[derive(Debug, Clone)]
pub struct StyleTarget {
    pub stats: [Stats; 4],
}

/// Loss terms of one training pass, plus the decoded image they were computed on.
#[derive(Debug, Clone)]
pub struct Losses {
    pub content: Tensor,
    pub style: Tensor,
    /// Decoded image `[B, 3, H, W]` (unclamped), part of the graph.
    pub output: Tensor,
}

/// Encoder + decoder.
#[derive(Debug, Clone)]
pub struct AdaInNet {
    pub encoder: VggEncoder,
    pub decoder: Decoder,
}

impl AdaInNet {
    /// Statistics of a style image `[1, 3, H, W]` (or of a batch of crops of one style).
    pub fn style_target(&self, style: &Tensor) -> Result<StyleTarget> {
        Ok(StyleTarget {
            stats: feature_stats(&self.encoder.features(style)?)?,
        })
    }

    /// Stylizes `content` `[B, 3, H, W]`: decoder(AdaIN(relu4_1(content), style, α)).
    pub fn stylize(&self, content: &Tensor, style: &StyleTarget, alpha: f64) -> Result<Tensor> {
        let feat = self.encoder.relu4_1(content)?;
        self.decoder.forward(&adain(&feat, &style.stats[3], alpha)?)
    }

    /// AdaIN's training losses for stylizing `content` with `style` (α = 1): content loss
    /// against the AdaIN target, style loss against the style's statistics.
    pub fn losses(&self, content: &Tensor, style: &StyleTarget) -> Result<Losses> {
        let target = adain(&self.encoder.relu4_1(content)?, &style.stats[3], 1.0)?;
        let output = self.decoder.forward(&target)?;
        let feats = self.encoder.features(&output)?;
        Ok(Losses {
            content: content_loss(&feats[3], &target)?,
            style: style_loss(&feats, &style.stats)?,
            output,
        })
    }
}
