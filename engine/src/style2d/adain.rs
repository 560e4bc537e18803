//! Adaptive instance normalisation: per-channel mean and standard deviation over the spatial
//! axes, and re-normalising content features to a style's statistics. As in the reference
//! implementation (Huang & Belongie's pytorch-AdaIN `calc_mean_std`), the variance is the
//! unbiased one and ε = 1e-5 is added to it before the square root.

use candle_core::{Result, Tensor};

/// ε added to the variance.
pub const EPS: f64 = 1e-5;

/// Channel statistics of NCHW features: mean and std, each `[B, C, 1, 1]`.
#[derive(Debug, Clone)]
pub struct Stats {
    pub mean: Tensor,
    pub std: Tensor,
}

/// Mean and unbiased std (+ε inside the root) of each channel of `feat` over H×W.
pub fn stats(feat: &Tensor) -> Result<Stats> {
    let (b, c, h, w) = feat.dims4()?;
    let n = h * w;
    if n < 2 {
        candle_core::bail!("channel statistics need at least 2 pixels, got {h}×{w}");
    }
    let flat = feat.reshape((b, c, n))?;
    let mean = flat.mean_keepdim(2)?;
    let centred = flat.broadcast_sub(&mean)?;
    let var = (centred.sqr()?.sum_keepdim(2)? / (n - 1) as f64)?;
    let std = (var + EPS)?.sqrt()?;
    Ok(Stats {
        mean: mean.reshape((b, c, 1, 1))?,
        std: std.reshape((b, c, 1, 1))?,
    })
}

/// AdaIN: `content` normalised per channel, then scaled and shifted to `style`, blended with
/// the content features by `alpha` (1 = full style, 0 = the content features unchanged).
/// `style` broadcasts over the batch when it has batch size 1.
pub fn adain(content: &Tensor, style: &Stats, alpha: f64) -> Result<Tensor> {
    let c = stats(content)?;
    let normalised = content.broadcast_sub(&c.mean)?.broadcast_div(&c.std)?;
    let t = normalised
        .broadcast_mul(&style.std)?
        .broadcast_add(&style.mean)?;
    if alpha == 1.0 {
        Ok(t)
    } else {
        (t * alpha)? + (content * (1.0 - alpha))?
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::style2d::gradcheck;
    use candle_core::Device;

    #[test]
    fn statistics_match_hand_computation() {
        // One channel with values 1..=4: mean 2.5, unbiased var 5/3.
        let x = Tensor::new(&[1f64, 2., 3., 4.], &Device::Cpu)
            .unwrap()
            .reshape((1, 1, 2, 2))
            .unwrap();
        let s = stats(&x).unwrap();
        assert!((s.mean.flatten_all().unwrap().to_vec1::<f64>().unwrap()[0] - 2.5).abs() < 1e-12);
        let std = s.std.flatten_all().unwrap().to_vec1::<f64>().unwrap()[0];
        assert!((std - (5.0f64 / 3.0 + 1e-5).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn adain_output_has_the_style_statistics() {
        let content = gradcheck::random(&[2, 3, 5, 4], 1);
        let style =
            stats(&((gradcheck::random(&[1, 3, 6, 6], 2) * 3.0).unwrap() + 1.0).unwrap()).unwrap();
        let out = stats(&adain(&content, &style, 1.0).unwrap()).unwrap();
        for (a, b) in [(&out.mean, &style.mean), (&out.std, &style.std)] {
            let d = a
                .broadcast_sub(b)
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_scalar::<f64>()
                .unwrap();
            assert!(d < 1e-4, "{d}");
        }
        // α = 0 returns the content features.
        let same = adain(&content, &style, 0.0).unwrap();
        let d = (same - &content)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        assert!(d < 1e-12);
    }

    #[test]
    fn gradients_match_finite_differences() {
        let style = stats(&gradcheck::random(&[1, 2, 3, 3], 3)).unwrap();
        gradcheck::check(&gradcheck::random(&[1, 2, 3, 4], 4), |x| {
            adain(x, &style, 0.7)
        });
        gradcheck::check(&gradcheck::random(&[2, 2, 3, 3], 5), |x| {
            let s = stats(x)?;
            Tensor::cat(&[s.mean, s.std], 1)
        });
    }
}
