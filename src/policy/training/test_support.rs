//! Test support: a two-variable model for the optimiser, EMA and checkpoint tests, and metrics
//! rows and a scratch folder for the metrics and loss-plot tests.
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{Init, VarBuilder, VarMap};

/// A VarMap with w [2] and b [1], initialised to known values.
pub fn tiny_model() -> (VarMap, Var, Var) {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    vb.get_with_hints(2, "w", Init::Const(0.0)).unwrap();
    vb.get_with_hints(1, "b", Init::Const(0.0)).unwrap();
    let data = varmap.data().lock().unwrap();
    let (w, b) = (data["w"].clone(), data["b"].clone());
    drop(data);
    w.set(&Tensor::new(&[1.0f32, -2.0], &Device::Cpu).unwrap()).unwrap();
    b.set(&Tensor::new(&[0.5f32], &Device::Cpu).unwrap()).unwrap();
    (varmap, w, b)
}

/// Loss (w . x + b - y)^2 for a fixed sample indexed by `k`.
pub fn loss(w: &Var, b: &Var, k: usize) -> Tensor {
    let x = Tensor::new(&[[1.0f32 + k as f32], [0.5]], &Device::Cpu).unwrap();
    let pred = w.as_tensor().unsqueeze(0).unwrap().matmul(&x).unwrap().squeeze(0).unwrap();
    let y = 3.0 - 0.1 * k as f64;
    (pred + b.as_tensor()).unwrap().affine(1.0, -y).unwrap().sqr().unwrap().sum_all().unwrap()
}

pub fn values(v: &Var) -> Vec<f32> {
    v.as_tensor().to_vec1().unwrap()
}

/// A fresh scratch folder for test `tag`.
pub fn tmp_dir(tag: &str) -> std::path::PathBuf {
    let p = std::env::temp_dir().join(format!("policy_train_metrics_{tag}_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&p);
    std::fs::create_dir_all(&p).unwrap();
    p
}

/// A metrics row of a falling loss at `step`.
pub fn metrics_row(step: u64) -> crate::policy::training::metrics::MetricsRow {
    let loss = 10.0 / step as f64;
    crate::policy::training::metrics::MetricsRow {
        step,
        loss,
        cfm: loss * 0.008,
        bce: loss * 0.02,
        lr: 1e-4,
        seconds: step as f64 * 0.5,
    }
}
