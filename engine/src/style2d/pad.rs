//! Reflection padding (PyTorch's `ReflectionPad2d`), which candle lacks: an `index_select`
//! with a reflected index along each spatial axis, so the backward pass is `index_add`.

use candle_core::{Result, Tensor};

/// Reflected indices for padding an axis of length `n` by `p` on both sides:
/// for n = 4, p = 1: [1, 0, 1, 2, 3, 2].
fn reflected(n: usize, p: usize) -> Vec<u32> {
    let n = n as i64;
    (-(p as i64)..n + p as i64)
        .map(|i| {
            let r = if i < 0 {
                -i
            } else if i >= n {
                2 * (n - 1) - i
            } else {
                i
            };
            r as u32
        })
        .collect()
}

/// Pads the last two axes of an NCHW tensor by `p` with reflection (p < H and p < W).
pub fn reflection_pad2d(x: &Tensor, p: usize) -> Result<Tensor> {
    let (_, _, h, w) = x.dims4()?;
    if p >= h || p >= w {
        candle_core::bail!("reflection padding {p} needs sides > {p}, got {h}×{w}");
    }
    let dev = x.device();
    let iw = Tensor::new(reflected(w, p), dev)?;
    let ih = Tensor::new(reflected(h, p), dev)?;
    x.contiguous()?.index_select(&iw, 3)?.index_select(&ih, 2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::style2d::gradcheck;

    #[test]
    fn matches_pytorch_reflection() {
        assert_eq!(reflected(4, 1), vec![1, 0, 1, 2, 3, 2]);
        assert_eq!(reflected(4, 2), vec![2, 1, 0, 1, 2, 3, 2, 1]);
        let x = Tensor::arange(0f32, 6.0, &candle_core::Device::Cpu)
            .unwrap()
            .reshape((1, 1, 2, 3))
            .unwrap();
        let y = reflection_pad2d(&x, 1)
            .unwrap()
            .squeeze(0)
            .unwrap()
            .squeeze(0)
            .unwrap();
        let rows = y.to_vec2::<f32>().unwrap();
        assert_eq!(rows[0], vec![4.0, 3.0, 4.0, 5.0, 4.0]);
        assert_eq!(rows[1], vec![1.0, 0.0, 1.0, 2.0, 1.0]);
        assert_eq!(rows[3], rows[1]);
    }

    #[test]
    fn gradient_matches_finite_differences() {
        gradcheck::check(&gradcheck::random(&[1, 2, 4, 5], 1), |x| {
            reflection_pad2d(x, 1)
        });
        gradcheck::check(&gradcheck::random(&[1, 1, 3, 4], 2), |x| {
            reflection_pad2d(x, 2)
        });
    }
}
