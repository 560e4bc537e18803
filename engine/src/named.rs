//! Named weights, the one way every model (field, style module, decoder, VAE) goes to and from
//! checkpoints and artifacts: its variables as `(name, tensor)` pairs, and those pairs copied
//! back into the variables with every name and shape checked.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Tensor, Var};

use crate::{EngineError, Result};

/// The variables' current values as named tensors.
pub fn tensors_of(vars: &[(String, Var)]) -> Vec<(String, Tensor)> {
    vars.iter()
        .map(|(n, v)| (n.clone(), v.as_tensor().clone()))
        .collect()
}

/// Copies named tensors into the matching variables (converted to each variable's dtype and
/// device). A missing name or a wrong shape is an error about `source`.
pub fn load_vars(
    vars: &[(String, Var)],
    tensors: &HashMap<String, Tensor>,
    source: &Path,
) -> Result<()> {
    for (name, var) in vars {
        let t = tensors
            .get(name)
            .ok_or_else(|| EngineError::artifact(source, format!("tensor `{name}` missing")))?;
        if t.dims() != var.dims() {
            return Err(EngineError::artifact(
                source,
                format!(
                    "tensor `{name}` has shape {:?}, the model expects {:?}",
                    t.dims(),
                    var.dims()
                ),
            ));
        }
        var.set(&t.to_dtype(var.dtype())?.to_device(var.device())?)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    #[test]
    fn weights_go_out_and_back_and_mismatches_name_the_tensor() {
        let dev = Device::Cpu;
        let a = Var::from_tensor(
            &Tensor::arange(0f32, 6.0, &dev)
                .unwrap()
                .reshape((2, 3))
                .unwrap(),
        )
        .unwrap();
        let vars = vec![("layer.weight".to_string(), a)];
        let saved: HashMap<String, Tensor> = tensors_of(&vars).into_iter().collect();
        let b = Var::zeros((2, 3), DType::F32, &dev).unwrap();
        let target = vec![("layer.weight".to_string(), b.clone())];
        load_vars(&target, &saved, Path::new("ckpt")).unwrap();
        assert_eq!(
            b.as_tensor()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap(),
            [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
        );
        let wrong = vec![(
            "layer.weight".to_string(),
            Var::zeros(3, DType::F32, &dev).unwrap(),
        )];
        let e = load_vars(&wrong, &saved, Path::new("ckpt"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("layer.weight") && e.contains("shape"), "{e}");
        let e = load_vars(&target, &HashMap::new(), Path::new("ckpt"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("ckpt") && e.contains("missing"), "{e}");
    }
}
