//! Exponential moving average (EMA 0.9999, supplementary Table B) of the model's weights, used
//! for inference. The shadow weights are f32 buffers keyed by variable name and saved exactly.
use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::named_state::{named_vars, read_counter, read_state_buffer, reject_unexpected, scalar_i64, to_f32_vec};
use crate::policy::checkpoint::format::EMA_UPDATES_TENSOR;
use crate::policy::error::{PolicyError, Result};

/// EMA settings. The paper uses decay 0.9999.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EmaConfig {
    /// Final decay per update.
    pub decay: f64,
    /// Warm-up: the decay at update n (1-based) is `min(decay, (1+n)/(10+n))`,
    /// so short runs are not dominated by the initial weights (with 0.9999 and
    /// no warm-up the EMA needs ~10k updates to forget the initialisation).
    pub warmup: bool,
}

impl Default for EmaConfig {
    fn default() -> Self {
        Self { decay: 0.9999, warmup: true }
    }
}

struct EmaParam {
    name: String,
    var: Var,
    shadow: Vec<f32>,
}

/// Exponential moving average of a model's weights:
/// `shadow = d * shadow + (1 - d) * theta` after each optimiser step.
pub struct Ema {
    config: EmaConfig,
    params: Vec<EmaParam>,
    updates: u64,
}

impl Ema {
    /// Starts the average at the model's current weights.
    pub fn new(varmap: &VarMap, config: EmaConfig) -> Result<Self> {
        if !(0.0..=1.0).contains(&config.decay) {
            return Err(PolicyError::Invalid(format!(
                "EMA decay {} must be in [0, 1] (the paper uses 0.9999)",
                config.decay
            )));
        }
        let params = named_vars(varmap, "EMA")?
            .into_iter()
            .map(|nv| -> Result<EmaParam> {
                let shadow = to_f32_vec(nv.var.as_tensor())?;
                Ok(EmaParam { name: nv.name, var: nv.var, shadow })
            })
            .collect::<Result<_>>()?;
        Ok(Self { config, params, updates: 0 })
    }

    pub fn config(&self) -> &EmaConfig {
        &self.config
    }

    /// Updates applied so far.
    pub fn updates(&self) -> u64 {
        self.updates
    }

    /// The decay used for update number `n` (1-based).
    pub fn decay_for_update(&self, n: u64) -> f64 {
        if self.config.warmup { self.config.decay.min((1.0 + n as f64) / (10.0 + n as f64)) } else { self.config.decay }
    }

    /// Folds the model's current weights into the average (call after each
    /// optimiser step).
    pub fn update(&mut self) -> Result<()> {
        let n = self.updates + 1;
        let d = self.decay_for_update(n) as f32;
        let one_minus_d = 1.0 - d;
        self.params.par_iter_mut().try_for_each(|p| -> Result<()> {
            let theta = to_f32_vec(p.var.as_tensor())?;
            for (s, &x) in p.shadow.iter_mut().zip(&theta) {
                *s = d * *s + one_minus_d * x;
            }
            Ok(())
        })?;
        self.updates = n;
        Ok(())
    }

    /// The averaged weights under the model's variable names.
    pub fn tensors(&self) -> Result<HashMap<String, Tensor>> {
        self.params
            .iter()
            .map(|p| Ok((p.name.clone(), Tensor::from_slice(&p.shadow, p.var.shape(), p.var.device())?)))
            .collect()
    }

    /// A VarBuilder over the averaged weights, to build the model for inference.
    pub fn var_builder(&self, device: &Device) -> Result<VarBuilder<'static>> {
        Ok(VarBuilder::from_tensors(self.tensors()?, DType::F32, device))
    }

    /// A new VarMap holding copies of the averaged weights.
    pub fn to_varmap(&self) -> Result<VarMap> {
        let varmap = VarMap::new();
        {
            let mut data =
                varmap.data().lock().map_err(|_| PolicyError::Invalid("EMA: VarMap lock poisoned".into()))?;
            for (name, t) in self.tensors()? {
                data.insert(name, Var::from_tensor(&t)?);
            }
        }
        Ok(varmap)
    }

    /// Overwrites the variables of `varmap` (same names and shapes) with the
    /// averaged weights, e.g. to evaluate the EMA model in place.
    pub fn copy_to(&self, varmap: &VarMap) -> Result<()> {
        let data = varmap.data().lock().map_err(|_| PolicyError::Invalid("EMA: VarMap lock poisoned".into()))?;
        for p in &self.params {
            let var = data
                .get(&p.name)
                .ok_or_else(|| PolicyError::Invalid(format!("EMA copy_to: the target VarMap has no '{}'", p.name)))?;
            if var.shape() != p.var.shape() {
                return Err(PolicyError::Invalid(format!(
                    "EMA copy_to: '{}' has shape {:?} in the target, {:?} in the average",
                    p.name,
                    var.dims(),
                    p.var.dims()
                )));
            }
            var.set(&Tensor::from_slice(&p.shadow, var.shape(), var.device())?.to_dtype(var.dtype())?)?;
        }
        Ok(())
    }

    /// The averaged weights plus [`EMA_UPDATES_TENSOR`].
    pub fn state_tensors(&self) -> Result<HashMap<String, Tensor>> {
        let mut out = self.tensors()?;
        let dev = self.params.first().map_or(Device::Cpu, |p| p.var.device().clone());
        out.insert(EMA_UPDATES_TENSOR.to_string(), scalar_i64(self.updates, &dev)?);
        Ok(out)
    }

    /// Restores [`Ema::state_tensors`]; on error nothing is changed.
    pub fn load_state_tensors(&mut self, tensors: &HashMap<String, Tensor>, source: &Path) -> Result<()> {
        let staged = self.stage_state(tensors, source)?;
        self.apply_state(staged);
        Ok(())
    }

    /// Validates a saved state without changing anything (first half of a load).
    pub(crate) fn stage_state(&self, tensors: &HashMap<String, Tensor>, source: &Path) -> Result<StagedEmaState> {
        let updates = read_counter(tensors, EMA_UPDATES_TENSOR, source)?;
        let mut expected = std::collections::HashSet::new();
        expected.insert(EMA_UPDATES_TENSOR.to_string());
        let mut shadows = Vec::with_capacity(self.params.len());
        for p in &self.params {
            shadows.push(read_state_buffer(tensors, &p.name, p.var.shape(), source)?);
            expected.insert(p.name.clone());
        }
        reject_unexpected(tensors, &expected, source)?;
        Ok(StagedEmaState { updates, shadows })
    }

    /// Installs a state checked by [`Ema::stage_state`] (cannot fail).
    pub(crate) fn apply_state(&mut self, staged: StagedEmaState) {
        for (p, s) in self.params.iter_mut().zip(staged.shadows) {
            p.shadow = s;
        }
        self.updates = staged.updates;
    }
}

/// A validated EMA state waiting to be installed.
pub(crate) struct StagedEmaState {
    updates: u64,
    shadows: Vec<Vec<f32>>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::checkpoint::weights::{read_safetensors, write_safetensors};
    use crate::policy::training::test_support::{tiny_model, values};

    #[test]
    fn ema_follows_the_formula_and_round_trips() {
        let (varmap, w, _b) = tiny_model();
        let mut ema = Ema::new(&varmap, EmaConfig { decay: 0.5, warmup: false }).unwrap();
        w.set(&Tensor::new(&[3.0f32, 2.0], &Device::Cpu).unwrap()).unwrap();
        ema.update().unwrap();
        // 0.5 * [1, -2] + 0.5 * [3, 2] = [2, 0]
        assert_eq!(ema.tensors().unwrap()["w"].to_vec1::<f32>().unwrap(), vec![2.0, 0.0]);
        ema.update().unwrap();
        assert_eq!(ema.tensors().unwrap()["w"].to_vec1::<f32>().unwrap(), vec![2.5, 1.0]);

        // The EMA VarMap / VarBuilder serve the averaged weights.
        let vb = ema.var_builder(&Device::Cpu).unwrap();
        assert_eq!(vb.get(2, "w").unwrap().to_vec1::<f32>().unwrap(), vec![2.5, 1.0]);
        let vm = ema.to_varmap().unwrap();
        assert_eq!(vm.data().lock().unwrap()["w"].as_tensor().to_vec1::<f32>().unwrap(), vec![2.5, 1.0]);

        let dir = std::env::temp_dir().join(format!("policy_train_ema_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("ema.safetensors");
        write_safetensors(&ema.state_tensors().unwrap(), &path).unwrap();
        let mut other = Ema::new(&varmap, EmaConfig { decay: 0.5, warmup: false }).unwrap();
        other.load_state_tensors(&read_safetensors(&path, &Device::Cpu).unwrap(), &path).unwrap();
        assert_eq!(other.updates(), 2);
        assert_eq!(other.tensors().unwrap()["w"].to_vec1::<f32>().unwrap(), vec![2.5, 1.0]);
        other.copy_to(&varmap).unwrap();
        assert_eq!(values(&w), vec![2.5, 1.0]);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn ema_warmup_starts_fast() {
        let (varmap, _, _) = tiny_model();
        let ema = Ema::new(&varmap, EmaConfig::default()).unwrap();
        assert!((ema.decay_for_update(1) - 2.0 / 11.0).abs() < 1e-12);
        assert_eq!(ema.decay_for_update(10_000_000), 0.9999);
        let plain = Ema::new(&varmap, EmaConfig { warmup: false, ..Default::default() }).unwrap();
        assert_eq!(plain.decay_for_update(1), 0.9999);
    }
}
