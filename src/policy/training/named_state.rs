//! Training state kept as f32 buffers keyed by variable name (the AdamW moments, the EMA
//! shadows): the model's variables in their fixed update order, and the checks applied when a
//! saved state is read back (names, shapes, dtype, counters; nothing unknown).
use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Shape, Tensor, Var};
use candle_nn::VarMap;

use crate::policy::error::{PolicyError, Result};

/// A trainable variable with its name and shape, read from a VarMap.
pub(super) struct NamedVar {
    pub(super) name: String,
    pub(super) var: Var,
}

/// The VarMap's variables sorted by name (the fixed update order). Only f32
/// variables are supported: training runs in f32.
pub(super) fn named_vars(varmap: &VarMap, what: &str) -> Result<Vec<NamedVar>> {
    let data =
        varmap.data().lock().map_err(|_| PolicyError::Invalid(format!("{what}: the VarMap lock is poisoned")))?;
    let mut vars: Vec<NamedVar> =
        data.iter().map(|(name, var)| NamedVar { name: name.clone(), var: var.clone() }).collect();
    drop(data);
    vars.sort_by(|a, b| a.name.cmp(&b.name));
    for v in &vars {
        if v.var.dtype() != DType::F32 {
            return Err(PolicyError::Invalid(format!(
                "{what}: variable '{}' is {:?}; only f32 variables can be trained",
                v.name,
                v.var.dtype()
            )));
        }
    }
    if vars.is_empty() {
        return Err(PolicyError::Invalid(format!(
            "{what}: the VarMap has no variables; build the model before the optimiser"
        )));
    }
    Ok(vars)
}

pub(super) fn to_f32_vec(t: &Tensor) -> Result<Vec<f32>> {
    Ok(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?)
}

pub(super) fn scalar_i64(value: u64, device: &Device) -> Result<Tensor> {
    let v = i64::try_from(value).map_err(|_| PolicyError::Invalid(format!("counter {value} does not fit in i64")))?;
    Ok(Tensor::new(&[v], device)?)
}

pub(super) fn read_counter(tensors: &HashMap<String, Tensor>, name: &str, source: &Path) -> Result<u64> {
    let t = tensors.get(name).ok_or_else(|| PolicyError::File {
        path: source.to_path_buf(),
        message: format!("missing tensor '{name}' (the step counter)"),
    })?;
    let values =
        t.flatten_all().and_then(|t| t.to_dtype(DType::I64)).and_then(|t| t.to_vec1::<i64>()).map_err(|e| {
            PolicyError::File {
                path: source.to_path_buf(),
                message: format!("tensor '{name}' is not an integer counter: {e}"),
            }
        })?;
    match values.as_slice() {
        [v] if *v >= 0 => Ok(*v as u64),
        _ => Err(PolicyError::File {
            path: source.to_path_buf(),
            message: format!("tensor '{name}' must hold one non-negative integer, got {values:?}"),
        }),
    }
}

/// Fetches `name` from `tensors`, checks it has `shape`, and returns its f32 values.
pub(super) fn read_state_buffer(
    tensors: &HashMap<String, Tensor>,
    name: &str,
    shape: &Shape,
    source: &Path,
) -> Result<Vec<f32>> {
    let t = tensors.get(name).ok_or_else(|| PolicyError::File {
        path: source.to_path_buf(),
        message: format!("missing tensor '{name}' (shape {:?}); was it saved for a different model?", shape.dims()),
    })?;
    if t.shape() != shape {
        return Err(PolicyError::File {
            path: source.to_path_buf(),
            message: format!("tensor '{name}' has shape {:?}, the model expects {:?}", t.dims(), shape.dims()),
        });
    }
    if t.dtype() != DType::F32 {
        return Err(PolicyError::File {
            path: source.to_path_buf(),
            message: format!("tensor '{name}' is {:?}, expected F32", t.dtype()),
        });
    }
    to_f32_vec(t)
}

/// Rejects tensors in a state file that the model does not know (a different
/// model configuration) — silently ignoring them would hide the mismatch.
pub(super) fn reject_unexpected(
    tensors: &HashMap<String, Tensor>,
    expected: &std::collections::HashSet<String>,
    source: &Path,
) -> Result<()> {
    let mut extra: Vec<&String> = tensors.keys().filter(|k| !expected.contains(*k)).collect();
    if extra.is_empty() {
        return Ok(());
    }
    extra.sort();
    Err(PolicyError::File {
        path: source.to_path_buf(),
        message: format!(
            "{} tensor(s) the model does not have, e.g. '{}'; the file belongs to a different model configuration",
            extra.len(),
            extra[0]
        ),
    })
}
