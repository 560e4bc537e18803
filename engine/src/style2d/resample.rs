//! 2×2 max-pooling and 2× nearest upsampling written as reshapes and broadcasts, because
//! candle 0.11's `max_pool2d` and `upsample_nearest2d` have wrong backward passes.

use candle_core::{Result, Tensor};

/// 2×2 max-pool with stride 2 on NCHW (even H and W).
pub fn max_pool2x2(x: &Tensor) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    if h % 2 != 0 || w % 2 != 0 {
        candle_core::bail!("max_pool2x2 needs even sides, got {h}×{w}");
    }
    x.reshape((b, c, h / 2, 2, w / 2, 2))?.max(5)?.max(3)
}

/// Nearest-neighbour 2× upsampling on NCHW.
pub fn upsample_nearest2x(x: &Tensor) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    x.reshape((b, c, h, 1, w, 1))?
        .broadcast_as((b, c, h, 2, w, 2))?
        .reshape((b, c, 2 * h, 2 * w))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::style2d::gradcheck;

    #[test]
    fn pool_and_upsample_values() {
        let x = Tensor::new(
            &[[1f32, 5., 2., 0.], [3., 4., 7., 1.]],
            &candle_core::Device::Cpu,
        )
        .unwrap()
        .reshape((1, 1, 2, 4))
        .unwrap();
        let p = max_pool2x2(&x)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert_eq!(p, vec![5.0, 7.0]);
        let u = upsample_nearest2x(&x).unwrap();
        assert_eq!(u.dims(), &[1, 1, 4, 8]);
        let rows = u
            .squeeze(0)
            .unwrap()
            .squeeze(0)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        assert_eq!(rows[1], vec![1., 1., 5., 5., 2., 2., 0., 0.]);
        assert_eq!(rows[2], vec![3., 3., 4., 4., 7., 7., 1., 1.]);
    }

    #[test]
    fn gradients_match_finite_differences() {
        // Random inputs have no ties, so the max is differentiable.
        gradcheck::check(&gradcheck::random(&[2, 2, 4, 6], 3), max_pool2x2);
        // The input also feeds a second consumer: the gradients must accumulate.
        gradcheck::check(&gradcheck::random(&[1, 2, 3, 2], 4), |x| {
            Tensor::cat(
                &[
                    upsample_nearest2x(x)?.flatten_all()?,
                    x.sqr()?.flatten_all()?,
                ],
                0,
            )
        });
    }
}
