//! Occupancy grid: a coarse voxel grid over the scene box that marks where density is
//! non-negligible, so ray marching skips empty space. Each cell keeps an exponential moving
//! maximum of the density sampled inside it (as in instant-ngp); a cell is occupied while that
//! value makes a step's opacity exceed a small threshold.

use glam::Vec3;

use crate::rng::Rng;
use crate::scene::Aabb;
use crate::Result;

#[derive(Debug, Clone)]
pub struct OccupancyGrid {
    pub resolution: usize,
    pub aabb: Aabb,
    /// Moving maximum of the density per cell (x fastest, then y, then z).
    pub density: Vec<f32>,
    occupied: Vec<bool>,
}

impl OccupancyGrid {
    /// A grid where every cell starts occupied.
    pub fn new(resolution: usize, aabb: Aabb) -> Self {
        let n = resolution.pow(3);
        Self {
            resolution,
            aabb,
            density: vec![f32::MAX; n],
            occupied: vec![true; n],
        }
    }

    /// Rebuilds a grid from saved densities (checkpoints), thresholding them again.
    pub fn from_density(
        resolution: usize,
        aabb: Aabb,
        density: Vec<f32>,
        sigma_threshold: f32,
    ) -> Self {
        let mut grid = Self::new(resolution, aabb);
        grid.density = density;
        grid.rethreshold(sigma_threshold);
        grid
    }

    /// Index of the cell containing `p`, or `None` outside the box.
    #[inline]
    pub fn cell(&self, p: Vec3) -> Option<usize> {
        let u = (p - self.aabb.min) / self.aabb.size() * self.resolution as f32;
        if u.min_element() < 0.0 || u.max_element() >= self.resolution as f32 {
            return None;
        }
        let r = self.resolution;
        Some(u.x as usize + r * (u.y as usize + r * u.z as usize))
    }

    #[inline]
    pub fn is_occupied(&self, p: Vec3) -> bool {
        self.cell(p).is_some_and(|c| self.occupied[c])
    }

    /// Fraction of occupied cells.
    pub fn occupied_fraction(&self) -> f32 {
        self.occupied.iter().filter(|&&o| o).count() as f32 / self.occupied.len() as f32
    }

    /// Samples the density at one jittered point in `count` random cells (all cells when
    /// `count` ≥ the number of cells), decays the moving maximum and re-thresholds.
    /// `density` maps packed positions [N·3] in field space to σ [N].
    pub fn update(
        &mut self,
        density: impl Fn(&[f32]) -> Result<Vec<f32>>,
        rng: &mut Rng,
        count: usize,
        decay: f32,
        sigma_threshold: f32,
    ) -> Result<()> {
        let n = self.density.len();
        let cells: Vec<usize> = if count >= n {
            (0..n).collect()
        } else {
            (0..count).map(|_| rng.below(n)).collect()
        };
        let r = self.resolution;
        let cell_size = self.aabb.size() / r as f32;
        let mut points = Vec::with_capacity(cells.len() * 3);
        for &c in &cells {
            let (x, y, z) = (c % r, (c / r) % r, c / (r * r));
            let p = self.aabb.min
                + (Vec3::new(x as f32, y as f32, z as f32)
                    + Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()))
                    * cell_size;
            points.extend_from_slice(&[p.x, p.y, p.z]);
        }
        let sigma = density(&points)?;
        for d in self.density.iter_mut().filter(|d| **d != f32::MAX) {
            *d *= decay;
        }
        // Cells never sampled keep their "unknown" marker; first samples replace it.
        for (&c, &s) in cells.iter().zip(&sigma) {
            let d = &mut self.density[c];
            *d = if *d == f32::MAX { s } else { d.max(s) };
        }
        self.rethreshold(sigma_threshold);
        Ok(())
    }

    fn rethreshold(&mut self, sigma_threshold: f32) {
        let known: Vec<f32> = self
            .density
            .iter()
            .copied()
            .filter(|&d| d != f32::MAX)
            .collect();
        let mean = if known.is_empty() {
            0.0
        } else {
            known.iter().sum::<f32>() / known.len() as f32
        };
        let threshold = sigma_threshold.min(mean);
        for (o, &d) in self.occupied.iter_mut().zip(&self.density) {
            *o = d > threshold;
        }
    }
}
