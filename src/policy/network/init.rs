//! Seeded weight initialisation. candle's CPU random generator cannot be seeded, so a model
//! built with `VarBuilder::from_varmap` starts from different weights every run. This backend
//! creates the same variables in a `VarMap` (same names, same distributions as the layers ask
//! for through their `Init` hints), drawn from a ChaCha generator keyed by (seed, variable name):
//! a seed fixes the initial weights, independently of the order in which layers are built.
use candle_core::{DType, Device, Result, Shape, Tensor, Var};
use candle_nn::init::NormalOrUniform;
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder, VarMap};
use rand::{Rng, SeedableRng};

/// A `VarMap` that fills new variables from a seed.
struct SeededVarMap {
    varmap: VarMap,
    seed: u64,
}

/// A `VarBuilder` creating the model's variables in `varmap`, initialised from `seed`.
pub fn seeded_var_builder(varmap: &VarMap, seed: u64, device: &Device) -> VarBuilder<'static> {
    VarBuilder::from_backend(Box::new(SeededVarMap { varmap: varmap.clone(), seed }), DType::F32, device.clone())
}

fn name_key(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3))
}

/// Values of `init` for `shape`, drawn from a generator keyed by (seed, name).
fn draw(init: &Init, shape: &Shape, name: &str, seed: u64) -> Vec<f32> {
    let n = shape.elem_count();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ name_key(name));
    let normal = |mean: f64, std: f64, rng: &mut rand_chacha::ChaCha8Rng| {
        // Box-Muller.
        let u1: f64 = rng.random_range(f64::EPSILON..1.0);
        let u2: f64 = rng.random_range(0.0..1.0);
        (mean + std * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
    };
    match *init {
        Init::Const(v) => vec![v as f32; n],
        Init::Randn { mean, stdev } => (0..n).map(|_| normal(mean, stdev, &mut rng)).collect(),
        Init::Uniform { lo, up } => (0..n).map(|_| rng.random_range(lo..up) as f32).collect(),
        Init::Kaiming { dist, fan, non_linearity } => {
            let std = non_linearity.gain() / (fan.for_shape(shape) as f64).sqrt();
            match dist {
                NormalOrUniform::Uniform => {
                    let bound = 3f64.sqrt() * std;
                    (0..n).map(|_| rng.random_range(-bound..bound) as f32).collect()
                }
                NormalOrUniform::Normal => (0..n).map(|_| normal(0.0, std, &mut rng)).collect(),
            }
        }
    }
}

impl SimpleBackend for SeededVarMap {
    fn get(&self, shape: Shape, name: &str, init: Init, dtype: DType, device: &Device) -> Result<Tensor> {
        let data = self.varmap.data();
        let mut vars = data.lock().map_err(|_| candle_core::Error::Msg("the VarMap lock is poisoned".into()))?;
        if let Some(var) = vars.get(name) {
            if var.shape() != &shape {
                candle_core::bail!("variable {name} has shape {:?}, the layer asks for {shape:?}", var.shape());
            }
            return Ok(var.as_tensor().clone());
        }
        let values = Tensor::from_vec(draw(&init, &shape, name, self.seed), shape, device)?.to_dtype(dtype)?;
        let var = Var::from_tensor(&values)?;
        let tensor = var.as_tensor().clone();
        vars.insert(name.to_string(), var);
        Ok(tensor)
    }

    fn get_unchecked(&self, name: &str, _dtype: DType, _device: &Device) -> Result<Tensor> {
        candle_core::bail!("variable {name} must be created with a shape and an initialisation")
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.varmap.data().lock().map(|v| v.contains_key(name)).unwrap_or(false)
    }
}
