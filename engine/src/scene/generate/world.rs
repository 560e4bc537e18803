//! The generated world: a checkered floor square with textured objects standing on it, laid
//! out from a seed, lit by a directional light plus ambient with hard shadows, and rendered
//! with supersampling (colour) and the centre ray (ground-truth depth).

use glam::{Mat3, Vec3};

use super::shapes::{Hit, Shape, EPS};
use super::textures::Texture;
use crate::camera::Camera;
use crate::rng::Rng;

/// Height of the floor; everything stands on it and stays within [-1, 1]³.
const FLOOR_Y: f32 = -0.6;
const FLOOR_HALF: f32 = 0.95;
/// Objects' footprints stay within this half-width of the floor.
const PLACE_HALF: f32 = 0.88;
const AMBIENT: f32 = 0.3;

/// The solid colour behind the scene.
pub(crate) const BACKGROUND: Vec3 = Vec3::new(0.80, 0.86, 0.93);

/// The objects of one footprint, given the footprint's centre on the floor.
type Stand = Box<dyn Fn(Vec3) -> Vec<Object>>;

struct Object {
    shape: Shape,
    texture: Texture,
}

pub(crate) struct World {
    objects: Vec<Object>,
    /// Unit direction towards the light.
    light: Vec3,
}

/// A rendered view: interleaved RGB in [0, 1] and z-depth (0 = background), row-major.
pub(crate) struct View {
    pub rgb: Vec<f32>,
    pub depth: Vec<f32>,
}

/// A colour of the given hue (turns), saturation and value.
fn hsv(h: f32, s: f32, v: f32) -> Vec3 {
    let rgb = Vec3::new(0.0, 2.0 / 3.0, 1.0 / 3.0).map(|o| {
        let k = (h + o).rem_euclid(1.0) * 6.0;
        (k - 3.0).abs() - 1.0
    });
    v * Vec3::ONE.lerp(rgb.clamp(Vec3::ZERO, Vec3::ONE), s)
}

impl World {
    /// The world for `seed`: 7 objects with varied shapes, colours and patterns.
    pub fn new(seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        let mut r = |lo: f32, hi: f32| lo + (hi - lo) * rng.uniform();
        let base_hue = r(0.0, 1.0);
        // Hues spread by the golden ratio so neighbours in the list differ clearly.
        let mut palette = (0..).map(|i| (base_hue + 0.618_034 * i as f32).rem_euclid(1.0));
        let mut colour = |s: f32, v: f32| hsv(palette.next().unwrap_or(0.0), s, v);

        let floor_hue = r(0.0, 1.0);
        let mut objects = vec![Object {
            shape: Shape::Floor {
                y: FLOOR_Y,
                half: FLOOR_HALF,
            },
            texture: Texture::Checker {
                a: hsv(floor_hue, 0.25, 0.85),
                b: hsv(floor_hue + 0.08, 0.45, 0.45),
                cell: 0.19,
            },
        }];

        let mut items: Vec<(f32, Stand)> = Vec::new();

        let radius = r(0.26, 0.32);
        let (base, dot) = (colour(0.7, 0.85), colour(0.5, 0.95));
        items.push((
            radius,
            Box::new(move |p| {
                vec![Object {
                    shape: Shape::Sphere {
                        centre: p + Vec3::Y * radius,
                        radius,
                    },
                    texture: Texture::Dots {
                        base,
                        dot,
                        count: 22,
                        cos_radius: 0.25f32.cos(),
                    },
                }]
            }),
        ));

        let half = Vec3::new(r(0.16, 0.21), r(0.17, 0.25), r(0.16, 0.21));
        let yaw = r(0.0, std::f32::consts::TAU);
        let (a, b) = (colour(0.75, 0.8), colour(0.3, 0.95));
        let small = r(0.09, 0.12);
        let (ma, mb, vein) = (colour(0.5, 0.9), colour(0.8, 0.6), colour(0.9, 0.3));
        let marble_seed = r(0.0, 1e9) as u32;
        items.push((
            half.x.hypot(half.z),
            Box::new(move |p| {
                vec![
                    Object {
                        shape: Shape::Cuboid {
                            centre: p + Vec3::Y * half.y,
                            half,
                            to_world: Mat3::from_rotation_y(yaw),
                        },
                        texture: Texture::Stripes {
                            a,
                            b,
                            axis: Vec3::new(1.0, 1.0, 0.3).normalize(),
                            period: 0.12,
                        },
                    },
                    Object {
                        shape: Shape::Sphere {
                            centre: p + Vec3::Y * (2.0 * half.y + small),
                            radius: small,
                        },
                        texture: Texture::Marble {
                            a: ma,
                            b: mb,
                            vein,
                            scale: 9.0,
                            seed: marble_seed,
                        },
                    },
                ]
            }),
        ));

        let (cyl_r, cyl_h) = (r(0.12, 0.16), r(0.65, 0.9));
        let (bottom, top, ring) = (colour(0.7, 0.5), colour(0.6, 0.95), colour(0.2, 0.95));
        items.push((
            cyl_r,
            Box::new(move |p| {
                vec![Object {
                    shape: Shape::Cylinder {
                        base: p,
                        radius: cyl_r,
                        height: cyl_h,
                    },
                    texture: Texture::Bands {
                        bottom,
                        top,
                        ring,
                        height: cyl_h,
                        period: 0.15,
                    },
                }]
            }),
        ));

        let (major, minor) = (r(0.2, 0.24), r(0.06, 0.08));
        let torus_yaw = r(0.0, std::f32::consts::TAU);
        let (ta, tb, tv) = (colour(0.8, 0.9), colour(0.6, 0.55), colour(0.2, 0.98));
        let torus_seed = r(0.0, 1e9) as u32;
        items.push((
            major + minor,
            Box::new(move |p| {
                // Standing upright: the ring's axis is horizontal.
                let to_world = Mat3::from_rotation_y(torus_yaw)
                    * Mat3::from_rotation_x(std::f32::consts::FRAC_PI_2);
                vec![Object {
                    shape: Shape::Torus {
                        centre: p + Vec3::Y * (major + minor),
                        to_world,
                        major,
                        minor,
                    },
                    texture: Texture::Marble {
                        a: ta,
                        b: tb,
                        vein: tv,
                        scale: 6.0,
                        seed: torus_seed,
                    },
                }]
            }),
        ));

        let cube = r(0.11, 0.14);
        let cube_yaw = r(0.0, std::f32::consts::TAU);
        let (ca, cb) = (colour(0.85, 0.9), colour(0.1, 0.2));
        items.push((
            cube * std::f32::consts::SQRT_2,
            Box::new(move |p| {
                vec![Object {
                    shape: Shape::Cuboid {
                        centre: p + Vec3::Y * cube,
                        half: Vec3::splat(cube),
                        to_world: Mat3::from_rotation_y(cube_yaw),
                    },
                    texture: Texture::Checker {
                        a: ca,
                        b: cb,
                        cell: cube * 2.0 / 3.0,
                    },
                }]
            }),
        ));

        let mid = r(0.17, 0.21);
        let axis = Vec3::new(r(-0.5, 0.5), 1.0, r(-0.5, 0.5)).normalize();
        let (sa, sb) = (colour(0.65, 0.9), colour(0.8, 0.45));
        items.push((
            mid,
            Box::new(move |p| {
                vec![Object {
                    shape: Shape::Sphere {
                        centre: p + Vec3::Y * mid,
                        radius: mid,
                    },
                    texture: Texture::Stripes {
                        a: sa,
                        b: sb,
                        axis,
                        period: 0.11,
                    },
                }]
            }),
        ));

        // Best-candidate placement: of several random spots, take the one with most room.
        let mut placed: Vec<(Vec3, f32)> = Vec::new();
        for (footprint, make) in &items {
            let limit = PLACE_HALF - footprint;
            let best = (0..48)
                .map(|_| Vec3::new(r(-limit, limit), FLOOR_Y, r(-limit, limit)))
                .map(|p| {
                    let room = placed
                        .iter()
                        .map(|(q, f)| (p - *q).length() - f - footprint)
                        .fold(f32::INFINITY, f32::min);
                    (p, room)
                })
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .map_or(Vec3::new(0.0, FLOOR_Y, 0.0), |(p, _)| p);
            placed.push((best, *footprint));
            objects.extend(make(best));
        }

        let (elevation, azimuth) = (r(0.75, 1.05), r(0.0, std::f32::consts::TAU));
        let light = Vec3::new(
            elevation.cos() * azimuth.cos(),
            elevation.sin(),
            elevation.cos() * azimuth.sin(),
        );
        Self { objects, light }
    }

    fn hit(&self, o: Vec3, d: Vec3) -> Option<(Hit, &Object)> {
        let mut best: Option<(Hit, &Object)> = None;
        for obj in &self.objects {
            let t_max = best.as_ref().map_or(f32::INFINITY, |(h, _)| h.t);
            if let Some(h) = obj.shape.intersect(o, d, t_max) {
                best = Some((h, obj));
            }
        }
        best
    }

    fn lit(&self, p: Vec3) -> bool {
        self.objects
            .iter()
            .all(|obj| obj.shape.intersect(p, self.light, f32::INFINITY).is_none())
    }

    /// Colour and distance along a unit ray, or `None` for the background.
    fn trace(&self, o: Vec3, d: Vec3) -> Option<(Vec3, f32)> {
        let (hit, obj) = self.hit(o, d)?;
        let p = o + hit.t * d;
        let albedo = obj.texture.albedo(hit.local, hit.local_normal);
        let facing = hit.normal.dot(self.light).max(0.0);
        let direct = if facing > 0.0 && self.lit(p + hit.normal * (4.0 * EPS)) {
            facing
        } else {
            0.0
        };
        // A slightly brighter ambient on upward faces keeps shadowed shapes readable.
        let ambient = AMBIENT * (0.8 + 0.2 * hit.normal.y);
        Some((albedo * (ambient + (1.0 - AMBIENT) * direct), hit.t))
    }

    /// Renders `camera` with `ss`×`ss` samples per pixel (`ss` odd, so the centre sample
    /// gives the ground-truth depth).
    pub fn render(&self, camera: &Camera, ss: u32) -> View {
        let k = camera.intrinsics;
        let n = (k.width * k.height) as usize;
        let mut view = View {
            rgb: Vec::with_capacity(3 * n),
            depth: Vec::with_capacity(n),
        };
        for y in 0..k.height {
            for x in 0..k.width {
                let mut sum = Vec3::ZERO;
                let mut depth = 0.0;
                for sy in 0..ss {
                    for sx in 0..ss {
                        let u = x as f32 + (sx as f32 + 0.5) / ss as f32;
                        let v = y as f32 + (sy as f32 + 0.5) / ss as f32;
                        let ray = camera.ray(u, v);
                        let sample = self.trace(ray.origin, ray.dir);
                        if sx == ss / 2 && sy == ss / 2 {
                            depth = sample.map_or(0.0, |(_, t)| t * ray.z_per_t);
                        }
                        sum += sample.map_or(BACKGROUND, |(c, _)| c);
                    }
                }
                let c = (sum / (ss * ss) as f32).clamp(Vec3::ZERO, Vec3::ONE);
                view.rgb.extend_from_slice(&c.to_array());
                view.depth.push(depth);
            }
        }
        view
    }
}
