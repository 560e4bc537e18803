//! Losses on a ray's compositing weights, computed on the host: the weights of each packed ray
//! from σ, a per-ray loss that gives its value and `g = ∂L/∂w`, and the chain rule back to σ.
//! With `w_k = T_k (1 − e^{−σ_k δ_k})` and `T` the transmittance,
//! `∂L/∂σ_k = δ_k (T_{k+1} g_k − Σ_{j>k} w_j g_j)` (a suffix sum, O(S)). The result is a tensor
//! whose value is the loss and whose gradient with respect to σ is the analytic one
//! (`σ·γ − stop_gradient(σ·γ) + L`), so it works on every device without a kernel of its own.
//! The distortion loss ([`super::distortion`]) and the depth-supervision loss
//! ([`super::depth_supervision`]) are the per-ray losses.

use std::ops::Range;

use candle_core::Tensor;

use crate::rays::PackedRays;
use crate::Result;

/// One ray's loss: given its sample range in the packing and its weights, writes `∂L/∂w` into
/// the last argument (zeroed, as long as the weights) and returns the ray's loss.
pub trait RayLoss: FnMut(usize, Range<usize>, &[f64], &mut [f64]) -> f64 {}
impl<F: FnMut(usize, Range<usize>, &[f64], &mut [f64]) -> f64> RayLoss for F {}

/// The sum over the rays of `per_ray`, divided by `divisor` (> 0), differentiable in σ [S].
pub fn weight_loss(
    sigma: &Tensor,
    rays: &PackedRays,
    divisor: f64,
    per_ray: impl RayLoss,
) -> Result<Tensor> {
    let s: Vec<f32> = sigma.to_dtype(candle_core::DType::F32)?.to_vec1()?;
    let (loss, grad) = loss_and_grad(&s, rays, per_ray);
    let n = divisor;
    let g = Tensor::from_vec(
        grad.iter().map(|g| (g / n) as f32).collect::<Vec<_>>(),
        s.len(),
        sigma.device(),
    )?
    .to_dtype(sigma.dtype())?;
    let linear = (sigma * &g)?.sum_all()?;
    Ok(((&linear - linear.detach())? + loss / n)?)
}

/// The sum over the rays of `per_ray`, and its gradient with respect to each σ.
pub fn loss_and_grad(
    sigma: &[f32],
    rays: &PackedRays,
    mut per_ray: impl RayLoss,
) -> (f64, Vec<f64>) {
    let mut total = 0.0;
    let mut grad = vec![0.0; sigma.len()];
    let (mut w, mut trans_after, mut g) = (Vec::new(), Vec::new(), Vec::new());
    for (ray, window) in rays.offsets.windows(2).enumerate() {
        let range = window[0] as usize..window[1] as usize;
        if range.is_empty() {
            continue;
        }
        // Weights and the transmittance after each sample.
        w.clear();
        trans_after.clear();
        let mut trans = 1.0f64;
        for k in range.clone() {
            let decay = (-(sigma[k] as f64) * rays.deltas[k] as f64).exp();
            w.push(trans * (1.0 - decay));
            trans *= decay;
            trans_after.push(trans);
        }
        g.clear();
        g.resize(w.len(), 0.0);
        total += per_ray(ray, range.clone(), &w, &mut g);
        // Through the weights to σ: suffix sums of w g.
        let mut after = 0.0f64;
        for (i, k) in range.enumerate().rev() {
            grad[k] = rays.deltas[k] as f64 * (trans_after[i] * g[i] - after);
            after += w[i] * g[i];
        }
    }
    (total, grad)
}
