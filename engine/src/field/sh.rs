//! Real spherical harmonics up to degree 3 (16 coefficients): the view-direction encoding of
//! the colour network, as in instant-ngp.

/// Encodes a unit direction into 16 SH basis values.
pub fn sh16(d: [f32; 3]) -> [f32; 16] {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    [
        0.282_094_8,
        -0.488_602_5 * y,
        0.488_602_5 * z,
        -0.488_602_5 * x,
        1.092_548_4 * x * y,
        -1.092_548_4 * y * z,
        0.315_391_57 * (2.0 * zz - xx - yy),
        -1.092_548_4 * x * z,
        0.546_274_2 * (xx - yy),
        -0.590_043_6 * y * (3.0 * xx - yy),
        2.890_611_4 * x * y * z,
        -0.457_045_8 * y * (4.0 * zz - xx - yy),
        0.373_176_33 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        -0.457_045_8 * x * (4.0 * zz - xx - yy),
        1.445_305_7 * z * (xx - yy),
        -0.590_043_6 * x * (xx - 3.0 * yy),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_is_orthonormal_on_the_sphere() {
        // Monte-Carlo check of ∫ Y_i Y_j dω = δ_ij over a Fibonacci sphere.
        let n = 20000;
        let mut gram = [[0f64; 16]; 16];
        for k in 0..n {
            let z = 1.0 - 2.0 * (k as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = k as f64 * std::f64::consts::PI * (3.0 - 5f64.sqrt());
            let y = sh16([(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32]);
            for i in 0..16 {
                for j in 0..16 {
                    gram[i][j] += (y[i] * y[j]) as f64 * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for (i, row) in gram.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 1e-2, "({i},{j}) = {v}");
            }
        }
    }
}
