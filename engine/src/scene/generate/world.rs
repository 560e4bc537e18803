//! The generated world: a checkered floor square with textured objects standing on it, laid
//! out from a seed, lit by a directional light plus ambient with hard shadows, and rendered
//! with supersampling (colour) and the centre ray (ground-truth depth). Around it: a solid
//! colour, a sky at infinity, or a textured room (what real captures look like).

use glam::{Mat3, Vec3};
use serde::{Deserialize, Serialize};

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

/// The room around the table (walls at ±x, ±z; floor and ceiling at the y bounds).
const ROOM_MIN: Vec3 = Vec3::new(-4.0, -1.4, -4.0);
const ROOM_MAX: Vec3 = Vec3::new(4.0, 3.0, 4.0);

/// What surrounds the table-top.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Surroundings {
    /// A solid colour, stated in the dataset: an object scene with a known background.
    #[default]
    Plain,
    /// A sky at infinity whose colour varies with the view direction (horizon to zenith, a
    /// glow around the sun, darker ground below the horizon); not stated in the dataset.
    Sky,
    /// A room around the table, past the content box: striped walls, a tiled floor and a
    /// ceiling, lit like the objects; a capture with no box and no background.
    Room,
    /// The room with marbled walls, floor and table top: no pattern repeats, as in a lived-in
    /// room, so structure from motion can tell views apart (stripes and tiles defeat it).
    Gallery,
}

impl Surroundings {
    /// Whether a room surrounds the table (the capture is unbounded).
    pub fn is_room(self) -> bool {
        matches!(self, Self::Room | Self::Gallery)
    }
}

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
    surroundings: Surroundings,
    /// The room's walls (+x, −x, +z, −z), floor and ceiling.
    room: [Texture; 6],
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
    pub fn new(seed: u64, surroundings: Surroundings) -> Self {
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
        let wall_hue = r(0.0, 1.0);
        let wall = |hue: f32, axis: Vec3| Texture::Stripes {
            a: hsv(hue, 0.35, 0.85),
            b: hsv(hue + 0.05, 0.55, 0.55),
            axis,
            period: 0.45,
        };
        if surroundings == Surroundings::Gallery {
            // Drawn from the hues above, not the generator, so every other scene of a seed stays
            // as it was.
            let marble = |hue: f32, seed: u32, scale: f32| Texture::Marble {
                a: hsv(hue, 0.45, 0.85),
                b: hsv(hue + 0.15, 0.6, 0.35),
                vein: hsv(hue + 0.5, 0.3, 0.95),
                scale,
                seed,
            };
            objects[0].texture = marble(floor_hue, 11, 3.0);
            let room =
                std::array::from_fn(|i| marble(wall_hue + 0.17 * i as f32, 20 + i as u32, 1.3));
            return Self {
                objects,
                light,
                surroundings,
                room,
            };
        }
        let room = [
            wall(wall_hue, Vec3::Z),
            wall(wall_hue + 0.5, Vec3::Z),
            wall(wall_hue + 0.25, Vec3::X),
            wall(wall_hue + 0.75, Vec3::X),
            Texture::Checker {
                a: hsv(wall_hue + 0.1, 0.4, 0.6),
                b: hsv(wall_hue + 0.1, 0.5, 0.35),
                cell: 0.6,
            },
            Texture::Checker {
                a: Vec3::splat(0.92),
                b: Vec3::splat(0.8),
                cell: 1.0,
            },
        ];
        Self {
            objects,
            light,
            surroundings,
            room,
        }
    }

    /// Where a ray from inside the room leaves it: distance, normal (pointing in) and which
    /// of [`World::room`]'s surfaces.
    fn room_exit(o: Vec3, d: Vec3) -> (f32, Vec3, usize) {
        let mut best = (f32::INFINITY, Vec3::ZERO, 0);
        for axis in 0..3 {
            let (t, sign) = if d[axis] > 0.0 {
                ((ROOM_MAX[axis] - o[axis]) / d[axis], 1.0)
            } else if d[axis] < 0.0 {
                ((ROOM_MIN[axis] - o[axis]) / d[axis], -1.0)
            } else {
                continue;
            };
            if t < best.0 {
                let mut normal = Vec3::ZERO;
                normal[axis] = -sign;
                // Surfaces: 0 +x, 1 −x, 2 +z, 3 −z, 4 floor, 5 ceiling.
                let surface = match (axis, sign > 0.0) {
                    (0, true) => 0,
                    (0, false) => 1,
                    (2, true) => 2,
                    (2, false) => 3,
                    (_, false) => 4,
                    (_, true) => 5,
                };
                best = (t, normal, surface);
            }
        }
        best
    }

    /// The sky's colour in direction `d` (unit).
    fn sky(&self, d: Vec3) -> Vec3 {
        let horizon = Vec3::new(0.85, 0.80, 0.70);
        let zenith = Vec3::new(0.25, 0.45, 0.85);
        let ground = Vec3::new(0.35, 0.32, 0.28);
        let up = d.y.clamp(-1.0, 1.0);
        let base = if up >= 0.0 {
            horizon.lerp(zenith, up.sqrt())
        } else {
            horizon.lerp(ground, (-up).sqrt().min(1.0))
        };
        let glow = d.dot(self.light).max(0.0).powi(6) * 0.35;
        let bands = 0.06 * (3.0 * d.z.atan2(d.x)).cos() * (1.0 - up.abs());
        (base + Vec3::new(glow, glow * 0.9, glow * 0.6) + Vec3::splat(bands))
            .clamp(Vec3::ZERO, Vec3::ONE)
    }

    /// What a ray that misses every object sees: colour and distance (`None` at infinity).
    fn surroundings(&self, o: Vec3, d: Vec3) -> (Vec3, Option<f32>) {
        match self.surroundings {
            Surroundings::Plain => (BACKGROUND, None),
            Surroundings::Sky => (self.sky(d), None),
            Surroundings::Room | Surroundings::Gallery => {
                let (t, normal, surface) = Self::room_exit(o, d);
                let p = o + t * d;
                (
                    self.shade(p, normal, self.room[surface].albedo(p, normal)),
                    Some(t),
                )
            }
        }
    }

    /// Ambient plus direct light with hard shadows at `p`.
    fn shade(&self, p: Vec3, normal: Vec3, albedo: Vec3) -> Vec3 {
        let facing = normal.dot(self.light).max(0.0);
        let direct = if facing > 0.0 && self.lit(p + normal * (4.0 * EPS)) {
            facing
        } else {
            0.0
        };
        // A slightly brighter ambient on upward faces keeps shadowed shapes readable.
        let ambient = AMBIENT * (0.8 + 0.2 * normal.y);
        albedo * (ambient + (1.0 - AMBIENT) * direct)
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

    /// Colour and distance along a unit ray (`None`: nothing at a finite distance).
    fn trace(&self, o: Vec3, d: Vec3) -> (Vec3, Option<f32>) {
        match self.hit(o, d) {
            Some((hit, obj)) => {
                let p = o + hit.t * d;
                let albedo = obj.texture.albedo(hit.local, hit.local_normal);
                (self.shade(p, hit.normal, albedo), Some(hit.t))
            }
            None => self.surroundings(o, d),
        }
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
                        let (colour, t) = self.trace(ray.origin, ray.dir);
                        if sx == ss / 2 && sy == ss / 2 {
                            depth = t.map_or(0.0, |t| t * ray.z_per_t);
                        }
                        sum += colour;
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
