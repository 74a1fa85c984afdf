//! The selective-scan op against a naive reference built from ordinary candle
//! ops (an L-step loop; candle autodiff for its gradients).
mod policy_reference;
use candle_core::{DType, Device, Tensor, Var};
use flowram::policy::kernels::selective_scan::{
    ScanInputs, selective_scan, selective_scan_with_state, selective_scan_with_state_gated,
};
use policy_reference::{TestResult, normal, rel_err, tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

struct Case {
    u: Var,
    delta_raw: Var,
    b: Var,
    c: Var,
    a: Var,
    d: Var,
    delta_bias: Var,
}

impl Case {
    fn random(seed: u64, batch: usize, seq_len: usize, d_inner: usize, d_state: usize) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let var = |t: Tensor| Var::from_tensor(&t).expect("var");
        Self {
            u: var(tensor(&mut rng, &[batch, seq_len, d_inner], normal)),
            delta_raw: var(tensor(&mut rng, &[batch, seq_len, d_inner], |r| normal(r) * 1.5)),
            b: var(tensor(&mut rng, &[batch, seq_len, d_state], normal)),
            c: var(tensor(&mut rng, &[batch, seq_len, d_state], normal)),
            // A = -exp(A_log) with A_log around log(1..N)
            a: var(tensor(&mut rng, &[d_inner, d_state], |r| -r.random_range(0.05f32..8.0))),
            d: var(tensor(&mut rng, &[d_inner], normal)),
            delta_bias: var(tensor(&mut rng, &[d_inner], |r| r.random_range(-5.0f32..0.5))),
        }
    }

    fn inputs(&self) -> ScanInputs<'_> {
        ScanInputs {
            u: self.u.as_tensor(),
            delta_raw: self.delta_raw.as_tensor(),
            b: self.b.as_tensor(),
            c: self.c.as_tensor(),
            a: self.a.as_tensor(),
            d: self.d.as_tensor(),
            delta_bias: self.delta_bias.as_tensor(),
        }
    }

    fn vars(&self) -> [(&'static str, &Var); 7] {
        [
            ("u", &self.u),
            ("delta_raw", &self.delta_raw),
            ("B", &self.b),
            ("C", &self.c),
            ("A", &self.a),
            ("D", &self.d),
            ("delta_bias", &self.delta_bias),
        ]
    }
}

fn reference_scan(x: &ScanInputs, h0: Option<&Tensor>) -> candle_core::Result<(Tensor, Tensor)> {
    policy_reference::reference_scan(x.u, x.delta_raw, x.b, x.c, x.a, x.d, x.delta_bias, h0)
}

fn check_forward_backward(seed: u64, batch: usize, seq_len: usize, d_inner: usize, d_state: usize) -> TestResult {
    let case = Case::random(seed, batch, seq_len, d_inner, d_state);
    let x = case.inputs();
    let mut rng = ChaCha8Rng::seed_from_u64(seed + 1000);
    // A random projection of y as the loss, so dL/dy is not uniform.
    let weight = tensor(&mut rng, &[batch, seq_len, d_inner], normal);

    let y = selective_scan(&x)?;
    let (y_ref, _) = reference_scan(&x, None)?;
    let err = rel_err(&y, &y_ref);
    println!("B={batch} L={seq_len} Di={d_inner} N={d_state}: y rel err {err:.2e}");
    assert!(err < 1e-4, "forward: rel err {err}");

    let grads = (&y * &weight)?.sum_all()?.backward()?;
    let grads_ref = (&y_ref * &weight)?.sum_all()?.backward()?;
    for (name, var) in case.vars() {
        let g = grads.get(var).ok_or(format!("no gradient for {name}"))?;
        let g_ref = grads_ref.get(var).ok_or(format!("no reference gradient for {name}"))?;
        assert_eq!(g.dims(), g_ref.dims(), "{name}");
        let err = rel_err(g, g_ref);
        println!("  d/d{name}: rel err {err:.2e}");
        assert!(err < 1e-4, "gradient of {name}: rel err {err}");
    }
    Ok(())
}

#[test]
fn odd_sizes_match_reference() -> TestResult {
    check_forward_backward(1, 3, 7, 5, 3)
}

#[test]
fn single_token_matches_reference() -> TestResult {
    check_forward_backward(2, 2, 1, 19, 4)
}

#[test]
fn channel_group_boundaries_match_reference() -> TestResult {
    // 33 channels = two full groups of 16 and one of 1.
    check_forward_backward(3, 2, 13, 33, 16)
}

#[test]
fn realistic_size_matches_reference() -> TestResult {
    // FlowRAM's Mamba: d_inner = 2 x 120, d_state = 16.
    check_forward_backward(4, 2, 200, 240, 16)
}

#[test]
fn prefix_then_suffix_equals_whole_sequence() -> TestResult {
    let (batch, seq_len, d_inner, d_state, split) = (2, 37, 40, 16, 29);
    let case = Case::random(5, batch, seq_len, d_inner, d_state);
    let x = case.inputs();
    let part = |start: usize, len: usize| -> candle_core::Result<[Tensor; 4]> {
        Ok([
            x.u.narrow(1, start, len)?,
            x.delta_raw.narrow(1, start, len)?,
            x.b.narrow(1, start, len)?,
            x.c.narrow(1, start, len)?,
        ])
    };
    fn sub<'a>(x: &ScanInputs<'a>, p: &'a [Tensor; 4]) -> ScanInputs<'a> {
        ScanInputs { u: &p[0], delta_raw: &p[1], b: &p[2], c: &p[3], ..*x }
    }
    let (y_all, h_all) = selective_scan_with_state(&x, None)?;
    let prefix = part(0, split)?;
    let suffix = part(split, seq_len - split)?;
    let (y_prefix, h_prefix) = selective_scan_with_state(&sub(&x, &prefix), None)?;
    let h_prefix_copy = h_prefix.copy()?;
    let (y_suffix, h_suffix) = selective_scan_with_state(&sub(&x, &suffix), Some(&h_prefix))?;
    // The cached state is not consumed: the suffix can run again from it.
    let (y_suffix2, _) = selective_scan_with_state(&sub(&x, &suffix), Some(&h_prefix))?;
    assert_eq!(rel_err(&h_prefix, &h_prefix_copy), 0.0);
    assert_eq!(rel_err(&y_suffix2, &y_suffix), 0.0);

    let y_joined = Tensor::cat(&[&y_prefix, &y_suffix], 1)?;
    let err = rel_err(&y_joined, &y_all);
    assert!(err < 1e-6, "prefix+suffix vs whole: rel err {err}");
    assert!(rel_err(&h_suffix, &h_all) < 1e-6);

    // The stateful scan agrees with the differentiable one and the reference.
    let y_op = selective_scan(&x)?;
    assert!(rel_err(&y_all, &y_op) < 1e-6);
    let (y_ref, h_ref) = reference_scan(&sub(&x, &suffix), Some(&h_prefix))?;
    assert!(rel_err(&y_suffix, &y_ref) < 1e-4);
    assert!(rel_err(&h_suffix, &h_ref) < 1e-4);

    // The fused output gate: y * SiLU(z).
    let z = (tensor(&mut ChaCha8Rng::seed_from_u64(55), &[batch, seq_len - split, d_inner], normal) * 3.0)?;
    let (gated, h_gated) = selective_scan_with_state_gated(&sub(&x, &suffix), Some(&h_prefix), &z)?;
    let want = (&y_ref * (&z * candle_nn::ops::sigmoid(&z)?)?)?;
    let err = rel_err(&gated, &want);
    assert!(err < 1e-4, "gated scan: rel err {err}");
    assert_eq!(rel_err(&h_gated, &h_suffix), 0.0);
    Ok(())
}

#[test]
fn bad_shapes_are_rejected() {
    let case = Case::random(6, 1, 4, 8, 4);
    let wrong = Tensor::zeros((1, 4, 5), DType::F32, &Device::Cpu).expect("zeros");
    let x = ScanInputs { b: &wrong, ..case.inputs() };
    let err = selective_scan(&x).expect_err("mismatched B must be rejected");
    assert!(err.to_string().contains("B must have shape"), "{err}");
}
