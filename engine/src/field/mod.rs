//! The radiance field: a hash-grid encoding feeding a density network (σ plus geometry
//! features) and a view-dependent colour network, with an occupancy grid to skip empty space.

pub mod hash_grid;
pub mod mlp;
pub mod occupancy;
pub mod radiance;
pub mod saved;
pub mod sh;
pub mod space;
