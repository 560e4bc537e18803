//! The distortion loss of mip-NeRF 360: per ray,
//! `L = Σ_i Σ_j w_i w_j |m_i − m_j| + ⅓ Σ_i w_i² δ_i`, with `w` the compositing weights and
//! `m_i`, `δ_i` the midpoint and length of sample i's interval along the ray (field-space
//! distances). It is small when a ray's weight sits in one short stretch (a surface) and large
//! when it is spread out (haze, floaters), which is how a field with a learned background is
//! kept from explaining the photos with fog.
//!
//! Samples are sorted along each ray, so with prefix sums `W_<i = Σ_{j<i} w_j` and
//! `M_<i = Σ_{j<i} w_j m_j` the double sum is `2 Σ_i w_i (m_i W_<i − M_<i)` (O(S)), and
//! `∂L/∂w_i = 2 (m_i W_<i − M_<i + M_>i − m_i W_>i) + ⅔ w_i δ_i`, taken to σ on the host by
//! [`super::weight_loss`].

use std::ops::Range;

use candle_core::Tensor;

use super::weight_loss::weight_loss;
use crate::rays::PackedRays;
use crate::Result;

/// Mean distortion loss over the rays of `rays` for densities `sigma` [S], differentiable in σ.
pub fn distortion_loss(sigma: &Tensor, rays: &PackedRays) -> Result<Tensor> {
    weight_loss(
        sigma,
        rays,
        rays.num_rays().max(1) as f64,
        |_, range, w, g| distortion(rays, range, w, g),
    )
}

/// One ray's distortion loss (samples `range` of `rays`, weights `w`); writes `∂L/∂w` into `g`.
fn distortion(rays: &PackedRays, range: Range<usize>, w: &[f64], g: &mut [f64]) -> f64 {
    let mid = |k: usize| rays.distances[k] as f64 + 0.5 * rays.deltas[k] as f64;
    let (sum_w, sum_wm): (f64, f64) = range
        .clone()
        .zip(w)
        .map(|(k, &wk)| (wk, wk * mid(k)))
        .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
    // The loss and g_i = ∂L/∂w_i, with running prefix sums.
    let (mut w_before, mut wm_before) = (0.0f64, 0.0f64);
    let mut total = 0.0;
    for (i, k) in range.enumerate() {
        let (m, wi, delta) = (mid(k), w[i], rays.deltas[k] as f64);
        let w_after = sum_w - w_before - wi;
        let wm_after = sum_wm - wm_before - wi * m;
        total += 2.0 * wi * (m * w_before - wm_before) + wi * wi * delta / 3.0;
        g[i] = 2.0 * (m * w_before - wm_before + wm_after - m * w_after) + 2.0 * wi * delta / 3.0;
        w_before += wi;
        wm_before += wi * m;
    }
    total
}

/// Sum over rays of the distortion loss, and its gradient with respect to each σ.
#[cfg(test)]
fn loss_and_grad(sigma: &[f32], rays: &PackedRays) -> (f64, Vec<f64>) {
    super::weight_loss::loss_and_grad(sigma, rays, |_, range, w, g| distortion(rays, range, w, g))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use candle_core::{Device, Var};

    fn rays(rng: &mut Rng) -> PackedRays {
        let mut rays = PackedRays {
            offsets: vec![0],
            ..Default::default()
        };
        for count in [6u32, 0, 1, 9] {
            let mut s = 0.1;
            for _ in 0..count {
                let delta = 0.05 + 0.1 * rng.uniform();
                rays.deltas.push(delta);
                rays.distances.push(s);
                rays.depths.push(s);
                // Gaps where empty cells were skipped.
                s += delta + if rng.uniform() < 0.3 { 0.2 } else { 0.0 };
            }
            let last = *rays.offsets.last().unwrap();
            rays.offsets.push(last + count);
        }
        rays
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let mut rng = Rng::new(3);
        let rays = rays(&mut rng);
        let sigma: Vec<f32> = (0..rays.num_samples())
            .map(|_| 8.0 * rng.uniform())
            .collect();
        let (_, grad) = loss_and_grad(&sigma, &rays);
        for k in 0..sigma.len() {
            let h = 1e-2f32;
            let mut plus = sigma.clone();
            plus[k] += h;
            let mut minus = sigma.clone();
            minus[k] -= h;
            let fd =
                (loss_and_grad(&plus, &rays).0 - loss_and_grad(&minus, &rays).0) / (2.0 * h as f64);
            assert!(
                (fd - grad[k]).abs() < 1e-3 * (1.0 + fd.abs()),
                "sample {k}: finite difference {fd}, analytic {}",
                grad[k]
            );
        }
    }

    #[test]
    fn a_surface_costs_less_than_haze_and_the_tensor_carries_the_gradient() {
        // One ray of ten samples: all weight in one sample, or spread evenly.
        let rays = PackedRays {
            offsets: vec![0, 10],
            deltas: vec![0.1; 10],
            depths: vec![0.0; 10],
            distances: (0..10).map(|i| i as f32 * 0.1).collect(),
        };
        let mut surface = vec![0.0f32; 10];
        surface[4] = 100.0;
        let haze = vec![2.3f32; 10];
        let (l_surface, _) = loss_and_grad(&surface, &rays);
        let (l_haze, _) = loss_and_grad(&haze, &rays);
        assert!(l_surface < 0.2 * l_haze, "{l_surface} vs {l_haze}");

        let dev = Device::Cpu;
        let sigma = Var::from_vec(haze.clone(), 10, &dev).unwrap();
        let loss = distortion_loss(sigma.as_tensor(), &rays).unwrap();
        let value = loss.to_scalar::<f32>().unwrap() as f64;
        assert!((value - l_haze).abs() < 1e-5 * l_haze.max(1.0));
        let g: Vec<f32> = loss
            .backward()
            .unwrap()
            .get(&sigma)
            .unwrap()
            .to_vec1()
            .unwrap();
        let (_, expected) = loss_and_grad(&haze, &rays);
        for (a, b) in g.iter().zip(&expected) {
            assert!((*a as f64 - b).abs() < 1e-5, "{a} vs {b}");
        }
    }
}
