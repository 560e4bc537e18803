//! The depth-supervision loss of DS-NeRF ("Depth-supervised NeRF", CVPR 2022), as
//! depth-nerfacto uses it: on a ray whose pixel has a known depth `d`, the cross-entropy
//! `L = −Σ_k h_k log(w_k + ε)` between a target distribution `h` over the ray's samples — a
//! Gaussian around `d` (standard deviation `s = SPREAD · d`), weighted by each sample's
//! interval — and the compositing weights `w`. It rewards weight near `d` and nothing else:
//! unlike a loss on the expected depth `Σ w_k z_k`, which a ray can raise by putting density
//! anywhere beyond the surface, it gives no reason for density away from the known surface.
//! A ray with no sample within 3 s of `d` (its surface not marched, the occupancy grid having
//! skipped it) carries no loss.

use candle_core::Tensor;

use super::weight_loss::weight_loss;
use crate::rays::PackedRays;
use crate::Result;

/// The target's standard deviation as a fraction of the known depth (about what structure
/// from motion's points are accurate to, and a few sample steps at the working resolution).
pub const SPREAD: f64 = 0.02;

/// Keeps `log w` finite where a weight is 0.
const EPSILON: f64 = 1e-5;

/// Mean loss over the rays with a known depth (`known[r] > 0`, z-depth as `rays.depths`) and a
/// sample near it, differentiable in σ [S]; `None` when there is no such ray.
pub fn depth_supervision_loss(
    sigma: &Tensor,
    rays: &PackedRays,
    known: &[f32],
) -> Result<Option<Tensor>> {
    let targets: Vec<Option<Vec<f64>>> = (0..rays.num_rays())
        .map(|r| target(rays, r, known[r]))
        .collect();
    let counted = targets.iter().flatten().count();
    if counted == 0 {
        return Ok(None);
    }
    let loss = weight_loss(sigma, rays, counted as f64, |r, _, w, g| {
        cross_entropy(targets[r].as_deref(), w, g)
    })?;
    Ok(Some(loss))
}

/// Ray `r`'s target distribution over its samples, if its depth `d` is known and a sample lies
/// within 3 s of it.
fn target(rays: &PackedRays, r: usize, d: f32) -> Option<Vec<f64>> {
    if d <= 0.0 {
        return None;
    }
    let (d, range) = (
        d as f64,
        rays.offsets[r] as usize..rays.offsets[r + 1] as usize,
    );
    let s = SPREAD * d;
    let near = range
        .clone()
        .any(|k| (rays.depths[k] as f64 - d).abs() <= 3.0 * s);
    if !near {
        return None;
    }
    let h: Vec<f64> = range
        .map(|k| {
            let z = (rays.depths[k] as f64 - d) / s;
            (-0.5 * z * z).exp() * rays.deltas[k] as f64
        })
        .collect();
    let sum: f64 = h.iter().sum();
    Some(h.into_iter().map(|x| x / sum).collect())
}

/// `−Σ h log(w + ε)`, writing `∂L/∂w` into `g`; 0 without a target.
fn cross_entropy(h: Option<&[f64]>, w: &[f64], g: &mut [f64]) -> f64 {
    let Some(h) = h else {
        return 0.0;
    };
    let mut total = 0.0;
    for ((hk, wk), gk) in h.iter().zip(w).zip(g) {
        total -= hk * (wk + EPSILON).ln();
        *gk = -hk / (wk + EPSILON);
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::weight_loss::loss_and_grad;
    use crate::rng::Rng;
    use candle_core::{Device, Var};

    /// Three rays of 12 samples 0.1 apart from z = 1: known depths 1.5, unknown, 1.8.
    fn rays() -> (PackedRays, Vec<f32>) {
        let mut rays = PackedRays {
            offsets: vec![0],
            ..Default::default()
        };
        for _ in 0..3 {
            for i in 0..12 {
                let z = 1.0 + 0.1 * i as f32;
                rays.deltas.push(0.1);
                rays.distances.push(z);
                rays.depths.push(z);
            }
            let last = *rays.offsets.last().unwrap();
            rays.offsets.push(last + 12);
        }
        (rays, vec![1.5, 0.0, 1.8])
    }

    fn host(sigma: &[f32], rays: &PackedRays, known: &[f32]) -> (f64, Vec<f64>) {
        loss_and_grad(sigma, rays, |r, _, w, g| {
            cross_entropy(target(rays, r, known[r]).as_deref(), w, g)
        })
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let (rays, known) = rays();
        let mut rng = Rng::new(5);
        let sigma: Vec<f32> = (0..rays.num_samples())
            .map(|_| 6.0 * rng.uniform())
            .collect();
        let (_, grad) = host(&sigma, &rays, &known);
        for k in 0..sigma.len() {
            let h = 1e-2f32;
            let (mut plus, mut minus) = (sigma.clone(), sigma.clone());
            plus[k] += h;
            minus[k] -= h;
            let fd =
                (host(&plus, &rays, &known).0 - host(&minus, &rays, &known).0) / (2.0 * h as f64);
            assert!(
                (fd - grad[k]).abs() < 1e-3 * (1.0 + fd.abs()),
                "sample {k}: finite difference {fd}, analytic {}",
                grad[k]
            );
        }
        // The ray without a known depth has no gradient.
        assert!(grad[12..24].iter().all(|&g| g == 0.0));
    }

    #[test]
    fn a_surface_at_the_known_depth_costs_least_and_density_beyond_it_is_not_rewarded() {
        let (rays, known) = rays();
        let known = [known[0], 0.0, 0.0];
        let loss = |sigma: &[f32]| host(sigma, &rays, &known).0;
        // Ray 0's sample 5 is at z = 1.5.
        let mut at = vec![0.0f32; 36];
        at[5] = 60.0;
        let mut before = vec![0.0f32; 36];
        before[2] = 60.0;
        let mut beyond = vec![0.0f32; 36];
        beyond[10] = 60.0;
        let haze = [vec![0.8f32; 12], vec![0.0; 24]].concat();
        let (l_at, l_before, l_beyond, l_haze) =
            (loss(&at), loss(&before), loss(&beyond), loss(&haze));
        assert!(
            l_at < 0.5 * l_before.min(l_beyond).min(l_haze),
            "{l_at} {l_before} {l_beyond} {l_haze}"
        );
        // Density far beyond the surface, on a transparent ray, does not lower the loss (an
        // expected-depth loss would reward it: it raises Σ w z towards d).
        let mut far = vec![0.0f32; 36];
        far[11] = 60.0;
        let empty = vec![0.0f32; 36];
        assert!(
            loss(&far) >= loss(&empty) - 1e-9,
            "{} vs {}",
            loss(&far),
            loss(&empty)
        );
    }

    #[test]
    fn the_tensor_carries_the_mean_loss_and_its_gradient() {
        let (rays, known) = rays();
        let sigma: Vec<f32> = (0..36).map(|i| (i % 7) as f32 * 0.5).collect();
        let var = Var::from_vec(sigma.clone(), 36, &Device::Cpu).unwrap();
        let loss = depth_supervision_loss(var.as_tensor(), &rays, &known)
            .unwrap()
            .unwrap();
        let (sum, grad) = host(&sigma, &rays, &known);
        // Two rays have a known depth.
        let value = loss.to_scalar::<f32>().unwrap() as f64;
        assert!(
            (value - sum / 2.0).abs() < 1e-4 * sum.max(1.0),
            "{value} vs {sum}"
        );
        let g: Vec<f32> = loss
            .backward()
            .unwrap()
            .get(&var)
            .unwrap()
            .to_vec1()
            .unwrap();
        for (a, b) in g.iter().zip(&grad) {
            assert!((*a as f64 - b / 2.0).abs() < 1e-4, "{a} vs {b}");
        }
        assert!(depth_supervision_loss(var.as_tensor(), &rays, &[0.0; 3])
            .unwrap()
            .is_none());
    }
}
