//! Rendered depth graded against a dataset's ground-truth depth: `nerf_pretrain` on its test
//! views, `render_views` on the training views it carries the truth onto.
//!
//! Pixels where the truth sees a surface and the render is opaque (> 0.5) are graded: absolute
//! error, and the error relative to the true depth. Pixels where a dense map sees nothing
//! (depth 0: a background at infinity) measure the opacity the field left there (haze); in a
//! sparse map (under [`DENSE`] of its pixels known: points from structure from motion) a 0 is
//! only unknown, and measures nothing.

use serde::{Deserialize, Serialize};

/// The fraction of known pixels from which a depth map's zeros are taken as a background at
/// infinity (a generated sky is under half of a view; structure from motion knows a few
/// percent of the pixels).
pub const DENSE: f64 = 0.1;

/// Running tallies over the frames of one evaluation.
#[derive(Debug, Default)]
pub struct DepthErrors {
    abs_sum: f64,
    relative: Vec<f32>,
    empty_opacity: f64,
    empty: usize,
}

/// What [`DepthErrors`] measured.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DepthSummary {
    /// Graded pixels (truth > 0, rendered opacity > 0.5).
    pub pixels: usize,
    /// Mean absolute error (world units).
    pub mae: f64,
    /// Median and 90th percentile of |d − g| / g.
    pub median_relative: f64,
    pub p90_relative: f64,
    /// Fraction of graded pixels more than 5 % off: surfaces put in the wrong place, as at
    /// silhouettes, rather than noise.
    pub over_5_percent: f64,
}

impl DepthErrors {
    /// Adds one frame: rendered depth and opacity and the true depth, row-major alike.
    pub fn add(&mut self, depth: &[f32], opacity: &[f32], truth: &[f32]) {
        let known = truth.iter().filter(|&&g| g > 0.0).count();
        let dense = known as f64 >= DENSE * truth.len() as f64;
        for ((d, o), g) in depth.iter().zip(opacity).zip(truth) {
            if *o > 0.5 && *g > 0.0 {
                self.abs_sum += f64::from((d - g).abs());
                self.relative.push(((d - g) / g).abs());
            } else if *g == 0.0 && dense {
                self.empty_opacity += f64::from(*o);
                self.empty += 1;
            }
        }
    }

    /// The errors over every graded pixel, `None` without any.
    pub fn summary(&self) -> Option<DepthSummary> {
        let mut relative = self.relative.clone();
        relative.sort_by(f32::total_cmp);
        let n = relative.len();
        let at = |q: f64| f64::from(relative[((q * n as f64) as usize).min(n - 1)]);
        (n > 0).then(|| DepthSummary {
            pixels: n,
            mae: self.abs_sum / n as f64,
            median_relative: at(0.5),
            p90_relative: at(0.9),
            over_5_percent: (n - relative.partition_point(|&r| r <= 0.05)) as f64 / n as f64,
        })
    }

    /// Mean opacity where the truth sees nothing, `None` without such pixels.
    pub fn empty_opacity(&self) -> Option<f64> {
        (self.empty > 0).then(|| self.empty_opacity / self.empty as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grades_opaque_pixels_and_measures_haze_where_the_truth_is_empty() {
        let mut e = DepthErrors::default();
        assert_eq!(e.summary(), None);
        // Four graded pixels (errors 0, 1 %, 2 %, 10 %), one transparent render (skipped),
        // two empty truths with haze 0.1 and 0.3.
        e.add(
            &[1.0, 2.02, 3.06, 4.4, 9.0, 5.0, 5.0],
            &[1.0, 0.9, 0.8, 0.6, 0.2, 0.1, 0.3],
            &[1.0, 2.0, 3.0, 4.0, 2.0, 0.0, 0.0],
        );
        let s = e.summary().unwrap();
        assert_eq!(s.pixels, 4);
        assert!(
            (s.mae - (0.0 + 0.02 + 0.06 + 0.4) / 4.0).abs() < 1e-6,
            "{s:?}"
        );
        assert!((s.median_relative - 0.02).abs() < 1e-6, "{s:?}");
        assert!((s.p90_relative - 0.1).abs() < 1e-6, "{s:?}");
        assert_eq!(s.over_5_percent, 0.25);
        assert!((e.empty_opacity().unwrap() - 0.2).abs() < 1e-6);
        // A sparse map's zeros are unknown, not empty: graded where known, no haze counted.
        let mut sparse = DepthErrors::default();
        let mut truth = vec![0.0; 20];
        truth[3] = 2.0;
        sparse.add(&[2.0; 20], &[1.0; 20], &truth);
        assert_eq!(sparse.summary().unwrap().pixels, 1);
        assert_eq!(sparse.empty_opacity(), None);
    }
}
