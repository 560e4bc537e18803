//! The encoder's and decoder's convolution: k×k, valid (the callers pad), stride 1, NCHW, as
//! a candle `CustomOp2` on the CPU with both gradients.
//!
//! candle 0.11's CPU conv2d builds its im2col tiles one value at a time, channel-innermost
//! from an NHWC copy it makes single-threaded — those scattered copies cost more than the
//! gemm itself — and its backward runs the input gradient through a direct
//! `conv_transpose2d` loop and always computes the kernel gradient, even for frozen weights.
//! Here:
//! - forward: im2col by rows — row (c, ky, kx) of the column matrix is input plane c shifted
//!   by (ky, kx), copied one output row (a contiguous run) at a time, rows in parallel — then
//!   one gemm W[C_out, C_in·k²] · col per band of output rows, written straight into NCHW;
//! - input gradient: col_g = Wᵀ · G per band, added back into the planes (col2im), planes in
//!   parallel;
//! - weight gradient: G · colᵀ accumulated over images and bands.
//!
//! Each gradient is computed only when its argument is tracked, so a frozen encoder (plain
//! tensors as weights) pays for the input gradient alone. Bands keep the column matrix under
//! [`BAND_VALUES`] values at any image size. Off the CPU, candle's conv2d does the work.

use candle_core::{CpuStorage, CustomOp2, Layout, Result, Shape, Tensor, WithDType};
use rayon::prelude::*;

use crate::cpu_ops::{contiguous_slice, matmul, Threads};

/// Most values in one band's column matrix (16 MiB in f32).
const BAND_VALUES: usize = 1 << 22;

/// Valid, stride-1 convolution of `x` `[B, C, H, W]` with `weight` `[O, C, k, k]`:
/// `[B, O, H − k + 1, W − k + 1]`. Differentiable in both arguments.
pub fn conv2d(x: &Tensor, weight: &Tensor) -> Result<Tensor> {
    if x.device().is_cpu() {
        x.contiguous()?.apply_op2(&weight.contiguous()?, Conv)
    } else {
        x.conv2d(weight, 0, 1, 1, 1)
    }
}

/// Sizes of one convolution.
#[derive(Debug, Clone, Copy)]
struct Geometry {
    batch: usize,
    c_in: usize,
    h: usize,
    w: usize,
    c_out: usize,
    k: usize,
}

impl Geometry {
    /// From the input's and the weight's dims, checked.
    fn new(x: &[usize], weight: &[usize]) -> Result<Self> {
        let (&[batch, c_in, h, w], &[c_out, wc, k, k2]) = (x, weight) else {
            candle_core::bail!("conv2d: input {x:?} and weight {weight:?} must both be 4-D");
        };
        if wc != c_in || k != k2 || k == 0 || h < k || w < k {
            candle_core::bail!(
                "conv2d: input {x:?} does not fit weight {weight:?} (square kernel, no larger \
                 than the input, matching channels)"
            );
        }
        Ok(Self {
            batch,
            c_in,
            h,
            w,
            c_out,
            k,
        })
    }

    fn oh(&self) -> usize {
        self.h - self.k + 1
    }

    fn ow(&self) -> usize {
        self.w - self.k + 1
    }

    /// Rows of the column matrix: C_in·k².
    fn rows(&self) -> usize {
        self.c_in * self.k * self.k
    }

    fn in_plane(&self) -> usize {
        self.h * self.w
    }

    fn out_plane(&self) -> usize {
        self.oh() * self.ow()
    }

    /// Output rows per band.
    fn band(&self) -> usize {
        (BAND_VALUES / (self.rows() * self.ow())).clamp(1, self.oh())
    }

    /// `(first output row, rows)` of each band.
    fn bands(&self) -> impl Iterator<Item = (usize, usize)> {
        let (band, oh) = (self.band(), self.oh());
        (0..oh).step_by(band).map(move |y0| (y0, band.min(oh - y0)))
    }

    /// A column matrix big enough for any band.
    fn column<T: WithDType>(&self) -> Vec<T> {
        vec![T::zero(); self.rows() * self.band() * self.ow()]
    }

    fn out_shape(&self) -> Shape {
        (self.batch, self.c_out, self.oh(), self.ow()).into()
    }
}

/// Fills `col` `[C_in·k², rows·W_out]` with the patches of output rows `y0..y0 + rows` of one
/// image `img` `[C_in, H, W]`.
fn im2col<T: WithDType>(g: &Geometry, img: &[T], y0: usize, rows: usize, col: &mut [T]) {
    let (k, w, ow) = (g.k, g.w, g.ow());
    let p = rows * ow;
    col[..g.rows() * p]
        .par_chunks_mut(p)
        .enumerate()
        .for_each(|(r, dst)| {
            let (c, ky, kx) = (r / (k * k), r / k % k, r % k);
            let plane = &img[c * g.in_plane()..(c + 1) * g.in_plane()];
            for (i, out_row) in dst.chunks_exact_mut(ow).enumerate() {
                let start = (y0 + i + ky) * w + kx;
                out_row.copy_from_slice(&plane[start..start + ow]);
            }
        });
}

/// Adds the column matrix `col` (the layout of [`im2col`]) back into the image gradient
/// `img` `[C_in, H, W]`.
fn col2im_add<T: WithDType>(g: &Geometry, col: &[T], y0: usize, rows: usize, img: &mut [T]) {
    let (k, w, ow) = (g.k, g.w, g.ow());
    let p = rows * ow;
    img.par_chunks_mut(g.in_plane())
        .enumerate()
        .for_each(|(c, plane)| {
            for kk in 0..k * k {
                let (ky, kx) = (kk / k, kk % k);
                let src = &col[(c * k * k + kk) * p..(c * k * k + kk + 1) * p];
                for (i, src_row) in src.chunks_exact(ow).enumerate() {
                    let start = (y0 + i + ky) * w + kx;
                    for (d, s) in plane[start..start + ow].iter_mut().zip(src_row) {
                        *d += *s;
                    }
                }
            }
        });
}

/// The convolution `[B, C_out, H_out, W_out]`.
fn forward<T: WithDType>(g: &Geometry, x: &[T], weight: &[T]) -> Vec<T> {
    let mut out = vec![T::zero(); g.batch * g.c_out * g.out_plane()];
    let mut col = g.column();
    for (img, dst) in x
        .chunks_exact(g.c_in * g.in_plane())
        .zip(out.chunks_exact_mut(g.c_out * g.out_plane()))
    {
        for (y0, rows) in g.bands() {
            let p = rows * g.ow();
            im2col(g, img, y0, rows, &mut col);
            matmul(
                g.c_out,
                p,
                g.rows(),
                (&mut dst[y0 * g.ow()..], g.out_plane()),
                (weight, g.rows() as isize, 1),
                (&col, p as isize, 1),
                false,
                Threads::Pool,
            );
        }
    }
    out
}

/// The gradient of the input, `[B, C_in, H, W]`, given the output's `grad`.
fn input_grad<T: WithDType>(g: &Geometry, grad: &[T], weight: &[T]) -> Vec<T> {
    let mut gx = vec![T::zero(); g.batch * g.c_in * g.in_plane()];
    let mut col = g.column();
    for (gimg, dst) in grad
        .chunks_exact(g.c_out * g.out_plane())
        .zip(gx.chunks_exact_mut(g.c_in * g.in_plane()))
    {
        for (y0, rows) in g.bands() {
            let p = rows * g.ow();
            // Wᵀ [C_in·k², C_out] · G_band [C_out, p].
            matmul(
                g.rows(),
                p,
                g.c_out,
                (&mut col, p),
                (weight, 1, g.rows() as isize),
                (&gimg[y0 * g.ow()..], g.out_plane() as isize, 1),
                false,
                Threads::Pool,
            );
            col2im_add(g, &col, y0, rows, dst);
        }
    }
    gx
}

/// The gradient of the weight, `[C_out, C_in, k, k]`, given the input and the output's `grad`.
fn weight_grad<T: WithDType>(g: &Geometry, x: &[T], grad: &[T]) -> Vec<T> {
    let mut gw = vec![T::zero(); g.c_out * g.rows()];
    let mut col = g.column();
    for (b, (img, gimg)) in x
        .chunks_exact(g.c_in * g.in_plane())
        .zip(grad.chunks_exact(g.c_out * g.out_plane()))
        .enumerate()
    {
        for (y0, rows) in g.bands() {
            let p = rows * g.ow();
            im2col(g, img, y0, rows, &mut col);
            // G_band [C_out, p] · colᵀ [p, C_in·k²].
            matmul(
                g.c_out,
                g.rows(),
                p,
                (&mut gw, g.rows()),
                (&gimg[y0 * g.ow()..], g.out_plane() as isize, 1),
                (&col, 1, p as isize),
                b > 0 || y0 > 0,
                Threads::Pool,
            );
        }
    }
    gw
}

/// Runs `f` on two contiguous CPU operands of the same float type.
fn with_slices(
    what: &str,
    (s1, l1): (&CpuStorage, &Layout),
    (s2, l2): (&CpuStorage, &Layout),
    f32_fn: impl FnOnce(&[f32], &[f32]) -> Vec<f32>,
    f64_fn: impl FnOnce(&[f64], &[f64]) -> Vec<f64>,
) -> Result<CpuStorage> {
    Ok(match (s1, s2) {
        (CpuStorage::F32(a), CpuStorage::F32(b)) => CpuStorage::F32(f32_fn(
            contiguous_slice(a, l1, what)?,
            contiguous_slice(b, l2, what)?,
        )),
        (CpuStorage::F64(a), CpuStorage::F64(b)) => CpuStorage::F64(f64_fn(
            contiguous_slice(a, l1, what)?,
            contiguous_slice(b, l2, what)?,
        )),
        _ => candle_core::bail!("{what}: operands must both be f32 or both f64"),
    })
}

/// `conv2d(x, weight)`.
struct Conv;

impl CustomOp2 for Conv {
    fn name(&self) -> &'static str {
        "conv2d-valid"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = Geometry::new(l1.dims(), l2.dims())?;
        let out = with_slices(
            "conv2d",
            (s1, l1),
            (s2, l2),
            |x, w| forward(&g, x, w),
            |x, w| forward(&g, x, w),
        )?;
        Ok((out, g.out_shape()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let gx = if x.track_op() {
            Some(grad.apply_op2_no_bwd(weight, &InputGrad { h: x.dim(2)? })?)
        } else {
            None
        };
        let gw = if weight.track_op() {
            Some(x.apply_op2_no_bwd(&grad, &WeightGrad { k: weight.dim(2)? })?)
        } else {
            None
        };
        Ok((gx, gw))
    }
}

/// The input gradient: `(grad, weight)` → `[B, C_in, h, w]` (`h` is the input's height; the
/// kernel's side gives the width).
struct InputGrad {
    h: usize,
}

impl CustomOp2 for InputGrad {
    fn name(&self) -> &'static str {
        "conv2d-valid-input-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (gd, wd) = (l1.dims(), l2.dims());
        let &[batch, _, oh, ow] = gd else {
            candle_core::bail!("conv2d backward: gradient {gd:?} must be 4-D");
        };
        let k = self.h + 1 - oh;
        let g = Geometry::new(&[batch, wd[1], self.h, ow + k - 1], wd)?;
        let out = with_slices(
            "conv2d backward",
            (s1, l1),
            (s2, l2),
            |gr, w| input_grad(&g, gr, w),
            |gr, w| input_grad(&g, gr, w),
        )?;
        Ok((out, (batch, g.c_in, g.h, g.w).into()))
    }
}

/// The weight gradient: `(x, grad)` → `[C_out, C_in, k, k]`.
struct WeightGrad {
    k: usize,
}

impl CustomOp2 for WeightGrad {
    fn name(&self) -> &'static str {
        "conv2d-valid-weight-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (xd, gd) = (l1.dims(), l2.dims());
        let (&[_, c_in, _, _], &[_, c_out, _, _]) = (xd, gd) else {
            candle_core::bail!("conv2d backward: {xd:?} and {gd:?} must be 4-D");
        };
        let g = Geometry::new(xd, &[c_out, c_in, self.k, self.k])?;
        let out = with_slices(
            "conv2d backward",
            (s1, l1),
            (s2, l2),
            |x, gr| weight_grad(&g, x, gr),
            |x, gr| weight_grad(&g, x, gr),
        )?;
        Ok((out, (c_out, c_in, self.k, self.k).into()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::style2d::gradcheck;
    use candle_core::Var;

    fn max_diff(a: &Tensor, b: &Tensor) -> f64 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_dtype(candle_core::DType::F64)
            .unwrap()
            .to_scalar::<f64>()
            .unwrap()
    }

    #[test]
    fn forward_matches_candle() {
        for (x, w) in [
            ([2, 3, 6, 5], [4, 3, 3, 3]),
            ([1, 5, 4, 7], [2, 5, 1, 1]),
            ([3, 2, 5, 5], [3, 2, 5, 5]),
        ] {
            let x = gradcheck::random(&x, 10);
            let w = gradcheck::random(&w, 11);
            let ours = conv2d(&x, &w).unwrap();
            assert!(max_diff(&ours, &x.conv2d(&w, 0, 1, 1, 1).unwrap()) < 1e-12);
        }
    }

    #[test]
    fn bands_cover_the_image_exactly() {
        // A column matrix of 16 × 1000 rows per band: several bands, the last one short.
        let g = Geometry::new(&[1, 16, 1002, 1000], &[1, 16, 1, 1]).unwrap();
        let bands: Vec<_> = g.bands().collect();
        assert!(bands.len() > 2, "{bands:?}");
        assert_eq!(bands[0].0, 0);
        assert!(bands.windows(2).all(|b| b[0].0 + b[0].1 == b[1].0));
        let last = bands.last().unwrap();
        assert_eq!(last.0 + last.1, g.oh());
        // A forward in several bands gives candle's result.
        let xs = gradcheck::random(&[1, 64, 1100, 70], 14).to_dtype(candle_core::DType::F32);
        let ws = gradcheck::random(&[3, 64, 3, 3], 15).to_dtype(candle_core::DType::F32);
        let (xs, ws) = (xs.unwrap(), ws.unwrap());
        assert!(Geometry::new(xs.dims(), ws.dims()).unwrap().bands().count() > 1);
        let d = max_diff(
            &conv2d(&xs, &ws).unwrap(),
            &xs.conv2d(&ws, 0, 1, 1, 1).unwrap(),
        );
        assert!(d < 1e-3, "{d}");
    }

    #[test]
    fn gradients_match_finite_differences() {
        let w = gradcheck::random(&[3, 2, 3, 3], 20);
        let x = gradcheck::random(&[2, 2, 5, 4], 21);
        gradcheck::check(&x, |x| conv2d(x, &w));
        gradcheck::check(&w, |w| conv2d(&x, w));
        let w1 = gradcheck::random(&[2, 3, 1, 1], 22);
        gradcheck::check(&gradcheck::random(&[1, 3, 3, 3], 23), |x| conv2d(x, &w1));
    }

    #[test]
    fn only_tracked_arguments_get_gradients() {
        let x = Var::from_tensor(&gradcheck::random(&[1, 2, 4, 4], 30)).unwrap();
        let frozen = gradcheck::random(&[3, 2, 3, 3], 31);
        let grads = conv2d(x.as_tensor(), &frozen)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(grads.get(x.as_tensor()).is_some());
        let w = Var::from_tensor(&frozen).unwrap();
        let input = gradcheck::random(&[1, 2, 4, 4], 32);
        let grads = conv2d(&input, w.as_tensor())
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(grads.get(w.as_tensor()).is_some());
    }
}
