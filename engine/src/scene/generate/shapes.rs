//! The generator's primitives and their ray intersections: spheres, yawed boxes, vertical
//! capped cylinders, tori (sphere-traced inside a bounding sphere) and a finite floor square.
//!
//! Every hit reports its point in the object's own frame, so textures stick to the object.

use glam::{Mat3, Vec3};

/// Rays start this far from surfaces they leave (shadow rays), to avoid self-hits.
pub(crate) const EPS: f32 = 1e-4;

/// A ray–surface intersection.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Hit {
    /// Distance along the (unit) ray direction.
    pub t: f32,
    /// Unit surface normal in world space, facing the ray origin's side for the floor.
    pub normal: Vec3,
    /// The hit point and normal in the object's frame (texture coordinates).
    pub local: Vec3,
    pub local_normal: Vec3,
}

#[derive(Debug, Clone)]
pub(crate) enum Shape {
    Sphere {
        centre: Vec3,
        radius: f32,
    },
    /// A box rotated about the vertical axis; `to_world` maps local to world directions.
    Cuboid {
        centre: Vec3,
        half: Vec3,
        to_world: Mat3,
    },
    /// A vertical capped cylinder standing on `base`.
    Cylinder {
        base: Vec3,
        radius: f32,
        height: f32,
    },
    /// A torus around its local y axis.
    Torus {
        centre: Vec3,
        to_world: Mat3,
        major: f32,
        minor: f32,
    },
    /// The square |x|, |z| ≤ `half` at height `y`.
    Floor {
        y: f32,
        half: f32,
    },
}

impl Shape {
    /// The nearest intersection with t in (EPS, t_max).
    pub fn intersect(&self, o: Vec3, d: Vec3, t_max: f32) -> Option<Hit> {
        let hit = match *self {
            Shape::Sphere { centre, radius } => sphere(o - centre, d, radius).map(|t| {
                let local = o - centre + t * d;
                let n = local / radius;
                (t, local, n, n)
            }),
            Shape::Cuboid {
                centre,
                half,
                to_world,
            } => {
                let to_local = to_world.transpose();
                cuboid(to_local * (o - centre), to_local * d, half)
                    .map(|(t, local, n)| (t, local, n, to_world * n))
            }
            Shape::Cylinder {
                base,
                radius,
                height,
            } => cylinder(o - base, d, radius, height).map(|(t, local, n)| (t, local, n, n)),
            Shape::Torus {
                centre,
                to_world,
                major,
                minor,
            } => {
                let to_local = to_world.transpose();
                torus(to_local * (o - centre), to_local * d, major, minor, t_max)
                    .map(|(t, local, n)| (t, local, n, to_world * n))
            }
            Shape::Floor { y, half } => {
                let t = (y - o.y) / d.y;
                let p = o + t * d;
                (t.is_finite() && p.x.abs() <= half && p.z.abs() <= half).then(|| {
                    let n = Vec3::new(0.0, -d.y.signum(), 0.0);
                    (t, p, Vec3::Y, n)
                })
            }
        }?;
        let (t, local, local_normal, normal) = hit;
        (t > EPS && t < t_max).then_some(Hit {
            t,
            normal,
            local,
            local_normal,
        })
    }
}

/// Nearest positive root of |o + t d| = r (unit d).
fn sphere(o: Vec3, d: Vec3, r: f32) -> Option<f32> {
    let b = o.dot(d);
    let disc = b * b - (o.length_squared() - r * r);
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    [-b - s, -b + s].into_iter().find(|&t| t > EPS)
}

/// Slab test against the box |x| ≤ half; returns t, local point, local normal.
fn cuboid(o: Vec3, d: Vec3, half: Vec3) -> Option<(f32, Vec3, Vec3)> {
    let inv = d.recip();
    let t1 = (-half - o) * inv;
    let t2 = (half - o) * inv;
    let (lo, hi) = (t1.min(t2), t1.max(t2));
    let (t_near, t_far) = (lo.max_element(), hi.min_element());
    if t_near > t_far || t_far <= EPS {
        return None;
    }
    let (t, faces) = if t_near > EPS {
        (t_near, lo)
    } else {
        (t_far, hi)
    };
    let axis = (0..3)
        .min_by(|&a, &b| (faces[a] - t).abs().total_cmp(&(faces[b] - t).abs()))
        .unwrap_or(0);
    let p = o + t * d;
    let mut n = Vec3::ZERO;
    n[axis] = p[axis].signum();
    Some((t, p, n))
}

/// Vertical cylinder of `radius` from y = 0 to `height`, with caps.
fn cylinder(o: Vec3, d: Vec3, r: f32, height: f32) -> Option<(f32, Vec3, Vec3)> {
    let mut best: Option<(f32, Vec3)> = None;
    let mut consider = |t: f32, n: Vec3| {
        if t > EPS && best.is_none_or(|(b, _)| t < b) {
            best = Some((t, n));
        }
    };
    let a = d.x * d.x + d.z * d.z;
    if a > 1e-12 {
        let b = o.x * d.x + o.z * d.z;
        let c = o.x * o.x + o.z * o.z - r * r;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            for t in [(-b - disc.sqrt()) / a, (-b + disc.sqrt()) / a] {
                let p = o + t * d;
                if (0.0..=height).contains(&p.y) {
                    consider(t, Vec3::new(p.x, 0.0, p.z) / r);
                }
            }
        }
    }
    for (y, n) in [(height, Vec3::Y), (0.0, Vec3::NEG_Y)] {
        let t = (y - o.y) / d.y;
        let p = o + t * d;
        if t.is_finite() && p.x * p.x + p.z * p.z <= r * r {
            consider(t, n);
        }
    }
    best.map(|(t, n)| (t, o + t * d, n))
}

/// Sphere tracing of the torus (major radius `big`, tube radius `small`) around local y.
fn torus(o: Vec3, d: Vec3, big: f32, small: f32, t_max: f32) -> Option<(f32, Vec3, Vec3)> {
    let bound = big + small;
    let b = o.dot(d);
    let disc = b * b - (o.length_squared() - bound * bound);
    if disc < 0.0 {
        return None;
    }
    let mut t = (-b - disc.sqrt()).max(0.0);
    let t_exit = (-b + disc.sqrt()).min(t_max);
    let sdf = |p: Vec3| {
        let q = (p.x * p.x + p.z * p.z).sqrt() - big;
        (q * q + p.y * p.y).sqrt() - small
    };
    for _ in 0..256 {
        let p = o + t * d;
        let dist = sdf(p);
        if dist < 1e-5 {
            let ring = Vec3::new(p.x, 0.0, p.z).normalize_or_zero() * big;
            return Some((t, p, (p - ring).normalize()));
        }
        t += dist;
        if t > t_exit {
            return None;
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(shape: &Shape, o: Vec3, d: Vec3, expect_t: f32, expect_n: Vec3) {
        let h = shape
            .intersect(o, d.normalize(), f32::INFINITY)
            .expect("hit");
        assert!((h.t - expect_t).abs() < 1e-3, "t {} vs {expect_t}", h.t);
        assert!(
            (h.normal - expect_n).length() < 1e-3,
            "n {} vs {expect_n}",
            h.normal
        );
    }

    #[test]
    fn primitives_hit_where_expected() {
        let o = Vec3::new(0.0, 0.5, 5.0);
        let d = Vec3::NEG_Z;
        check(
            &Shape::Sphere {
                centre: Vec3::new(0.0, 0.5, 0.0),
                radius: 1.0,
            },
            o,
            d,
            4.0,
            Vec3::Z,
        );
        let rot = Mat3::from_rotation_y(std::f32::consts::FRAC_PI_2);
        let cuboid = Shape::Cuboid {
            centre: Vec3::ZERO,
            half: Vec3::new(2.0, 1.0, 0.5),
            to_world: rot,
        };
        check(&cuboid, o, d, 3.0, Vec3::Z);
        let cyl = Shape::Cylinder {
            base: Vec3::ZERO,
            radius: 0.5,
            height: 1.0,
        };
        check(&cyl, o, d, 4.5, Vec3::Z);
        check(&cyl, Vec3::new(0.0, 3.0, 0.0), Vec3::NEG_Y, 2.0, Vec3::Y);
        let torus = Shape::Torus {
            centre: Vec3::ZERO,
            to_world: Mat3::IDENTITY,
            major: 1.0,
            minor: 0.25,
        };
        check(&torus, Vec3::new(0.0, 0.0, 5.0), d, 3.75, Vec3::Z);
        let floor = Shape::Floor { y: -1.0, half: 1.0 };
        check(&floor, Vec3::new(0.5, 1.0, 0.0), Vec3::NEG_Y, 2.0, Vec3::Y);
        assert!(floor
            .intersect(Vec3::new(1.5, 1.0, 0.0), Vec3::NEG_Y, f32::INFINITY)
            .is_none());
    }
}
