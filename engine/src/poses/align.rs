//! How good recovered camera poses are: the similarity transform (scale, rotation, translation)
//! that best maps the recovered camera centres onto reference ones (Umeyama, 1991), and after
//! it, each camera's rotation error in degrees and position error as a fraction of the
//! reference cameras' spread. Structure from motion recovers a scene only up to a similarity,
//! so this is the comparison that means something.

use std::collections::BTreeMap;
use std::path::Path;

use glam::{DMat3, DVec3};
use nalgebra::{Matrix3, Vector3};
use serde::Serialize;

use crate::{EngineError, Result};

/// A camera for comparison: camera-to-world rotation and centre.
#[derive(Debug, Clone, Copy)]
pub struct PoseSample {
    pub rotation: DMat3,
    pub position: DVec3,
}

/// `x ↦ scale · rotation · x + translation`.
#[derive(Debug, Clone, Copy)]
pub struct Similarity {
    pub scale: f64,
    pub rotation: DMat3,
    pub translation: DVec3,
}

impl Similarity {
    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.scale * (self.rotation * p) + self.translation
    }
}

/// The errors of recovered poses against reference ones, after alignment.
#[derive(Debug, Clone, Serialize)]
pub struct PoseErrors {
    pub cameras: usize,
    pub median_rotation_deg: f64,
    pub max_rotation_deg: f64,
    /// Median position error over the reference cameras' spread (their RMS distance to their
    /// centroid).
    pub median_position: f64,
    pub max_position: f64,
}

/// The least-squares similarity mapping `from[i]` onto `to[i]`; `None` for fewer than three
/// points or points all on a line.
pub fn similarity(from: &[DVec3], to: &[DVec3]) -> Option<Similarity> {
    assert_eq!(from.len(), to.len());
    let n = from.len();
    if n < 3 {
        return None;
    }
    let mean = |v: &[DVec3]| v.iter().copied().sum::<DVec3>() / n as f64;
    let (mu_from, mu_to) = (mean(from), mean(to));
    let mut cov = Matrix3::<f64>::zeros();
    let mut var_from = 0.0;
    for (a, b) in from.iter().zip(to) {
        let (da, db) = (*a - mu_from, *b - mu_to);
        cov += vec(db) * vec(da).transpose();
        var_from += da.length_squared();
    }
    cov /= n as f64;
    var_from /= n as f64;
    let svd = cov.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let sv = svd.singular_values;
    // Rank below 2: the centres are (nearly) collinear and the rotation is undetermined.
    if sv[1] <= 1e-9 * sv[0].max(1e-300) || var_from <= 0.0 {
        return None;
    }
    let r = u * d * v_t;
    let scale = (sv[0] * d[(0, 0)] + sv[1] * d[(1, 1)] + sv[2] * d[(2, 2)]) / var_from;
    let rotation = mat(&r);
    Some(Similarity {
        scale,
        rotation,
        translation: mu_to - scale * (rotation * mu_from),
    })
}

/// Aligns `recovered` to `reference` (paired by index) and measures the errors.
pub fn pose_errors(recovered: &[PoseSample], reference: &[PoseSample]) -> Option<PoseErrors> {
    let from: Vec<DVec3> = recovered.iter().map(|p| p.position).collect();
    let to: Vec<DVec3> = reference.iter().map(|p| p.position).collect();
    let s = similarity(&from, &to)?;
    let centroid = to.iter().copied().sum::<DVec3>() / to.len() as f64;
    let spread = (to
        .iter()
        .map(|p| (*p - centroid).length_squared())
        .sum::<f64>()
        / to.len() as f64)
        .sqrt();
    let mut rot = Vec::new();
    let mut pos = Vec::new();
    for (r, t) in recovered.iter().zip(reference) {
        pos.push((s.apply(r.position) - t.position).length() / spread);
        let aligned = s.rotation * r.rotation;
        rot.push(angle_deg(&(aligned.transpose() * t.rotation)));
    }
    Some(PoseErrors {
        cameras: recovered.len(),
        median_rotation_deg: median(&rot),
        max_rotation_deg: rot.iter().copied().fold(0.0, f64::max),
        median_position: median(&pos),
        max_position: pos.iter().copied().fold(0.0, f64::max),
    })
}

/// The camera poses of a `transforms.json`, by image file name (its folder dropped), for
/// comparing two datasets of the same photos.
pub fn read_transforms(file: &Path) -> Result<BTreeMap<String, PoseSample>> {
    let err = |reason: String| EngineError::dataset(file, "frames", reason);
    let text = std::fs::read_to_string(file).map_err(|e| EngineError::io(file, e))?;
    let doc: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| err(format!("not JSON: {e}")))?;
    let frames = doc["frames"]
        .as_array()
        .ok_or_else(|| err("missing".into()))?;
    let mut out = BTreeMap::new();
    for (i, f) in frames.iter().enumerate() {
        let name = f["file_path"]
            .as_str()
            .and_then(|p| Path::new(p).file_name()?.to_str())
            .ok_or_else(|| err(format!("frames[{i}].file_path missing")))?;
        let m: Vec<Vec<f64>> = serde_json::from_value(f["transform_matrix"].clone())
            .map_err(|e| err(format!("frames[{i}].transform_matrix: {e}")))?;
        if m.len() < 3 || m.iter().take(3).any(|r| r.len() != 4) {
            return Err(err(format!(
                "frames[{i}].transform_matrix is not 3×4 or 4×4"
            )));
        }
        let col = |c: usize| DVec3::new(m[0][c], m[1][c], m[2][c]);
        out.insert(
            name.to_string(),
            PoseSample {
                rotation: DMat3::from_cols(col(0), col(1), col(2)),
                position: col(3),
            },
        );
    }
    Ok(out)
}

/// The rotation angle of a rotation matrix, in degrees.
fn angle_deg(r: &DMat3) -> f64 {
    let trace = r.x_axis.x + r.y_axis.y + r.z_axis.z;
    ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

fn vec(v: DVec3) -> Vector3<f64> {
    Vector3::new(v.x, v.y, v.z)
}

fn mat(m: &Matrix3<f64>) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(m[(0, 0)], m[(1, 0)], m[(2, 0)]),
        DVec3::new(m[(0, 1)], m[(1, 1)], m[(2, 1)]),
        DVec3::new(m[(0, 2)], m[(1, 2)], m[(2, 2)]),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    fn cameras() -> Vec<PoseSample> {
        (0..12)
            .map(|i| {
                let a = i as f64 * 0.5;
                PoseSample {
                    rotation: DMat3::from_quat(DQuat::from_rotation_y(a)),
                    position: DVec3::new(a.cos() * 3.0, 0.3 * (i % 3) as f64, a.sin() * 3.0),
                }
            })
            .collect()
    }

    #[test]
    fn a_similarity_is_recovered_exactly() {
        let reference = cameras();
        let rot = DMat3::from_quat(DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0));
        let (scale, shift) = (0.37, DVec3::new(4.0, -2.0, 9.0));
        // The recovered world is the reference world under the inverse similarity.
        let recovered: Vec<PoseSample> = reference
            .iter()
            .map(|p| PoseSample {
                rotation: rot.transpose() * p.rotation,
                position: rot.transpose() * ((p.position - shift) / scale),
            })
            .collect();
        let s = similarity(
            &recovered.iter().map(|p| p.position).collect::<Vec<_>>(),
            &reference.iter().map(|p| p.position).collect::<Vec<_>>(),
        )
        .unwrap();
        assert!((s.scale - scale).abs() < 1e-9, "{}", s.scale);
        assert!((s.translation - shift).length() < 1e-9);
        let e = pose_errors(&recovered, &reference).unwrap();
        assert!(e.max_rotation_deg < 1e-5 && e.max_position < 1e-9, "{e:?}");
    }

    #[test]
    fn errors_are_measured_in_degrees_and_spread() {
        let reference = cameras();
        let mut recovered = reference.clone();
        // One camera turned by 10°: its rotation error is 10°, the others' near 0.
        recovered[4].rotation = DMat3::from_rotation_x(10f64.to_radians()) * recovered[4].rotation;
        let e = pose_errors(&recovered, &reference).unwrap();
        assert!((e.max_rotation_deg - 10.0).abs() < 1e-6, "{e:?}");
        assert!(e.median_rotation_deg < 1e-6);
        assert!(similarity(&[DVec3::ZERO, DVec3::X, DVec3::X * 2.0], &[DVec3::ZERO; 3]).is_none());
    }
}
