//! Test helper: compares the gradient candle's backward pass computes with central finite
//! differences, in f64.

use candle_core::{DType, Device, Tensor, Var};

use crate::rng::Rng;

/// A deterministic f64 tensor with entries in [-1, 1).
pub fn random(shape: &[usize], seed: u64) -> Tensor {
    let mut rng = Rng::new(seed);
    let n = shape.iter().product();
    let data: Vec<f64> = (0..n).map(|_| rng.uniform() as f64 * 2.0 - 1.0).collect();
    Tensor::from_vec(data, shape, &Device::Cpu).unwrap()
}

/// The largest absolute entry of `t` (of any float type), as f32.
pub fn max_abs(t: &Tensor) -> f32 {
    t.abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_dtype(DType::F32)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

/// Checks d(Σ f(x) · r)/dx (r a fixed random weighting, so every output matters) against
/// finite differences at every element of `x`. Panics with the worst mismatch.
pub fn check(x: &Tensor, f: impl Fn(&Tensor) -> candle_core::Result<Tensor>) {
    assert_eq!(x.dtype(), DType::F64);
    let probe = f(x).unwrap();
    let r = random(probe.dims(), 99);
    let loss = |t: &Tensor| -> candle_core::Result<Tensor> { (f(t)? * &r)?.sum_all() };
    let var = Var::from_tensor(x).unwrap();
    let grads = loss(var.as_tensor()).unwrap().backward().unwrap();
    let analytic = grads
        .get(var.as_tensor())
        .expect("no gradient reached the input")
        .flatten_all()
        .unwrap()
        .to_vec1::<f64>()
        .unwrap();
    let base = x.flatten_all().unwrap().to_vec1::<f64>().unwrap();
    let eps = 1e-6;
    let eval = |i: usize, d: f64| -> f64 {
        let mut v = base.clone();
        v[i] += d;
        let t = Tensor::from_vec(v, x.dims(), x.device()).unwrap();
        loss(&t).unwrap().to_scalar::<f64>().unwrap()
    };
    let mut worst = (0.0f64, 0usize, 0.0, 0.0);
    for (i, &a) in analytic.iter().enumerate() {
        let n = (eval(i, eps) - eval(i, -eps)) / (2.0 * eps);
        let err = (a - n).abs() / (1.0 + n.abs());
        if err > worst.0 {
            worst = (err, i, a, n);
        }
    }
    assert!(
        worst.0 < 1e-6,
        "gradient mismatch at element {}: analytic {} vs numeric {}",
        worst.1,
        worst.2,
        worst.3
    );
}
