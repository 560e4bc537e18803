//! Procedural surface patterns for the generator: checks, stripes, polka dots, wavy colour
//! bands and value-noise marble. All are functions of the object-local hit point, so they
//! stay put on the object from every view.

use glam::Vec3;

#[derive(Debug, Clone)]
pub(crate) enum Texture {
    /// Squares of size `cell` on each face (the axis along the normal is dropped).
    Checker { a: Vec3, b: Vec3, cell: f32 },
    /// Parallel stripes across `axis` with the given period.
    Stripes {
        a: Vec3,
        b: Vec3,
        axis: Vec3,
        period: f32,
    },
    /// Dots spread evenly (Fibonacci lattice) over directions from the object centre.
    Dots {
        base: Vec3,
        dot: Vec3,
        count: usize,
        cos_radius: f32,
    },
    /// A bottom-to-top colour gradient crossed by wavy rings.
    Bands {
        bottom: Vec3,
        top: Vec3,
        ring: Vec3,
        height: f32,
        period: f32,
    },
    /// Veined marble from fractal value noise.
    Marble {
        a: Vec3,
        b: Vec3,
        vein: Vec3,
        scale: f32,
        seed: u32,
    },
}

impl Texture {
    pub fn albedo(&self, p: Vec3, n: Vec3) -> Vec3 {
        match *self {
            Texture::Checker { a, b, cell } => {
                let n = n.abs();
                let (u, v) = if n.x >= n.y && n.x >= n.z {
                    (p.y, p.z)
                } else if n.y >= n.z {
                    (p.x, p.z)
                } else {
                    (p.x, p.y)
                };
                let parity = ((u / cell).floor() + (v / cell).floor()) as i64 & 1;
                if parity == 0 {
                    a
                } else {
                    b
                }
            }
            Texture::Stripes { a, b, axis, period } => {
                if (p.dot(axis) / period).rem_euclid(1.0) < 0.5 {
                    a
                } else {
                    b
                }
            }
            Texture::Dots {
                base,
                dot,
                count,
                cos_radius,
            } => {
                let dir = p.normalize_or_zero();
                let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
                let inside = (0..count).any(|i| {
                    let y = 1.0 - 2.0 * (i as f32 + 0.5) / count as f32;
                    let r = (1.0 - y * y).sqrt();
                    let phi = golden * i as f32;
                    Vec3::new(r * phi.cos(), y, r * phi.sin()).dot(dir) > cos_radius
                });
                if inside {
                    dot
                } else {
                    base
                }
            }
            Texture::Bands {
                bottom,
                top,
                ring,
                height,
                period,
            } => {
                let wave = 0.03 * (6.0 * p.z.atan2(p.x)).sin();
                if ((p.y + wave) / period).rem_euclid(1.0) < 0.3 {
                    ring
                } else {
                    bottom.lerp(top, (p.y / height).clamp(0.0, 1.0))
                }
            }
            Texture::Marble {
                a,
                b,
                vein,
                scale,
                seed,
            } => {
                let q = p * scale;
                let turbulence = fbm(q, seed);
                let s = (q.x + 0.6 * q.y + 6.0 * turbulence).sin();
                if s.abs() < 0.12 {
                    vein
                } else {
                    a.lerp(b, 0.5 + 0.5 * s)
                }
            }
        }
    }
}

/// Fractal (4-octave) value noise in roughly [0, 1].
fn fbm(p: Vec3, seed: u32) -> f32 {
    let mut sum = 0.0;
    let mut amp = 0.5;
    let mut q = p;
    for octave in 0..4 {
        sum += amp * value_noise(q, seed.wrapping_add(octave));
        amp *= 0.5;
        q *= 2.03;
    }
    sum / 0.9375
}

/// Trilinear interpolation of hashed lattice values, smoothstep-weighted.
fn value_noise(p: Vec3, seed: u32) -> f32 {
    let cell = p.floor();
    let f = p - cell;
    let w = f * f * (Vec3::splat(3.0) - 2.0 * f);
    let (x, y, z) = (cell.x as i32, cell.y as i32, cell.z as i32);
    let v = |dx: i32, dy: i32, dz: i32| hash(x + dx, y + dy, z + dz, seed);
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(v(0, 0, 0), v(1, 0, 0), w.x);
    let x10 = lerp(v(0, 1, 0), v(1, 1, 0), w.x);
    let x01 = lerp(v(0, 0, 1), v(1, 0, 1), w.x);
    let x11 = lerp(v(0, 1, 1), v(1, 1, 1), w.x);
    lerp(lerp(x00, x10, w.y), lerp(x01, x11, w.y), w.z)
}

/// A lattice point's pseudo-random value in [0, 1).
fn hash(x: i32, y: i32, z: i32, seed: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x8da6_b343)
        ^ (y as u32).wrapping_mul(0xd816_3841)
        ^ (z as u32).wrapping_mul(0xcb1a_b31f)
        ^ seed.wrapping_mul(0x9e37_79b9);
    h ^= h >> 13;
    h = h.wrapping_mul(0x5bd1_e995);
    h ^= h >> 15;
    (h >> 8) as f32 / (1u32 << 24) as f32
}
