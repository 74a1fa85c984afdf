//! AdamW with decoupled weight decay (supplementary Table B: lr 1e-4, wd 5e-4, betas
//! 0.9/0.999) over the variables of a `candle_nn::VarMap`, with optional gradient-norm clipping.
//! The moments are plain f32 buffers keyed by variable name, updated in a fixed order and saved
//! exactly (f32 moments + step count, see [`AdamW::state_tensors`]), so a resumed run continues
//! bit-identically.
use std::collections::HashMap;
use std::path::Path;

use candle_core::backprop::GradStore;
use candle_core::{Device, Tensor, Var};
use candle_nn::VarMap;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::named_state::{named_vars, read_counter, read_state_buffer, reject_unexpected, scalar_i64, to_f32_vec};
use crate::policy::error::{PolicyError, Result};

/// AdamW hyper-parameters. Defaults are the paper's (Table B).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamWConfig {
    /// Step size (1e-4).
    pub learning_rate: f64,
    /// Decoupled weight decay: each step `theta *= 1 - lr * weight_decay` (5e-4).
    pub weight_decay: f64,
    /// First-moment decay (0.9).
    pub beta1: f64,
    /// Second-moment decay (0.999).
    pub beta2: f64,
    /// Denominator epsilon (1e-8).
    pub eps: f64,
    /// Clip the global L2 norm of all gradients to this value (none by default).
    pub max_grad_norm: Option<f64>,
}

impl Default for AdamWConfig {
    fn default() -> Self {
        Self { learning_rate: 1e-4, weight_decay: 5e-4, beta1: 0.9, beta2: 0.999, eps: 1e-8, max_grad_norm: None }
    }
}

impl AdamWConfig {
    /// Checks every field's range and names the wrong one.
    pub fn validate(&self) -> Result<()> {
        let bad = |field: &str, value: f64, want: &str| {
            Err(PolicyError::Invalid(format!("AdamW config: {field} = {value}, expected {want}")))
        };
        if !(self.learning_rate.is_finite() && self.learning_rate >= 0.0) {
            return bad("learning_rate", self.learning_rate, "a finite value >= 0");
        }
        if !(self.weight_decay.is_finite() && self.weight_decay >= 0.0) {
            return bad("weight_decay", self.weight_decay, "a finite value >= 0");
        }
        if !(0.0..1.0).contains(&self.beta1) {
            return bad("beta1", self.beta1, "a value in [0, 1)");
        }
        if !(0.0..1.0).contains(&self.beta2) {
            return bad("beta2", self.beta2, "a value in [0, 1)");
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return bad("eps", self.eps, "a finite value > 0");
        }
        if let Some(max) = self.max_grad_norm
            && !(max.is_finite() && max > 0.0)
        {
            return bad("max_grad_norm", max, "a finite value > 0 (or none)");
        }
        Ok(())
    }
}

/// A validated optimiser state waiting to be installed.
pub(crate) struct StagedAdamWState {
    step: u64,
    moments: Vec<(Vec<f32>, Vec<f32>)>,
}

struct AdamWParam {
    name: String,
    var: Var,
    /// First moment, f32, same element count as the variable.
    m: Vec<f32>,
    /// Second moment.
    v: Vec<f32>,
}

/// What one optimiser step did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamWStepStats {
    /// The step just taken (1 for the first).
    pub step: u64,
    /// Global L2 norm of the gradients before clipping.
    pub grad_norm: f64,
    /// Factor the gradients were multiplied by (1 when not clipped).
    pub clip_scale: f64,
    /// Variables that had no gradient this step and were left untouched.
    pub vars_without_grad: usize,
}

/// AdamW (Loshchilov & Hutter) with decoupled weight decay, as PyTorch's
/// `torch.optim.AdamW`:
/// `theta *= 1 - lr*wd; m = b1 m + (1-b1) g; v = b2 v + (1-b2) g^2;
/// theta -= lr/(1-b1^t) * m / (sqrt(v)/sqrt(1-b2^t) + eps)`.
///
/// Variables without a gradient in a step are skipped (no decay, moments
/// unchanged); the step counter `t` is global.
pub struct AdamW {
    config: AdamWConfig,
    params: Vec<AdamWParam>,
    step: u64,
}

impl AdamW {
    /// An optimiser over every variable of `varmap` (create the model first),
    /// with zero moments and step 0.
    pub fn new(varmap: &VarMap, config: AdamWConfig) -> Result<Self> {
        config.validate()?;
        let params = named_vars(varmap, "AdamW")?
            .into_iter()
            .map(|nv| {
                let n = nv.var.elem_count();
                AdamWParam { name: nv.name, var: nv.var, m: vec![0.0; n], v: vec![0.0; n] }
            })
            .collect();
        Ok(Self { config, params, step: 0 })
    }

    pub fn config(&self) -> &AdamWConfig {
        &self.config
    }

    /// Current learning rate.
    pub fn learning_rate(&self) -> f64 {
        self.config.learning_rate
    }

    /// Sets the learning rate for the next steps (for a schedule).
    pub fn set_learning_rate(&mut self, learning_rate: f64) -> Result<()> {
        if !(learning_rate.is_finite() && learning_rate >= 0.0) {
            return Err(PolicyError::Invalid(format!("learning rate {learning_rate}: expected a finite value >= 0")));
        }
        self.config.learning_rate = learning_rate;
        Ok(())
    }

    /// Steps taken so far.
    pub fn step_count(&self) -> u64 {
        self.step
    }

    /// `loss.backward()` then [`AdamW::step`].
    pub fn backward_step(&mut self, loss: &Tensor) -> Result<AdamWStepStats> {
        let grads = loss.backward()?;
        self.step(&grads)
    }

    /// One update from the gradients in `grads`. Fails without changing
    /// anything when the gradient norm is not finite (lower the learning rate
    /// or enable `max_grad_norm`).
    pub fn step(&mut self, grads: &GradStore) -> Result<AdamWStepStats> {
        // Gather gradients first (fixed order) so a failure changes nothing.
        let mut flat_grads: Vec<Option<Vec<f32>>> = Vec::with_capacity(self.params.len());
        for p in &self.params {
            match grads.get(p.var.as_tensor()) {
                Some(g) => {
                    if g.shape() != p.var.shape() {
                        return Err(PolicyError::Invalid(format!(
                            "gradient of '{}' has shape {:?}, the variable {:?}",
                            p.name,
                            g.dims(),
                            p.var.dims()
                        )));
                    }
                    flat_grads.push(Some(to_f32_vec(g)?));
                }
                None => flat_grads.push(None),
            }
        }
        let vars_without_grad = flat_grads.iter().filter(|g| g.is_none()).count();
        // Per-variable sums of squares in f64 (each sequential), then summed in name order.
        let sq_sums: Vec<f64> = flat_grads
            .par_iter()
            .map(|g| g.as_ref().map_or(0.0, |g| g.iter().map(|&x| (x as f64) * (x as f64)).sum()))
            .collect();
        let grad_norm = sq_sums.iter().sum::<f64>().sqrt();
        if !grad_norm.is_finite() {
            return Err(PolicyError::Invalid(format!(
                "AdamW step {}: gradient norm is {grad_norm}; the update was skipped (lower the learning rate or set max_grad_norm)",
                self.step + 1
            )));
        }
        let clip_scale = match self.config.max_grad_norm {
            Some(max) if grad_norm > max => max / (grad_norm + 1e-6),
            _ => 1.0,
        };

        let step = self.step + 1;
        let cfg = &self.config;
        let lr = cfg.learning_rate;
        let decay = (1.0 - lr * cfg.weight_decay) as f32;
        let bias1 = 1.0 - cfg.beta1.powf(step as f64);
        let bias2 = 1.0 - cfg.beta2.powf(step as f64);
        let step_size = (lr / bias1) as f32;
        let inv_sqrt_bias2 = (1.0 / bias2.sqrt()) as f32;
        let (b1, b2) = (cfg.beta1 as f32, cfg.beta2 as f32);
        let (one_minus_b1, one_minus_b2) = ((1.0 - cfg.beta1) as f32, (1.0 - cfg.beta2) as f32);
        let eps = cfg.eps as f32;
        let clip = clip_scale as f32;

        let updated: Vec<Option<Vec<f32>>> = self
            .params
            .par_iter_mut()
            .zip(flat_grads.into_par_iter())
            .map(|(p, grad)| -> Result<Option<Vec<f32>>> {
                let Some(grad) = grad else { return Ok(None) };
                let mut theta = to_f32_vec(p.var.as_tensor())?;
                for i in 0..theta.len() {
                    let g = if clip_scale != 1.0 { grad[i] * clip } else { grad[i] };
                    let m = b1 * p.m[i] + one_minus_b1 * g;
                    let v = b2 * p.v[i] + one_minus_b2 * g * g;
                    p.m[i] = m;
                    p.v[i] = v;
                    let denom = v.sqrt() * inv_sqrt_bias2 + eps;
                    theta[i] = theta[i] * decay - step_size * m / denom;
                }
                Ok(Some(theta))
            })
            .collect::<Result<_>>()?;
        for (p, theta) in self.params.iter().zip(updated) {
            if let Some(theta) = theta {
                let t = Tensor::from_vec(theta, p.var.shape(), p.var.device())?;
                p.var.set(&t)?;
            }
        }
        self.step = step;
        Ok(AdamWStepStats { step, grad_norm, clip_scale, vars_without_grad })
    }

    /// The optimiser state as tensors: `{prefix}m.{var}`, `{prefix}v.{var}`
    /// (f32, the variable's shape) and `{prefix}step` (i64 `[1]`).
    pub fn state_tensors(&self, prefix: &str) -> Result<HashMap<String, Tensor>> {
        let mut out = HashMap::with_capacity(2 * self.params.len() + 1);
        for p in &self.params {
            let shape = p.var.shape();
            let dev = p.var.device();
            out.insert(format!("{prefix}m.{}", p.name), Tensor::from_slice(&p.m, shape, dev)?);
            out.insert(format!("{prefix}v.{}", p.name), Tensor::from_slice(&p.v, shape, dev)?);
        }
        let dev = self.params.first().map_or(Device::Cpu, |p| p.var.device().clone());
        out.insert(format!("{prefix}step"), scalar_i64(self.step, &dev)?);
        Ok(out)
    }

    /// Restores the state written by [`AdamW::state_tensors`] with the same
    /// prefix. Every variable's moments must be present with its shape and no
    /// unknown tensor may appear; on error nothing is changed. `source` names
    /// the file in error messages.
    pub fn load_state_tensors(&mut self, tensors: &HashMap<String, Tensor>, prefix: &str, source: &Path) -> Result<()> {
        let staged = self.stage_state(tensors, prefix, source)?;
        self.apply_state(staged);
        Ok(())
    }

    /// Validates a saved state without changing anything (first half of a load).
    pub(crate) fn stage_state(
        &self,
        tensors: &HashMap<String, Tensor>,
        prefix: &str,
        source: &Path,
    ) -> Result<StagedAdamWState> {
        let step = read_counter(tensors, &format!("{prefix}step"), source)?;
        let mut expected = std::collections::HashSet::new();
        expected.insert(format!("{prefix}step"));
        let mut moments = Vec::with_capacity(self.params.len());
        for p in &self.params {
            let (m_name, v_name) = (format!("{prefix}m.{}", p.name), format!("{prefix}v.{}", p.name));
            let m = read_state_buffer(tensors, &m_name, p.var.shape(), source)?;
            let v = read_state_buffer(tensors, &v_name, p.var.shape(), source)?;
            expected.insert(m_name);
            expected.insert(v_name);
            moments.push((m, v));
        }
        reject_unexpected(tensors, &expected, source)?;
        Ok(StagedAdamWState { step, moments })
    }

    /// Installs a state checked by [`AdamW::stage_state`] (cannot fail).
    pub(crate) fn apply_state(&mut self, staged: StagedAdamWState) {
        for (p, (m, v)) in self.params.iter_mut().zip(staged.moments) {
            p.m = m;
            p.v = v;
        }
        self.step = staged.step;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::checkpoint::format::OPTIMIZER_PREFIX;
    use crate::policy::checkpoint::weights::{read_safetensors, write_safetensors};
    use crate::policy::training::test_support::{loss, tiny_model, values};

    #[test]
    fn adamw_matches_hand_computation() {
        let (varmap, w, b) = tiny_model();
        let cfg = AdamWConfig { learning_rate: 0.1, weight_decay: 0.01, ..Default::default() };
        let mut opt = AdamW::new(&varmap, cfg.clone()).unwrap();
        // Reference in f64, same maths.
        let mut theta = [1.0f64, -2.0, 0.5];
        let (mut m, mut v) = ([0.0f64; 3], [0.0f64; 3]);
        for k in 0..3 {
            let x = [1.0 + k as f64, 0.5];
            let y = 3.0 - 0.1 * k as f64;
            let r = theta[0] * x[0] + theta[1] * x[1] + theta[2] - y;
            let g = [2.0 * r * x[0], 2.0 * r * x[1], 2.0 * r];
            let t = (k + 1) as i32;
            for i in 0..3 {
                theta[i] *= 1.0 - cfg.learning_rate * cfg.weight_decay;
                m[i] = 0.9 * m[i] + 0.1 * g[i];
                v[i] = 0.999 * v[i] + 0.001 * g[i] * g[i];
                let mhat = m[i] / (1.0 - 0.9f64.powi(t));
                let vhat = v[i] / (1.0 - 0.999f64.powi(t));
                theta[i] -= cfg.learning_rate * mhat / (vhat.sqrt() + 1e-8);
            }
            let stats = opt.backward_step(&loss(&w, &b, k)).unwrap();
            assert_eq!(stats.step, k as u64 + 1);
            let got = [values(&w)[0], values(&w)[1], values(&b)[0]];
            for i in 0..3 {
                assert!((got[i] as f64 - theta[i]).abs() < 1e-5, "step {k} param {i}: {got:?} vs {theta:?}");
            }
        }
    }

    #[test]
    fn gradient_clipping_scales_to_max_norm() {
        let (varmap, w, b) = tiny_model();
        let cfg = AdamWConfig { max_grad_norm: Some(0.5), ..Default::default() };
        let mut opt = AdamW::new(&varmap, cfg).unwrap();
        let grads = loss(&w, &b, 0).backward().unwrap();
        let stats = opt.step(&grads).unwrap();
        assert!(stats.grad_norm > 0.5);
        assert!((stats.grad_norm * stats.clip_scale - 0.5).abs() < 1e-5);
        assert!(AdamW::new(&varmap, AdamWConfig { max_grad_norm: Some(-1.0), ..Default::default() }).is_err());
    }

    #[test]
    fn adamw_save_load_resumes_bit_identically() {
        let dir = std::env::temp_dir().join(format!("policy_train_adamw_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("opt.safetensors");
        let cfg = AdamWConfig { learning_rate: 0.05, ..Default::default() };

        // Uninterrupted: 4 steps.
        let (vm_a, wa, ba) = tiny_model();
        let mut opt_a = AdamW::new(&vm_a, cfg.clone()).unwrap();
        for k in 0..4 {
            opt_a.backward_step(&loss(&wa, &ba, k)).unwrap();
        }
        // Interrupted after 3: save weights + optimiser, rebuild, load, 1 more.
        let (vm_b, wb, bb) = tiny_model();
        let mut opt_b = AdamW::new(&vm_b, cfg.clone()).unwrap();
        for k in 0..3 {
            opt_b.backward_step(&loss(&wb, &bb, k)).unwrap();
        }
        write_safetensors(&opt_b.state_tensors(OPTIMIZER_PREFIX).unwrap(), &path).unwrap();
        let (saved_w, saved_b) = (values(&wb), values(&bb));
        let (vm_c, wc, bc) = tiny_model();
        wc.set(&Tensor::new(saved_w.as_slice(), &Device::Cpu).unwrap()).unwrap();
        bc.set(&Tensor::new(saved_b.as_slice(), &Device::Cpu).unwrap()).unwrap();
        let mut opt_c = AdamW::new(&vm_c, cfg).unwrap();
        opt_c.load_state_tensors(&read_safetensors(&path, &Device::Cpu).unwrap(), OPTIMIZER_PREFIX, &path).unwrap();
        assert_eq!(opt_c.step_count(), 3);
        opt_c.backward_step(&loss(&wc, &bc, 3)).unwrap();
        assert_eq!(values(&wa), values(&wc));
        assert_eq!(values(&ba), values(&bc));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn adamw_load_rejects_missing_moment() {
        let (varmap, _, _) = tiny_model();
        let mut opt = AdamW::new(&varmap, AdamWConfig::default()).unwrap();
        let mut state = opt.state_tensors("adamw.").unwrap();
        state.remove("adamw.v.w");
        let err = opt.load_state_tensors(&state, "adamw.", Path::new("opt.safetensors")).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("opt.safetensors") && msg.contains("adamw.v.w"), "{msg}");
    }
}
