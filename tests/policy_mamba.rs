//! The fused block ops and the Mamba stack against references built from
//! ordinary candle ops (autodiff for gradients), the cached prefix against the
//! whole sequence, and the initialisation and checkpoint format.
mod policy_reference;
use candle_core::{D, DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use flowram::policy::kernels::mamba_ops::{ada_rms_norm, causal_conv_silu, gated_residual, silu_gate};
use flowram::policy::network::mamba::{Conditioning, MambaConfig, MambaStack, StackState};
use policy_reference::{TestResult, randn, reference_scan, rel_err, rng};

const TOL: f32 = 1e-4;

fn var(t: Tensor) -> Var {
    Var::from_tensor(&t).expect("var")
}

fn silu(x: &Tensor) -> candle_core::Result<Tensor> {
    x * candle_nn::ops::sigmoid(x)?
}

fn rms_norm_ref(x: &Tensor, w: &Tensor, eps: f64) -> candle_core::Result<Tensor> {
    let ms = x.sqr()?.mean_keepdim(D::Minus1)?;
    x.broadcast_div(&(ms + eps)?.sqrt()?)?.broadcast_mul(w)
}

/// Causal depthwise conv as PyTorch defines it: Conv1d(groups = Di,
/// padding = K - 1) on [B, Di, L], first L outputs. x [B, L, Di], w [Di, K].
fn conv_ref(x: &Tensor, w: &Tensor, bias: &Tensor) -> candle_core::Result<Tensor> {
    let (_, l, di) = x.dims3()?;
    let k = w.dim(1)?;
    let y = x.transpose(1, 2)?.contiguous()?.conv1d(&w.reshape((di, 1, k))?, k - 1, 1, 1, di)?;
    y.narrow(2, 0, l)?.transpose(1, 2)?.broadcast_add(bias)
}

/// Checks value and gradients (of a random projection of the output) of `got`
/// against `want` for every listed var.
fn check_grads(name: &str, got: &Tensor, want: &Tensor, vars: &[(&str, &Var)], seed: u64) -> TestResult {
    let err = rel_err(got, want);
    println!("{name}: forward rel err {err:.2e}");
    assert!(err < TOL, "{name} forward: {err}");
    let proj = randn(&mut rng(seed), got.dims());
    let g = (got * &proj)?.sum_all()?.backward()?;
    let g_ref = (want * &proj)?.sum_all()?.backward()?;
    for (vname, v) in vars {
        let a = g.get(v).ok_or(format!("{name}: no gradient for {vname}"))?;
        let b = g_ref.get(v).ok_or(format!("{name}: no reference gradient for {vname}"))?;
        let err = rel_err(a, b);
        println!("  d/d{vname}: rel err {err:.2e}");
        assert!(err < TOL, "{name}: gradient of {vname}: {err}");
    }
    Ok(())
}

#[test]
fn ada_rms_norm_matches_reference() -> TestResult {
    let r = &mut rng(10);
    let (b, l, c) = (2, 5, 37);
    let x = var(randn(r, &[b, l, c]));
    let w = var(randn(r, &[c]));
    let m = var(randn(r, &[b, 1, 2 * c])); // one condition per sequence, broadcast
    let mb = m.as_tensor().broadcast_as((b, l, 2 * c))?;
    let got = ada_rms_norm(&x, &w, &mb, 1e-5)?;
    let (shift, scale) = (mb.narrow(2, 0, c)?, mb.narrow(2, c, c)?);
    let want = ((rms_norm_ref(&x, &w, 1e-5)? * (scale + 1.0)?)? + shift)?;
    check_grads("ada_rms_norm", &got, &want, &[("x", &x), ("weight", &w), ("shift_scale", &m)], 11)
}

#[test]
fn causal_conv_silu_matches_pytorch_conv1d() -> TestResult {
    let r = &mut rng(20);
    let (b, l, di, k) = (2, 9, 21, 4);
    // x is the first half of a [B, L, 2 Di] projection, as in the mixer.
    let xz = var(randn(r, &[b, l, 2 * di]));
    let x = xz.as_tensor().narrow(2, 0, di)?;
    let w = var(randn(r, &[di, k]));
    let bias = var(randn(r, &[di]));
    let got = causal_conv_silu(&x, &w, &bias, None)?;
    let want = silu(&conv_ref(&x, &w, &bias)?)?;
    check_grads("causal_conv_silu", &got, &want, &[("x", &xz), ("weight", &w), ("bias", &bias)], 21)
}

#[test]
fn causal_conv_with_tail_continues_the_sequence() -> TestResult {
    let r = &mut rng(30);
    let (b, di, k) = (2, 19, 4);
    let w = randn(r, &[di, k]);
    let bias = randn(r, &[di]);
    let whole = randn(r, &[b, 12, di]);
    let want = causal_conv_silu(&whole, &w, &bias, None)?;
    for (start, len) in [(3, 9), (10, 2), (11, 1), (5, 4)] {
        let tail = whole.narrow(1, start - (k - 1), k - 1)?;
        let got = causal_conv_silu(&whole.narrow(1, start, len)?, &w, &bias, Some(&tail))?;
        let err = rel_err(&got, &want.narrow(1, start, len)?);
        assert!(err < 1e-6, "start {start} len {len}: {err}");
    }
    Ok(())
}

#[test]
fn silu_gate_matches_reference() -> TestResult {
    let r = &mut rng(40);
    let (b, l, di) = (3, 4, 35);
    let y = var(randn(r, &[b, l, di]));
    let xz = var((randn(r, &[b, l, 2 * di]) * 3.0)?);
    let z = xz.as_tensor().narrow(2, di, di)?;
    let got = silu_gate(&y, &z)?;
    let want = (y.as_tensor() * silu(&z)?)?;
    check_grads("silu_gate", &got, &want, &[("y", &y), ("z", &xz)], 41)
}

#[test]
fn gated_residual_matches_reference() -> TestResult {
    let r = &mut rng(50);
    let (b, l, c) = (2, 6, 17);
    let x = var(randn(r, &[b, l, c]));
    let m = var(randn(r, &[b, l, c]));
    let gate = var(randn(r, &[b, 1, c]));
    let gb = gate.as_tensor().broadcast_as((b, l, c))?;
    let got = gated_residual(&x, &m, &gb)?;
    let want = (x.as_tensor() + (&gb * m.as_tensor())?)?;
    check_grads("gated_residual", &got, &want, &[("x", &x), ("mixed", &m), ("gate", &gate)], 51)
}

// ---------------------------------------------------------------------------
// The stack

fn small_config() -> MambaConfig {
    MambaConfig {
        d_model: 12,
        d_state: 4,
        d_conv: 4,
        expand: 2, // d_inner 24: one full and one partial channel group
        n_layers: 2,
        d_cond: Some(5),
        ..MambaConfig::default()
    }
}

/// A stack whose every weight is moved away from its initialisation (the
/// AdaLN-Zero gates would otherwise hide the mixers).
fn perturbed_stack(cfg: &MambaConfig, seed: u64) -> Result<(VarMap, MambaStack), Box<dyn std::error::Error>> {
    let varmap = VarMap::new();
    let stack = MambaStack::new(cfg, VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu))?;
    let r = &mut rng(seed);
    let mut names: Vec<(String, Var)> =
        varmap.data().lock().map_err(|_| "poisoned")?.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
    names.sort_by(|a, b| a.0.cmp(&b.0));
    for (_, v) in names {
        let noise = (randn(r, v.dims()) * 0.3)?;
        v.set(&(v.as_tensor() + noise)?)?;
    }
    Ok((varmap, stack))
}

fn param(varmap: &VarMap, name: &str) -> Result<Tensor, Box<dyn std::error::Error>> {
    let data = varmap.data().lock().map_err(|_| "poisoned")?;
    Ok(data.get(name).ok_or(format!("no var {name}"))?.as_tensor().clone())
}

/// The stack from ordinary candle ops; cond per token [B, L, d_cond].
fn reference_stack(
    varmap: &VarMap,
    cfg: &MambaConfig,
    x: &Tensor,
    cond: &Tensor,
) -> Result<Tensor, Box<dyn std::error::Error>> {
    let (c, di, n, rk) = (cfg.d_model, cfg.d_inner(), cfg.d_state, cfg.dt_rank());
    let mut x = x.clone();
    for i in 0..cfg.n_layers {
        let p = |name: &str| param(varmap, &format!("layers.{i}.{name}"));
        let lin = |t: &Tensor, w: &Tensor| t.broadcast_matmul(&w.t()?);
        let modulation = lin(&silu(cond)?, &p("ada_ln.weight")?)?.broadcast_add(&p("ada_ln.bias")?)?;
        let (shift, scale, gate) =
            (modulation.narrow(2, 0, c)?, modulation.narrow(2, c, c)?, modulation.narrow(2, 2 * c, c)?);
        let h = ((rms_norm_ref(&x, &p("norm.weight")?, cfg.norm_eps)? * (scale + 1.0)?)? + shift)?;
        let xz = lin(&h, &p("mixer.in_proj.weight")?)?;
        let (xs, z) = (xz.narrow(2, 0, di)?, xz.narrow(2, di, di)?);
        let w = p("mixer.conv1d.weight")?.reshape((di, cfg.d_conv))?;
        let u = silu(&conv_ref(&xs, &w, &p("mixer.conv1d.bias")?)?)?;
        let dbc = lin(&u, &p("mixer.x_proj.weight")?)?;
        let delta_raw = lin(&dbc.narrow(2, 0, rk)?, &p("mixer.dt_proj.weight")?)?;
        let a = p("mixer.A_log")?.exp()?.neg()?;
        let (y, _) = reference_scan(
            &u,
            &delta_raw,
            &dbc.narrow(2, rk, n)?,
            &dbc.narrow(2, rk + n, n)?,
            &a,
            &p("mixer.D")?,
            &p("mixer.dt_proj.bias")?,
            None,
        )?;
        let mixed = lin(&(y * silu(&z)?)?, &p("mixer.out_proj.weight")?)?;
        x = (x + (gate * mixed)?)?;
    }
    Ok(rms_norm_ref(&x, &param(varmap, "norm_f.weight")?, cfg.norm_eps)?)
}

#[test]
fn stack_matches_reference_forward_and_gradients() -> TestResult {
    let cfg = small_config();
    let (varmap, stack) = perturbed_stack(&cfg, 60)?;
    let r = &mut rng(61);
    let (b, lp, ls) = (2, 6, 5);
    let x = var(randn(r, &[b, lp + ls, cfg.d_model]));
    let cond_prefix = var(randn(r, &[b, cfg.d_cond()]));
    let cond_suffix = var(randn(r, &[b, cfg.d_cond()]));
    let cond = Conditioning::prefix_suffix(lp, cond_prefix.as_tensor().clone(), ls, cond_suffix.as_tensor().clone());
    let got = stack.forward(&x, &cond)?;
    let per_token = Tensor::cat(
        &[
            cond_prefix.as_tensor().unsqueeze(1)?.broadcast_as((b, lp, cfg.d_cond()))?,
            cond_suffix.as_tensor().unsqueeze(1)?.broadcast_as((b, ls, cfg.d_cond()))?,
        ],
        1,
    )?;
    let want = reference_stack(&varmap, &cfg, &x, &per_token)?;
    let data = varmap.data().lock().map_err(|_| "poisoned")?.clone();
    let mut vars: Vec<(&str, &Var)> = data.iter().map(|(k, v)| (k.as_str(), v)).collect();
    vars.sort_by(|a, b| a.0.cmp(b.0));
    assert_eq!(vars.len(), 2 * 12 + 1, "weights per layer and norm_f");
    vars.extend([("x", &x), ("cond_prefix", &cond_prefix), ("cond_suffix", &cond_suffix)]);
    check_grads("stack", &got, &want, &vars, 62)?;

    // The per-token form of the condition gives the same result.
    let got_per_token = stack.forward(&x, &Conditioning::PerToken(per_token))?;
    assert!(rel_err(&got_per_token, &got) < 1e-6);
    Ok(())
}

fn copy_state(s: &StackState) -> Vec<(Tensor, Tensor)> {
    s.layers().iter().map(|l| (l.conv_tail.copy().expect("copy"), l.ssm_state.copy().expect("copy"))).collect()
}

#[test]
fn prefix_then_suffixes_equal_whole_sequence() -> TestResult {
    let cfg = MambaConfig { n_layers: 3, ..MambaConfig::default() };
    let (_varmap, stack) = perturbed_stack(&cfg, 70)?;
    let r = &mut rng(71);
    let b = 2;
    // A prefix, then suffixes shorter and longer than the conv tail (d_conv - 1 = 3).
    let lens = [41usize, 2, 1, 17];
    let total: usize = lens.iter().sum();
    let x = randn(r, &[b, total, cfg.d_model]);
    let conds: Vec<Tensor> = lens.iter().map(|_| randn(r, &[b, cfg.d_cond()])).collect();
    let whole =
        stack.forward(&x, &Conditioning::Segments(lens.iter().copied().zip(conds.iter().cloned()).collect()))?;
    let mut state: Option<StackState> = None;
    let mut start = 0;
    for (len, cond) in lens.iter().zip(&conds) {
        let (out, next) =
            stack.forward_cached(&x.narrow(1, start, *len)?, &Conditioning::Shared(cond.clone()), state.as_ref())?;
        let err = rel_err(&out, &whole.narrow(1, start, *len)?);
        println!("tokens {start}..{}: rel err {err:.2e}", start + len);
        assert!(err < TOL, "tokens {start}..{}: {err}", start + len);
        start += len;
        assert_eq!(next.tokens(), start);
        state = Some(next);
    }
    Ok(())
}

#[test]
fn state_only_and_last_token_passes_equal_the_full_pass() -> TestResult {
    let cfg = MambaConfig { n_layers: 3, ..MambaConfig::default() };
    let (_varmap, stack) = perturbed_stack(&cfg, 90)?;
    let r = &mut rng(91);
    let b = 2;
    let prefix = randn(r, &[b, 37, cfg.d_model]);
    let prefix_cond = Conditioning::Shared(randn(r, &[b, cfg.d_cond()]));
    let (_, full_state) = stack.forward_cached(&prefix, &prefix_cond, None)?;
    let state = stack.forward_state(&prefix, &prefix_cond, None)?;
    assert_eq!(state.tokens(), full_state.tokens());
    for (a, f) in state.layers().iter().zip(full_state.layers()) {
        assert!(rel_err(&a.ssm_state, &f.ssm_state) < TOL, "ssm state differs");
        assert!(rel_err(&a.conv_tail, &f.conv_tail) < TOL, "conv tail differs");
    }
    // suffixes of 1 token, shorter than the conv tail, and longer
    for len in [1usize, 2, 11] {
        let suffix = randn(r, &[b, len, cfg.d_model]);
        let cond = Conditioning::Shared(randn(r, &[b, cfg.d_cond()]));
        let (full, _) = stack.forward_cached(&suffix, &cond, Some(&state))?;
        let last = stack.forward_last_token(&suffix, &cond, Some(&state))?;
        assert_eq!(last.dims(), &[b, cfg.d_model]);
        let err = rel_err(&last, &full.narrow(1, len - 1, 1)?.squeeze(1)?);
        println!("suffix of {len}: last-token rel err {err:.2e}");
        assert!(err < TOL, "suffix of {len}: {err}");
    }
    Ok(())
}

#[test]
fn suffix_reruns_from_the_same_saved_state() -> TestResult {
    let cfg = MambaConfig::default();
    let (_varmap, stack) = perturbed_stack(&cfg, 80)?;
    let r = &mut rng(81);
    let b = 1;
    let prefix = randn(r, &[b, 30, cfg.d_model]);
    let (_, saved) = stack.forward_cached(&prefix, &Conditioning::Shared(randn(r, &[b, cfg.d_cond()])), None)?;
    let before = copy_state(&saved);
    let suffix = randn(r, &[b, 9, cfg.d_model]);
    let cond_a = Conditioning::Shared(randn(r, &[b, cfg.d_cond()]));
    let cond_b = Conditioning::Shared(randn(r, &[b, cfg.d_cond()]));
    let (out1, _) = stack.forward_cached(&suffix, &cond_a, Some(&saved))?;
    let (out_other, _) = stack.forward_cached(&suffix, &cond_b, Some(&saved))?;
    let (out2, _) = stack.forward_cached(&suffix, &cond_a, Some(&saved))?;
    assert_eq!(rel_err(&out1, &out2), 0.0, "same suffix from the same state differs");
    assert!(rel_err(&out_other, &out1) > 1e-3, "the suffix condition has no effect");
    for ((t0, h0), l) in before.iter().zip(saved.layers()) {
        assert_eq!(rel_err(&l.conv_tail, t0), 0.0, "conv tail changed");
        assert_eq!(rel_err(&l.ssm_state, h0), 0.0, "ssm state changed");
    }
    Ok(())
}

#[test]
fn fresh_stack_has_standard_init_and_is_identity_up_to_final_norm() -> TestResult {
    let cfg = MambaConfig::default();
    let varmap = VarMap::new();
    let stack = MambaStack::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu))?;
    let a_log = param(&varmap, "layers.0.mixer.A_log")?.to_vec2::<f32>()?;
    assert_eq!(a_log.len(), cfg.d_inner());
    for row in &a_log {
        for (n, v) in row.iter().enumerate() {
            assert!((v - ((n + 1) as f32).ln()).abs() < 1e-6);
        }
    }
    let bias = param(&varmap, "layers.3.mixer.dt_proj.bias")?.to_vec1::<f32>()?;
    let dt: Vec<f32> = bias.iter().map(|b| b.exp().ln_1p()).collect();
    assert!(dt.iter().all(|&d| (1e-3 * 0.999..=1e-1 * 1.001).contains(&d)), "softplus(dt bias) outside [1e-3, 1e-1]");
    assert!(dt.iter().cloned().fold(f32::MAX, f32::min) < 1.2e-3 && dt.iter().cloned().fold(0.0, f32::max) > 0.08);
    assert!(param(&varmap, "layers.1.mixer.D")?.to_vec1::<f32>()?.iter().all(|&d| d == 1.0));
    let r = &mut rng(90);
    let x = randn(r, &[2, 7, cfg.d_model]);
    let out = stack.forward(&x, &Conditioning::Shared(randn(r, &[2, cfg.d_cond()])))?;
    let want = rms_norm_ref(&x, &Tensor::ones(cfg.d_model, DType::F32, &Device::Cpu)?, cfg.norm_eps)?;
    assert!(rel_err(&out, &want) < 1e-6, "AdaLN-Zero: a fresh stack must pass tokens through");
    Ok(())
}

#[test]
fn checkpoint_round_trip_through_safetensors() -> TestResult {
    let cfg = small_config();
    let (varmap, stack) = perturbed_stack(&cfg, 100)?;
    let dir = std::env::temp_dir().join(format!("policy_mamba_ckpt_{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let path = dir.join("mamba.safetensors");
    varmap.save(&path)?;
    let r = &mut rng(101);
    let x = randn(r, &[1, 8, cfg.d_model]);
    let cond = Conditioning::Shared(randn(r, &[1, cfg.d_cond()]));
    let want = stack.forward(&x, &cond)?;
    // Straight from the file ...
    let vb = unsafe { VarBuilder::from_mmaped_safetensors(&[&path], DType::F32, &Device::Cpu)? };
    let loaded = MambaStack::new(&cfg, vb)?;
    assert_eq!(rel_err(&loaded.forward(&x, &cond)?, &want), 0.0);
    // ... and into a VarMap for further training.
    let mut varmap2 = VarMap::new();
    let stack2 = MambaStack::new(&cfg, VarBuilder::from_varmap(&varmap2, DType::F32, &Device::Cpu))?;
    varmap2.load(&path)?;
    assert_eq!(rel_err(&stack2.forward(&x, &cond)?, &want), 0.0);
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}

#[test]
fn bad_inputs_are_rejected_with_a_reason() -> TestResult {
    let cfg = small_config();
    let varmap = VarMap::new();
    let stack = MambaStack::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu))?;
    let r = &mut rng(110);
    let cond = Conditioning::Shared(randn(r, &[2, cfg.d_cond()]));
    let err = stack.forward(&randn(r, &[2, 5, cfg.d_model + 1]), &cond).expect_err("wrong width");
    assert!(err.to_string().contains("tokens must be"), "{err}");
    let x = randn(r, &[2, 5, cfg.d_model]);
    let segments = Conditioning::prefix_suffix(2, randn(r, &[2, cfg.d_cond()]), 2, randn(r, &[2, cfg.d_cond()]));
    let err = stack.forward(&x, &segments).expect_err("segments do not cover L");
    assert!(err.to_string().contains("cover 4 tokens"), "{err}");
    let err = stack.forward(&x, &Conditioning::Shared(randn(r, &[2, 3]))).expect_err("wrong d_cond");
    assert!(err.to_string().contains("d_cond"), "{err}");
    let (_, state) = stack.forward_cached(&x, &cond, None)?;
    let x1 = randn(r, &[1, 5, cfg.d_model]);
    let err = stack
        .forward_cached(&x1, &Conditioning::Shared(randn(r, &[1, cfg.d_cond()])), Some(&state))
        .expect_err("batch mismatch");
    assert!(err.to_string().contains("batch"), "{err}");
    let bad = MambaConfig { d_state: 0, ..cfg };
    assert!(MambaStack::new(&bad, VarBuilder::from_varmap(&VarMap::new(), DType::F32, &Device::Cpu)).is_err());
    Ok(())
}
