//! Reference implementations from ordinary candle ops and test helpers.
#![allow(dead_code)]
use candle_core::{DType, Device, IndexOp, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub type TestResult = Result<(), Box<dyn std::error::Error>>;

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

pub fn normal(rng: &mut ChaCha8Rng) -> f32 {
    // Box-Muller
    let (u1, u2): (f32, f32) = (rng.random_range(1e-7..1.0), rng.random());
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

pub fn tensor(rng: &mut ChaCha8Rng, shape: &[usize], f: impl Fn(&mut ChaCha8Rng) -> f32) -> Tensor {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| f(rng)).collect();
    Tensor::from_vec(v, shape, &Device::Cpu).expect("shape matches data")
}

pub fn randn(rng: &mut ChaCha8Rng, shape: &[usize]) -> Tensor {
    tensor(rng, shape, normal)
}

/// max |got - want| / max |want|
pub fn rel_err(got: &Tensor, want: &Tensor) -> f32 {
    let max_abs = |t: Tensor| -> f32 {
        t.abs().and_then(|t| t.flatten_all()).and_then(|t| t.max(0)).and_then(|t| t.to_scalar::<f32>()).expect("max")
    };
    assert_eq!(got.dims(), want.dims(), "shapes differ");
    let diff = max_abs((got - want).expect("same shape"));
    diff / max_abs(want.clone()).max(1e-12)
}

/// The selective scan with ordinary candle ops, one token at a time:
/// u, delta_raw [B, L, Di]; b, c [B, L, N]; a [Di, N]; d, delta_bias [Di].
/// Returns (y [B, L, Di], h_last [B, Di, N]).
#[allow(clippy::too_many_arguments)]
pub fn reference_scan(
    u: &Tensor,
    delta_raw: &Tensor,
    b: &Tensor,
    c: &Tensor,
    a: &Tensor,
    d: &Tensor,
    delta_bias: &Tensor,
    h0: Option<&Tensor>,
) -> candle_core::Result<(Tensor, Tensor)> {
    let (batch, seq_len, d_inner) = u.dims3()?;
    let d_state = a.dim(1)?;
    let delta = (delta_raw.broadcast_add(delta_bias)?.exp()? + 1.0)?.log()?;
    let mut h = match h0 {
        Some(h0) => h0.clone(),
        None => Tensor::zeros((batch, d_inner, d_state), DType::F32, &Device::Cpu)?,
    };
    let mut ys = Vec::with_capacity(seq_len);
    for t in 0..seq_len {
        let dt = delta.i((.., t, ..))?;
        let ut = u.i((.., t, ..))?;
        let bt = b.i((.., t, ..))?;
        let ct = c.i((.., t, ..))?;
        let decay = dt.unsqueeze(2)?.broadcast_mul(&a.unsqueeze(0)?)?.exp()?;
        let drive = (&dt * &ut)?.unsqueeze(2)?.broadcast_mul(&bt.unsqueeze(1)?)?;
        h = ((decay * &h)? + drive)?;
        let y = (h.broadcast_mul(&ct.unsqueeze(1)?)?.sum(2)? + ut.broadcast_mul(d)?)?;
        ys.push(y);
    }
    Ok((Tensor::stack(&ys, 1)?, h))
}
