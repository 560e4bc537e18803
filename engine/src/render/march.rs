//! Ray marching: fixed-size steps along each ray inside the scene box, keeping only samples in
//! occupied cells, packed ray after ray (the ray and sample types are in [`crate::rays`]).

use glam::Vec3;

use crate::field::occupancy::OccupancyGrid;
use crate::field::space::Contraction;
use crate::rays::{PackedRays, RayBatch, Samples};
use crate::rng::Rng;

/// Marches every ray with step `step` from max(near, box entry) to min(far, box exit), keeping
/// at most `max_samples` samples per ray in occupied cells. With `jitter`, each ray's first
/// sample is offset by a random fraction of a step (training); without, samples sit at the
/// step centres (deterministic rendering). With a `contraction` the rays are world rays
/// marched through all of contracted space (see [`crate::field::space`]): `step` is then a
/// contracted length, and sample positions and deltas are contracted.
pub fn march(
    rays: &RayBatch,
    grid: &OccupancyGrid,
    contraction: Option<&Contraction>,
    step: f32,
    max_samples: usize,
    mut jitter: Option<&mut Rng>,
) -> Samples {
    let mut out = Samples {
        packed: PackedRays {
            offsets: Vec::with_capacity(rays.len() + 1),
            ..Default::default()
        },
        ..Default::default()
    };
    out.packed.offsets.push(0);
    let push = |out: &mut Samples, r: usize, p: Vec3, delta: f32, t: f32, distance: f32| {
        out.positions.extend_from_slice(&[p.x, p.y, p.z]);
        out.ray.push(r as u32);
        out.packed.deltas.push(delta);
        out.packed.depths.push(rays.depth[r].depth(t));
        out.packed.distances.push(distance);
    };
    for r in 0..rays.len() {
        let (o, d) = (rays.origins[r], rays.dirs[r]);
        let offset = jitter.as_mut().map_or(0.5, |rng| rng.uniform());
        let mut count = 0;
        match contraction {
            None => {
                if let Some((t0, t1)) = grid.aabb.intersect(o, d) {
                    let (t0, t1) = (t0.max(rays.near), t1.min(rays.far));
                    let mut t = t0 + offset * step;
                    while t < t1 && count < max_samples {
                        let p = o + t * d;
                        if grid.is_occupied(p) {
                            let len = d.length();
                            push(&mut out, r, p, step * len, t, t * len);
                            count += 1;
                        }
                        t += step;
                    }
                }
            }
            Some(c) => {
                let dir_len = d.length();
                let (_, n0) = c.normalise(o + rays.near * d);
                let mut t = rays.near + offset * c.world_step(step, n0, dir_len);
                let (mut x, mut n) = c.normalise(o + t * d);
                let mut distance = 0.0;
                while t < rays.far && n < Contraction::REACH && count < max_samples {
                    let p = Contraction::contract(x, n);
                    let next_t = t + c.world_step(step, n, dir_len);
                    let (next_x, next_n) = c.normalise(o + next_t * d);
                    let next = if next_t.is_finite() {
                        Contraction::contract(next_x, next_n)
                    } else {
                        // The last step reaches the edge of contracted space.
                        p * (2.0 / p.abs().max_element())
                    };
                    let delta = (next - p).length();
                    if grid.is_occupied(p) {
                        push(&mut out, r, p, delta, t, distance);
                        count += 1;
                    }
                    distance += delta;
                    (t, x, n) = (next_t, next_x, next_n);
                }
            }
        }
        out.packed.offsets.push(out.ray.len() as u32);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Intrinsics};
    use crate::scene::Aabb;

    #[test]
    fn samples_stay_in_box_and_occupied_cells() {
        let aabb = Aabb {
            min: Vec3::splat(-1.0),
            max: Vec3::splat(1.0),
        };
        let mut grid = OccupancyGrid::new(8, aabb);
        // Only the cells with x > 0 are occupied.
        grid.update(
            |p| {
                Ok(p.chunks_exact(3)
                    .map(|p| if p[0] > 0.0 { 100.0 } else { 0.0 })
                    .collect())
            },
            &mut Rng::new(1),
            usize::MAX,
            0.95,
            1.0,
        )
        .unwrap();
        let k = Intrinsics {
            fx: 20.0,
            fy: 20.0,
            cx: 8.0,
            cy: 8.0,
            width: 16,
            height: 16,
        };
        let cam = Camera::look_at(k, Vec3::new(0.3, 0.2, 4.0), Vec3::ZERO, Vec3::Y);
        let mut rays = RayBatch {
            near: 0.0,
            far: 10.0,
            ..Default::default()
        };
        for y in 0..16 {
            for x in 0..16 {
                rays.push(&cam.pixel_ray(x, y), None);
            }
        }
        let s = march(&rays, &grid, None, 0.05, 1000, None);
        assert!(!s.ray.is_empty());
        for p in s.positions.chunks_exact(3) {
            assert!(
                p[0] > -1e-6 && p.iter().all(|v| v.abs() <= 1.0 + 1e-5),
                "{p:?}"
            );
        }
        // Depth of a sample equals its camera z-depth.
        let k0 = 0;
        let p = Vec3::from_slice(&s.positions[0..3]);
        let (_, _, z) = cam.project(p);
        assert!((s.packed.depths[k0] - z).abs() < 1e-4);
    }

    #[test]
    fn contracted_marching_reaches_far_surroundings_in_few_steps() {
        use crate::field::space::Contraction;
        let c = Contraction {
            centre: Vec3::ZERO,
            half: 1.0,
        };
        let grid = OccupancyGrid::new(16, Contraction::BOX);
        let k = Intrinsics {
            fx: 8.0,
            fy: 8.0,
            cx: 4.0,
            cy: 4.0,
            width: 8,
            height: 8,
        };
        let cam = Camera::look_at(
            k,
            Vec3::new(0.0, 0.0, 0.5),
            Vec3::new(0.0, 0.0, -5.0),
            Vec3::Y,
        );
        let rays = RayBatch::for_camera(&cam, None, 0.01, 1e4);
        let step = 0.02;
        let s = march(&rays, &grid, Some(&c), step, 10_000, None);
        for (r, w) in s.packed.offsets.windows(2).enumerate() {
            let range = w[0] as usize..w[1] as usize;
            // Every position is contracted; the ray reaches past 25 box half-sizes (the last
            // whole step before the edge of contracted space)…
            for k in range.clone() {
                let p = Vec3::from_slice(&s.positions[3 * k..3 * k + 3]);
                assert!(p.abs().max_element() < 2.0, "{p}");
            }
            let last = range.end - 1;
            let z = s.packed.depths[last];
            assert!(z > 25.0, "ray {r} stops at z-depth {z}");
            // …in about (contracted length / step) samples of about `step` each: 1.5 inside the
            // unit cube (more for oblique rays) and 1 beyond.
            let n = range.len() as f32;
            assert!(n < 3.5 / step, "{n} samples");
            let total: f32 = range.clone().map(|k| s.packed.deltas[k]).sum();
            assert!((s.packed.distances[last] + s.packed.deltas[last] - total).abs() < 1e-3);
            assert!(range.clone().all(|k| s.packed.deltas[k] < 1.6 * step));
            // Depth is the world z-depth of the sample.
            let first = Vec3::from_slice(&s.positions[3 * range.start..3 * range.start + 3]);
            let (_, _, z0) = cam.project(first); // inside the unit cube: contracted = world
            assert!((s.packed.depths[range.start] - z0).abs() < 1e-4);
        }
    }
}
