//! AdaIN's training losses: content = MSE between relu4_1 of the decoded image and the AdaIN
//! target; style = Σ over relu1_1 … relu4_1 of MSE(channel means) + MSE(channel stds).

use candle_core::{Result, Tensor};

use super::adain::{stats, Stats};
use super::encoder::Features;

/// Mean squared error over all elements.
pub fn mse(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    a.broadcast_sub(b)?.sqr()?.mean_all()
}

/// Content loss.
pub fn content_loss(decoded_relu4_1: &Tensor, target: &Tensor) -> Result<Tensor> {
    mse(decoded_relu4_1, target)
}

/// Channel statistics of each of the four features: a style's target for [`style_loss`].
pub fn feature_stats(features: &Features) -> Result<[Stats; 4]> {
    let v: Vec<Stats> = features.iter().map(stats).collect::<Result<_>>()?;
    Ok(v.try_into().expect("four features"))
}

/// Style loss of decoded features against a style's statistics (broadcast over the batch
/// when the style has batch size 1).
pub fn style_loss(decoded: &Features, style: &[Stats; 4]) -> Result<Tensor> {
    let mut total: Option<Tensor> = None;
    for (f, s) in decoded.iter().zip(style) {
        let d = stats(f)?;
        let term = (mse(&d.mean, &s.mean)? + mse(&d.std, &s.std)?)?;
        total = Some(match total {
            None => term,
            Some(t) => (t + term)?,
        });
    }
    Ok(total.expect("four features"))
}
