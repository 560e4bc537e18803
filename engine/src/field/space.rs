//! Where a field lives: the box its encoding and occupancy grid cover, and, for unbounded
//! captures, the contraction that maps all of world space into that box (mip-NeRF 360's
//! scene contraction with the L∞ norm, as nerfacto uses for hash grids).
//!
//! With a contraction, world points are first normalised to the content box (the box's centre
//! at 0, its faces at ±1) and then contracted: x stays x inside the unit cube and becomes
//! (2 − 1/‖x‖∞) · x/‖x‖∞ outside, so everything lies in (−2, 2)³. Marching takes equal steps
//! in contracted space — steps grow with the square of the distance outside the box — and
//! compositing uses contracted lengths, so density is per unit of contracted length whatever
//! the capture's scale. Space past [`Contraction::REACH`] box half-sizes is left to the
//! learned background.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::scene::{Aabb, Background, Scene};

/// Scene contraction around a content box.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Contraction {
    /// Centre of the content box (world units).
    pub centre: Vec3,
    /// Half of the content box's longest side (world units): the unit of normalised space.
    pub half: f32,
}

impl Contraction {
    /// Marching stops where ‖x‖∞ reaches this many box half-sizes (contracted radius 1.99).
    pub const REACH: f32 = 100.0;

    /// The box contracted space fills.
    pub const BOX: Aabb = Aabb {
        min: Vec3::splat(-2.0),
        max: Vec3::splat(2.0),
    };

    /// The contraction around `aabb` (its longest side sets the scale, so the unit region is a
    /// cube containing the box).
    pub fn around(aabb: &Aabb) -> Self {
        Self {
            centre: aabb.center(),
            half: aabb.size().max_element() * 0.5,
        }
    }

    /// Normalised position of a world point and its L∞ norm.
    #[inline]
    pub fn normalise(&self, world: Vec3) -> (Vec3, f32) {
        let x = (world - self.centre) / self.half;
        (x, x.abs().max_element())
    }

    /// The contracted position of a normalised point with L∞ norm `norm`.
    #[inline]
    pub fn contract(x: Vec3, norm: f32) -> Vec3 {
        if norm <= 1.0 {
            x
        } else {
            x * ((2.0 - 1.0 / norm) / norm)
        }
    }

    /// Contracted position of a world point.
    #[inline]
    pub fn apply(&self, world: Vec3) -> Vec3 {
        let (x, n) = self.normalise(world);
        Self::contract(x, n)
    }

    /// World distance of a contracted step of length `step` taken at L∞ norm `norm` along a
    /// ray whose direction has length `dir_len`, exact for rays moving straight away from the
    /// centre: outside the unit cube the contracted radius is 2 − 1/‖x‖, so the step ends where
    /// 1/‖x‖ has dropped by `step`. Infinite when that is past [`Contraction::REACH`].
    #[inline]
    pub fn world_step(&self, step: f32, norm: f32, dir_len: f32) -> f32 {
        if norm <= 1.0 {
            return step * self.half / dir_len;
        }
        let inv = 1.0 / norm - step;
        if inv <= 1.0 / Self::REACH {
            return f32::INFINITY;
        }
        (1.0 / inv - norm) * self.half / dir_len
    }

    /// The normalised L∞ norm of a contracted point (the inverse of the radial map).
    #[inline]
    pub fn norm_of_contracted(p: Vec3) -> f32 {
        let r = p.abs().max_element();
        if r <= 1.0 {
            r
        } else {
            1.0 / (2.0 - r).max(1.0 / Self::REACH)
        }
    }
}

/// Where a field lives and what lies behind it; saved with the field.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FieldSpace {
    /// The box the encoding and the occupancy grid cover, in field space: world, NDC, or
    /// contracted ([`Contraction::BOX`]).
    pub aabb: Aabb,
    /// Set for unbounded captures: world points are contracted into `aabb`.
    pub contraction: Option<Contraction>,
    pub background: Background,
}

impl FieldSpace {
    /// The space a field for `scene` works in.
    pub fn for_scene(scene: &Scene) -> Self {
        if scene.unbounded {
            Self {
                aabb: Contraction::BOX,
                contraction: Some(Contraction::around(&scene.aabb)),
                background: scene.background,
            }
        } else {
            Self {
                aabb: scene.aabb,
                contraction: None,
                background: scene.background,
            }
        }
    }

    /// Largest extent of the content, in world units (for relative depth errors).
    pub fn content_extent(&self) -> f32 {
        match self.contraction {
            Some(c) => 2.0 * c.half,
            None => self.aabb.size().max_element(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contraction_is_identity_inside_and_bounded_outside() {
        let c = Contraction {
            centre: Vec3::new(1.0, 2.0, 3.0),
            half: 2.0,
        };
        let inside = Vec3::new(2.0, 3.0, 2.0);
        assert!((c.apply(inside) - Vec3::new(0.5, 0.5, -0.5)).length() < 1e-6);
        for far in [10.0f32, 1e3, 1e6] {
            let p = c.apply(Vec3::new(far, -far * 0.5, 0.0));
            assert!(p.abs().max_element() < 2.0, "{p}");
            assert!(p.abs().max_element() > 2.0 - 2.0 * 2.0 / far);
        }
        // Continuous at the unit cube's faces, and the norm inverts the radial map.
        let on = Vec3::new(1.0, 0.3, -0.2);
        assert!((Contraction::contract(on * 1.0001, 1.0001) - on).length() < 1e-3);
        for n in [0.5f32, 1.0, 3.0, 50.0] {
            let x = Vec3::new(n, n * 0.2, -n * 0.7);
            let p = Contraction::contract(x, n);
            assert!((Contraction::norm_of_contracted(p) - n).abs() < 1e-3 * n.max(1.0));
        }
    }

    #[test]
    fn world_steps_give_equal_contracted_steps_along_radial_rays() {
        let c = Contraction {
            centre: Vec3::ZERO,
            half: 1.0,
        };
        let step = 0.01;
        for start in [0.2f32, 1.5, 7.0, 40.0] {
            let p = Vec3::new(start, 0.0, 0.0);
            let (_, n) = c.normalise(p);
            let dt = c.world_step(step, n, 1.0);
            let moved = (c.apply(p + Vec3::X * dt) - c.apply(p)).length();
            assert!((moved / step - 1.0).abs() < 0.02, "start {start}: {moved}");
        }
    }
}
