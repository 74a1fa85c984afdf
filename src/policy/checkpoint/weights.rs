//! Named tensors on disk (safetensors, written atomically) and the model's variables: the
//! tensors of a `VarMap`, and loading weights into one with every name, shape and dtype checked
//! before anything changes.
use std::collections::{HashMap, HashSet};
use std::path::Path;

use candle_core::{Device, Tensor};
use candle_nn::VarMap;

use super::format::EMA_UPDATES_TENSOR;
use crate::policy::error::{PolicyError, Result};

/// Writes tensors as a safetensors file atomically ([`crate::files`]).
pub fn write_safetensors(tensors: &HashMap<String, Tensor>, path: &Path) -> Result<()> {
    crate::files::write_atomic_or(
        path,
        |tmp| {
            candle_core::safetensors::save(tensors, tmp)
                .map_err(|e| PolicyError::file(tmp, format!("cannot write safetensors: {e}")))
        },
        |e| PolicyError::io(path, "write", e),
    )
}

/// Reads a safetensors file onto `device`.
pub fn read_safetensors(path: &Path, device: &Device) -> Result<HashMap<String, Tensor>> {
    let bytes = std::fs::read(path).map_err(|e| PolicyError::io(path, "read", e))?;
    parse_safetensors(path, &bytes, device)
}

/// Parses the bytes of a safetensors file (read from `path`, named in errors).
pub(super) fn parse_safetensors(path: &Path, bytes: &[u8], device: &Device) -> Result<HashMap<String, Tensor>> {
    candle_core::safetensors::load_buffer(bytes, device)
        .map_err(|e| PolicyError::file(path, format!("not a valid safetensors file (truncated or corrupt?): {e}")))
}

/// The model's variables as named tensors (what goes to `model.safetensors`).
pub fn varmap_tensors(model: &VarMap) -> Result<HashMap<String, Tensor>> {
    let data =
        model.data().lock().map_err(|_| PolicyError::Invalid("checkpoint: the VarMap lock is poisoned".into()))?;
    Ok(data.iter().map(|(k, v)| (k.clone(), v.as_tensor().clone())).collect())
}

/// The device of the model's variables (the CPU for an empty model).
pub fn model_device(model: &VarMap) -> Device {
    model.all_vars().first().map_or(Device::Cpu, |v| v.device().clone())
}

/// Checks `tensors` against the model's variables by name, shape and dtype, and returns them in
/// a form ready to assign. Names in `ignore` may be present besides the model's. Errors name
/// `source`.
pub fn check_model_tensors(
    model: &VarMap,
    tensors: &HashMap<String, Tensor>,
    ignore: &[&str],
    source: &Path,
) -> Result<Vec<(candle_core::Var, Tensor)>> {
    let data =
        model.data().lock().map_err(|_| PolicyError::Invalid("checkpoint: the VarMap lock is poisoned".into()))?;
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let mut out = Vec::with_capacity(names.len());
    for name in names {
        let var = &data[name];
        let t = tensors.get(name).ok_or_else(|| {
            PolicyError::file(
                source,
                format!(
                    "missing tensor '{name}' (the model expects shape {:?}); the checkpoint was written by a different model configuration",
                    var.dims()
                ),
            )
        })?;
        if t.shape() != var.shape() {
            return Err(PolicyError::file(
                source,
                format!("tensor '{name}' has shape {:?}, the model expects {:?}", t.dims(), var.dims()),
            ));
        }
        if t.dtype() != var.dtype() {
            return Err(PolicyError::file(
                source,
                format!("tensor '{name}' is {:?}, the model expects {:?}", t.dtype(), var.dtype()),
            ));
        }
        out.push((var.clone(), t.clone()));
    }
    let known: HashSet<&str> = data.keys().map(String::as_str).chain(ignore.iter().copied()).collect();
    let mut extra: Vec<&String> = tensors.keys().filter(|k| !known.contains(k.as_str())).collect();
    extra.sort();
    if let Some(first) = extra.first() {
        return Err(PolicyError::file(
            source,
            format!(
                "{} tensor(s) the model does not have, e.g. '{first}'; the checkpoint was written by a different model configuration",
                extra.len()
            ),
        ));
    }
    Ok(out)
}

/// Loads model weights from a safetensors file (e.g. a checkpoint's `model.safetensors` or
/// `ema.safetensors` for inference) into `model`, checking names and shapes. Nothing is changed
/// on error.
pub fn load_model_weights(path: &Path, model: &VarMap) -> Result<()> {
    let tensors = read_safetensors(path, &model_device(model))?;
    let assignments = check_model_tensors(model, &tensors, &[EMA_UPDATES_TENSOR], path)?;
    for (var, t) in assignments {
        var.set(&t)?;
    }
    Ok(())
}
