//! The Mamba layers of FlowRAM's region-aware Mamba: the Mamba mixer (as in
//! candle-transformers' `models/mamba.rs`, here for whole sequences and with
//! a backward pass), the residual pre-norm block with AdaLN-Zero modulation,
//! and the stack, with a cached prefix for inference.
//!
//! In the policy, the prefix (semantic tokens + language tokens) is the same
//! for every Euler step of the flow, so it is run once with
//! [`MambaStack::forward_cached`]; each step then runs only its suffix
//! (geometric tokens around the current action estimate + action tokens) from
//! the saved [`StackState`]. The prefix is modulated by a time-independent
//! condition, the suffix by a time-dependent one; [`Conditioning`] expresses
//! both, and the per-segment form lets training see exactly what inference sees.
//!
//! Weights live in a VarMap under mamba_ssm's names (`layers.{i}.norm.weight`,
//! `layers.{i}.mixer.in_proj.weight`, `...mixer.A_log`, ...) plus
//! `layers.{i}.ada_ln.{weight,bias}` and `norm_f.weight`, so checkpoints are
//! plain safetensors.

use crate::policy::error::{PolicyError, Result};
use crate::policy::kernels::mamba_ops::{ada_rms_norm, causal_conv_silu, gated_residual, silu_gate};
use crate::policy::kernels::selective_scan::{
    ScanInputs, selective_scan, selective_scan_with_state, selective_scan_with_state_gated,
};
use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::{Init, VarBuilder};
use serde::{Deserialize, Serialize};

/// Hyper-parameters of the Mamba stack (FlowRAM, Table B: d_model 120,
/// d_state 16, d_conv 4, expand 2; 4 layers).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MambaConfig {
    /// Token width C.
    pub d_model: usize,
    /// SSM state size N per channel.
    pub d_state: usize,
    /// Kernel size of the causal depthwise convolution.
    pub d_conv: usize,
    /// d_inner = expand * d_model.
    pub expand: usize,
    /// Number of residual Mamba blocks.
    pub n_layers: usize,
    /// Width of the AdaLN condition; `None` means d_model.
    #[serde(default)]
    pub d_cond: Option<usize>,
    /// RMSNorm epsilon.
    #[serde(default = "default_norm_eps")]
    pub norm_eps: f64,
    /// Initial step sizes softplus(dt bias) span [dt_min, dt_max] log-uniformly.
    #[serde(default = "default_dt_min")]
    pub dt_min: f64,
    #[serde(default = "default_dt_max")]
    pub dt_max: f64,
}

fn default_norm_eps() -> f64 {
    1e-5
}
fn default_dt_min() -> f64 {
    1e-3
}
fn default_dt_max() -> f64 {
    1e-1
}

impl Default for MambaConfig {
    /// FlowRAM's values.
    fn default() -> Self {
        Self {
            d_model: 120,
            d_state: 16,
            d_conv: 4,
            expand: 2,
            n_layers: 4,
            d_cond: None,
            norm_eps: default_norm_eps(),
            dt_min: default_dt_min(),
            dt_max: default_dt_max(),
        }
    }
}

impl MambaConfig {
    /// Di, channels of the SSM.
    pub fn d_inner(&self) -> usize {
        self.expand * self.d_model
    }

    /// Rank of the step-size projection, ceil(d_model / 16).
    pub fn dt_rank(&self) -> usize {
        self.d_model.div_ceil(16)
    }

    /// Floating-point operations of one layer on one token (multiply and add counted apart):
    /// in_proj (x and z halves), the depthwise causal conv, x_proj, dt_proj, the scan (about 9
    /// per state element: discretisation, update, readout), the gate and out_proj. With
    /// `full_output` false, the z half, the gate and out_proj are left out: the last layer of an
    /// inference pass needs them only at the last token.
    pub fn layer_flops_per_token(&self, full_output: bool) -> f64 {
        let (c, di, n, r, k) = (self.d_model, self.d_inner(), self.d_state, self.dt_rank(), self.d_conv);
        let mut flops = 2 * c * di + 2 * di * k + 2 * di * (r + 2 * n) + 2 * r * di + 9 * di * n;
        if full_output {
            flops += 2 * c * di + 4 * di + 2 * di * c;
        }
        flops as f64
    }

    /// Width of the AdaLN condition.
    pub fn d_cond(&self) -> usize {
        self.d_cond.unwrap_or(self.d_model)
    }

    /// Checks that every size is positive and the dt range is valid.
    pub fn validate(&self) -> Result<()> {
        let sizes = [
            ("d_model", self.d_model),
            ("d_state", self.d_state),
            ("d_conv", self.d_conv),
            ("expand", self.expand),
            ("n_layers", self.n_layers),
            ("d_cond", self.d_cond()),
        ];
        for (name, v) in sizes {
            if v == 0 {
                return Err(PolicyError::Invalid(format!("MambaConfig.{name} must be > 0")));
            }
        }
        let valid = self.dt_min > 0.0 && self.dt_min <= self.dt_max && self.norm_eps > 0.0;
        if !valid {
            return Err(PolicyError::Invalid(format!(
                "MambaConfig: need 0 < dt_min <= dt_max and norm_eps > 0, got dt_min {} dt_max {} norm_eps {}",
                self.dt_min, self.dt_max, self.norm_eps
            )));
        }
        Ok(())
    }
}

/// The AdaLN condition of each token of a call. Widths are `d_cond`.
#[derive(Clone, Debug)]
pub enum Conditioning {
    /// One condition [B, d_cond] for every token (e.g. the cached prefix with
    /// the observation condition, or one suffix pass with the step's condition).
    Shared(Tensor),
    /// Consecutive token segments, each with its own condition [B, d_cond]:
    /// `(tokens, condition)`; the token counts must add up to L. Training uses
    /// this for prefix + suffix in one pass.
    Segments(Vec<(usize, Tensor)>),
    /// One condition per token: [B, L, d_cond].
    PerToken(Tensor),
}

impl Conditioning {
    /// Prefix tokens with `prefix_cond`, the rest with `suffix_cond` ([B, d_cond] each).
    pub fn prefix_suffix(prefix_len: usize, prefix_cond: Tensor, suffix_len: usize, suffix_cond: Tensor) -> Self {
        Self::Segments(vec![(prefix_len, prefix_cond), (suffix_len, suffix_cond)])
    }
}

/// What one layer keeps between calls of [`MambaStack::forward_cached`].
#[derive(Clone, Debug)]
pub struct LayerState {
    /// The last d_conv - 1 inputs of the causal conv: [B, d_conv - 1, Di].
    pub conv_tail: Tensor,
    /// The SSM state after the last token: [B, Di, N].
    pub ssm_state: Tensor,
}

/// The state of the whole stack after a prefix. Immutable: running a suffix
/// returns a new state and leaves this one usable for the next suffix.
#[derive(Clone, Debug)]
pub struct StackState {
    layers: Vec<LayerState>,
    tokens: usize,
}

impl StackState {
    /// Per-layer states, first layer first.
    pub fn layers(&self) -> &[LayerState] {
        &self.layers
    }

    /// Tokens processed so far (prefix and any suffixes run from it).
    pub fn tokens(&self) -> usize {
        self.tokens
    }

    /// Batch size the state was computed for.
    pub fn batch_size(&self) -> usize {
        self.layers.first().map_or(0, |l| l.ssm_state.dims()[0])
    }
}

/// Gets `name` from `vb`, or, when `vb` is a VarMap that does not hold it yet,
/// creates it with the values `init` computes (custom initialisations that
/// candle's `Init` cannot express).
fn get_or_init(
    vb: &VarBuilder,
    shape: impl Into<Shape>,
    name: &str,
    init: impl FnOnce() -> Result<Tensor>,
) -> Result<Tensor> {
    let shape = shape.into();
    if vb.contains_tensor(name) {
        return Ok(vb.get(shape, name)?);
    }
    let var = vb.get_with_hints(shape, name, Init::Const(0.0))?;
    // Writes into the VarMap's variable (the returned tensor shares its storage).
    var.slice_set(&init()?, 0, 0)?;
    Ok(var)
}

/// PyTorch's default initialisation of Linear/Conv weights: U(-1/sqrt(fan_in), 1/sqrt(fan_in)).
fn uniform_fan_in(fan_in: usize) -> Init {
    let bound = 1.0 / (fan_in as f64).sqrt();
    Init::Uniform { lo: -bound, up: bound }
}

/// `x @ w^T` for x [B, L, In], w [Out, In]: one batched matmul against the
/// broadcast weight, which candle runs as a single gemm over B*L rows when x
/// is contiguous. (Reshaping to [B*L, In] and back would add two graph nodes
/// whose backward passes each cost a zero-fill and an add of the whole tensor.)
fn linear(x: &Tensor, w: &Tensor) -> Result<Tensor> {
    let b = x.dim(0)?;
    Ok(x.matmul(&w.broadcast_left(b)?.t()?)?)
}

/// The Mamba mixer: in_proj -> (x, z); x -> causal depthwise conv -> SiLU = u;
/// u -> x_proj -> (dt, B, C); dt -> dt_proj -> delta_raw; selective scan;
/// y * SiLU(z) -> out_proj.
#[derive(Clone, Debug)]
pub struct MambaMixer {
    /// [2 Di, C]
    in_proj: Tensor,
    /// [Di, d_conv] (a view of the stored [Di, 1, d_conv])
    conv_weight: Tensor,
    /// `[Di]`
    conv_bias: Tensor,
    /// [dt_rank + 2N, Di]
    x_proj: Tensor,
    /// [Di, dt_rank]
    dt_proj: Tensor,
    /// `[Di]`, the scan's delta_bias
    dt_bias: Tensor,
    /// [Di, N], A = -exp(A_log)
    a_log: Tensor,
    /// `[Di]`
    d: Tensor,
    /// [C, Di]
    out_proj: Tensor,
    d_inner: usize,
    d_state: usize,
    dt_rank: usize,
    d_conv: usize,
}

impl MambaMixer {
    /// Standard Mamba initialisation: A_log = log(1..N), D = 1, dt_proj bias
    /// = softplus^-1(dt) with dt log-uniform in [dt_min, dt_max] (spread
    /// evenly over the channels rather than drawn at random), dt_proj weight
    /// U(+-dt_rank^-1/2), the rest PyTorch's defaults.
    pub fn new(cfg: &MambaConfig, vb: VarBuilder) -> Result<Self> {
        let (c, di, n, r, k) = (cfg.d_model, cfg.d_inner(), cfg.d_state, cfg.dt_rank(), cfg.d_conv);
        let in_proj = vb.get_with_hints((2 * di, c), "in_proj.weight", uniform_fan_in(c))?;
        let conv_weight = vb.get_with_hints((di, 1, k), "conv1d.weight", uniform_fan_in(k))?;
        let conv_bias = vb.get_with_hints(di, "conv1d.bias", uniform_fan_in(k))?;
        let x_proj = vb.get_with_hints((r + 2 * n, di), "x_proj.weight", uniform_fan_in(di))?;
        let dt_proj = vb.get_with_hints((di, r), "dt_proj.weight", uniform_fan_in(r))?;
        let dt_bias = get_or_init(&vb, di, "dt_proj.bias", || {
            let (lo, hi) = (cfg.dt_min.ln(), cfg.dt_max.ln());
            let bias: Vec<f32> = (0..di)
                .map(|d| {
                    let dt = (lo + (hi - lo) * (d as f64 + 0.5) / di as f64).exp().max(1e-4);
                    (dt + (-(-dt).exp_m1()).ln()) as f32 // softplus^-1
                })
                .collect();
            Ok(Tensor::from_vec(bias, di, vb.device())?)
        })?;
        let a_log = get_or_init(&vb, (di, n), "A_log", || {
            let row: Vec<f32> = (1..=n).map(|v| (v as f32).ln()).collect();
            Ok(Tensor::from_vec(row, (1, n), vb.device())?.repeat((di, 1))?)
        })?;
        let d = vb.get_with_hints(di, "D", Init::Const(1.0))?;
        let out_proj = vb.get_with_hints((c, di), "out_proj.weight", uniform_fan_in(di))?;
        Ok(Self {
            in_proj,
            conv_weight: conv_weight.reshape((di, k))?,
            conv_bias,
            x_proj,
            dt_proj,
            dt_bias,
            a_log,
            d,
            out_proj,
            d_inner: di,
            d_state: n,
            dt_rank: r,
            d_conv: k,
        })
    }

    fn detached(&self) -> Self {
        Self {
            in_proj: self.in_proj.detach(),
            conv_weight: self.conv_weight.detach(),
            conv_bias: self.conv_bias.detach(),
            x_proj: self.x_proj.detach(),
            dt_proj: self.dt_proj.detach(),
            dt_bias: self.dt_bias.detach(),
            a_log: self.a_log.detach(),
            d: self.d.detach(),
            out_proj: self.out_proj.detach(),
            ..*self
        }
    }

    /// `h`: [B, L, C] (normalised, modulated tokens) -> [B, L, C]. With
    /// `cache`, runs from `state` (or zeros) without gradient and returns the
    /// state after the last token.
    fn forward(&self, h: &Tensor, cache: Option<Option<&LayerState>>) -> Result<(Tensor, Option<LayerState>)> {
        let (di, n, r) = (self.d_inner, self.d_state, self.dt_rank);
        let state = cache.flatten();
        // in_proj as two products (rows 0..Di -> x, Di..2Di -> z): same FLOPs as one
        // [2 Di] product, but no narrow of a [B, L, 2 Di] result, whose backward
        // would zero-pad and add two [B, L, 2 Di] gradients.
        let x = linear(h, &self.in_proj.narrow(0, 0, di)?)?; // [B, L, Di]
        let z = linear(h, &self.in_proj.narrow(0, di, di)?)?; // [B, L, Di]
        let u = causal_conv_silu(&x, &self.conv_weight, &self.conv_bias, state.map(|s| &s.conv_tail))?;
        let dbc = linear(&u, &self.x_proj)?; // [B, L, dt_rank + 2N]
        let delta_raw = linear(&dbc.narrow(2, 0, r)?, &self.dt_proj)?; // [B, L, Di]
        let bm = dbc.narrow(2, r, n)?;
        let cm = dbc.narrow(2, r + n, n)?;
        let a = self.a_log.exp()?.neg()?;
        let inputs =
            ScanInputs { u: &u, delta_raw: &delta_raw, b: &bm, c: &cm, a: &a, d: &self.d, delta_bias: &self.dt_bias };
        let (gated, new_state) = match cache {
            None => (silu_gate(&selective_scan(&inputs)?, &z)?, None),
            Some(state) => {
                // inference: the gate is fused into the scan
                let (gated, ssm_state) = selective_scan_with_state_gated(&inputs, state.map(|s| &s.ssm_state), &z)?;
                let conv_tail = next_conv_tail(state.map(|s| &s.conv_tail), &x, self.d_conv - 1)?;
                (gated, Some(LayerState { conv_tail, ssm_state }))
            }
        };
        let out = linear(&gated, &self.out_proj)?;
        Ok((out, new_state))
    }
}

impl MambaMixer {
    /// Inference pass of a last layer whose outputs are needed only at the last token (`Some`)
    /// or not at all (`None`: the state only). The scan still runs over every token (the state
    /// depends on all of them), but z, the gate and out_proj run on the last token or not at
    /// all: of the five projections, only in_proj's x half, x_proj and dt_proj stay full length.
    /// Returns ([B, 1, C] or nothing, the state after `h`).
    fn forward_tail(
        &self,
        h: &Tensor,
        state: Option<&LayerState>,
        last_token: bool,
    ) -> Result<(Option<Tensor>, LayerState)> {
        let (di, n, r) = (self.d_inner, self.d_state, self.dt_rank);
        let l = h.dim(1)?;
        let x = linear(h, &self.in_proj.narrow(0, 0, di)?)?;
        let u = causal_conv_silu(&x, &self.conv_weight, &self.conv_bias, state.map(|s| &s.conv_tail))?;
        let dbc = linear(&u, &self.x_proj)?;
        let delta_raw = linear(&dbc.narrow(2, 0, r)?, &self.dt_proj)?;
        let (bm, cm) = (dbc.narrow(2, r, n)?, dbc.narrow(2, r + n, n)?);
        let a = self.a_log.exp()?.neg()?;
        let inputs =
            ScanInputs { u: &u, delta_raw: &delta_raw, b: &bm, c: &cm, a: &a, d: &self.d, delta_bias: &self.dt_bias };
        let (y, ssm_state) = selective_scan_with_state(&inputs, state.map(|s| &s.ssm_state))?;
        let conv_tail = next_conv_tail(state.map(|s| &s.conv_tail), &x, self.d_conv - 1)?;
        let out = if last_token {
            let z = linear(&h.narrow(1, l - 1, 1)?.contiguous()?, &self.in_proj.narrow(0, di, di)?)?;
            let gated = silu_gate(&y.narrow(1, l - 1, 1)?.contiguous()?, &z)?;
            Some(linear(&gated, &self.out_proj)?)
        } else {
            None
        };
        Ok((out, LayerState { conv_tail, ssm_state }))
    }
}

/// The last `k1` conv inputs after appending `x` [B, L, Di] to `old` [B, k1, Di].
fn next_conv_tail(old: Option<&Tensor>, x: &Tensor, k1: usize) -> Result<Tensor> {
    let (b, l, di) = x.dims3()?;
    if l >= k1 {
        return Ok(x.narrow(1, l - k1, k1)?.contiguous()?);
    }
    let old = match old {
        Some(old) => old.clone(),
        None => Tensor::zeros((b, k1, di), DType::F32, x.device())?,
    };
    Ok(Tensor::cat(&[&old, &x.contiguous()?], 1)?.narrow(1, l, k1)?.contiguous()?)
}

/// Residual pre-norm block with AdaLN-Zero:
/// `x + gate * Mixer(rms_norm(x) * (1 + scale) + shift)`, with
/// `(shift, scale, gate) = Linear(SiLU(cond))`, the Linear initialised to zero
/// (so every block starts as the identity).
#[derive(Clone, Debug)]
pub struct MambaLayer {
    /// `[C]`
    norm_weight: Tensor,
    /// [3C, d_cond], [3C]: shift, scale, gate
    ada_ln_weight: Tensor,
    ada_ln_bias: Tensor,
    mixer: MambaMixer,
    d_model: usize,
    d_cond: usize,
    norm_eps: f64,
}

impl MambaLayer {
    pub fn new(cfg: &MambaConfig, vb: VarBuilder) -> Result<Self> {
        let (c, dc) = (cfg.d_model, cfg.d_cond());
        Ok(Self {
            norm_weight: vb.get_with_hints(c, "norm.weight", Init::Const(1.0))?,
            ada_ln_weight: vb.get_with_hints((3 * c, dc), "ada_ln.weight", Init::Const(0.0))?,
            ada_ln_bias: vb.get_with_hints(3 * c, "ada_ln.bias", Init::Const(0.0))?,
            mixer: MambaMixer::new(cfg, vb.pp("mixer"))?,
            d_model: c,
            d_cond: dc,
            norm_eps: cfg.norm_eps,
        })
    }

    fn detached(&self) -> Self {
        Self {
            norm_weight: self.norm_weight.detach(),
            ada_ln_weight: self.ada_ln_weight.detach(),
            ada_ln_bias: self.ada_ln_bias.detach(),
            mixer: self.mixer.detached(),
            ..*self
        }
    }

    /// Linear(SiLU(cond)) for a [.., d_cond] condition -> [.., 3C].
    fn ada_ln(&self, cond: &Tensor) -> Result<Tensor> {
        let act = candle_nn::ops::silu(cond)?;
        let out = match act.rank() {
            2 => act.matmul(&self.ada_ln_weight.t()?)?,
            _ => linear(&act, &self.ada_ln_weight)?,
        };
        Ok(out.broadcast_add(&self.ada_ln_bias)?)
    }

    /// (shift, scale, gate) of every token: [B, L, 3C], a broadcast view where
    /// the condition is shared.
    fn modulation(&self, cond: &Conditioning, batch: usize, seq_len: usize) -> Result<Tensor> {
        let per_segment = |c: &Tensor, len: usize| -> Result<Tensor> {
            check_cond(c, &[batch, self.d_cond], "segment condition")?;
            Ok(self.ada_ln(c)?.unsqueeze(1)?.broadcast_as((batch, len, 3 * self.d_model))?)
        };
        match cond {
            Conditioning::Shared(c) => per_segment(c, seq_len),
            Conditioning::Segments(segments) => {
                let total: usize = segments.iter().map(|(len, _)| len).sum();
                if total != seq_len {
                    return Err(PolicyError::Invalid(format!(
                        "conditioning segments cover {total} tokens, the sequence has {seq_len}"
                    )));
                }
                let parts = segments
                    .iter()
                    .filter(|(len, _)| *len > 0)
                    .map(|(len, c)| per_segment(c, *len))
                    .collect::<Result<Vec<_>>>()?;
                match parts.as_slice() {
                    [one] => Ok(one.clone()),
                    _ => Ok(Tensor::cat(&parts, 1)?),
                }
            }
            Conditioning::PerToken(c) => {
                check_cond(c, &[batch, seq_len, self.d_cond], "per-token condition")?;
                self.ada_ln(c)
            }
        }
    }

    fn forward(
        &self,
        x: &Tensor,
        modulation: &Tensor,
        cache: Option<Option<&LayerState>>,
    ) -> Result<(Tensor, Option<LayerState>)> {
        let c = self.d_model;
        let shift_scale = modulation.narrow(2, 0, 2 * c)?;
        let gate = modulation.narrow(2, 2 * c, c)?;
        let h = ada_rms_norm(x, &self.norm_weight, &shift_scale, self.norm_eps)?;
        let (mixed, state) = self.mixer.forward(&h, cache)?;
        Ok((gated_residual(x, &mixed, &gate)?, state))
    }
}

impl MambaLayer {
    /// [`MambaMixer::forward_tail`] inside the residual block: ([B, 1, C] output of the last
    /// token or nothing, the state).
    fn forward_tail(
        &self,
        x: &Tensor,
        modulation: &Tensor,
        state: Option<&LayerState>,
        last_token: bool,
    ) -> Result<(Option<Tensor>, LayerState)> {
        let c = self.d_model;
        let l = x.dim(1)?;
        let h = ada_rms_norm(x, &self.norm_weight, &modulation.narrow(2, 0, 2 * c)?, self.norm_eps)?;
        let (mixed, new_state) = self.mixer.forward_tail(&h, state, last_token)?;
        let out = match mixed {
            Some(mixed) => {
                let gate = modulation.narrow(1, l - 1, 1)?.narrow(2, 2 * c, c)?;
                Some(gated_residual(&x.narrow(1, l - 1, 1)?.contiguous()?, &mixed, &gate)?)
            }
            None => None,
        };
        Ok((out, new_state))
    }
}

fn check_cond(c: &Tensor, shape: &[usize], what: &str) -> Result<()> {
    if c.dims() != shape || c.dtype() != DType::F32 {
        return Err(PolicyError::Invalid(format!(
            "AdaLN {what}: expected f32 {shape:?} ([batch, (tokens,) d_cond]), got {:?} {:?}",
            c.dtype(),
            c.shape()
        )));
    }
    Ok(())
}

/// `n_layers` AdaLN Mamba blocks and a final RMSNorm (`norm_f`), over a causal
/// token sequence [B, L, d_model].
#[derive(Clone, Debug)]
pub struct MambaStack {
    cfg: MambaConfig,
    layers: Vec<MambaLayer>,
    /// `[C]`
    final_norm_weight: Tensor,
}

impl MambaStack {
    /// Builds the stack; weights under `vb` (`layers.{i}.*`, `norm_f.weight`).
    /// `vb` must hold f32 on the CPU.
    pub fn new(cfg: &MambaConfig, vb: VarBuilder) -> Result<Self> {
        cfg.validate()?;
        if vb.dtype() != DType::F32 || !vb.device().is_cpu() {
            return Err(PolicyError::Invalid(format!(
                "MambaStack: weights must be f32 on the CPU, got {:?} on {:?}",
                vb.dtype(),
                vb.device().location()
            )));
        }
        let layers =
            (0..cfg.n_layers).map(|i| MambaLayer::new(cfg, vb.pp("layers").pp(i))).collect::<Result<Vec<_>>>()?;
        let final_norm_weight = vb.get_with_hints(cfg.d_model, "norm_f.weight", Init::Const(1.0))?;
        Ok(Self { cfg: cfg.clone(), layers, final_norm_weight })
    }

    pub fn config(&self) -> &MambaConfig {
        &self.cfg
    }

    fn check_tokens(&self, x: &Tensor) -> Result<(usize, usize)> {
        match x.dims() {
            &[b, l, c] if c == self.cfg.d_model && l > 0 && x.dtype() == DType::F32 && x.device().is_cpu() => {
                Ok((b, l))
            }
            _ => Err(PolicyError::Invalid(format!(
                "MambaStack: tokens must be f32 [batch, seq_len > 0, {}] on the CPU, got {:?} {:?}",
                self.cfg.d_model,
                x.dtype(),
                x.shape()
            ))),
        }
    }

    fn final_norm(&self, x: &Tensor, final_norm_weight: &Tensor) -> Result<Tensor> {
        let (b, l, c) = x.dims3()?;
        let no_modulation = Tensor::zeros((1, 1, 2 * c), DType::F32, &Device::Cpu)?.broadcast_as((b, l, 2 * c))?;
        ada_rms_norm(x, final_norm_weight, &no_modulation, self.cfg.norm_eps)
    }

    /// Training forward, differentiable: x [B, L, d_model] -> [B, L, d_model],
    /// from zero state. `cond` gives each token's AdaLN condition.
    pub fn forward(&self, x: &Tensor, cond: &Conditioning) -> Result<Tensor> {
        let (b, l) = self.check_tokens(x)?;
        let mut x = x.clone();
        for layer in &self.layers {
            let modulation = layer.modulation(cond, b, l)?;
            x = layer.forward(&x, &modulation, None)?.0;
        }
        self.final_norm(&x, &self.final_norm_weight)
    }

    /// Inference forward (no gradient): runs x [B, L, d_model] from `state`
    /// (`None`: the start of the sequence) and returns the outputs and the
    /// state after x. `state` is not modified, so several suffixes can run
    /// from one cached prefix. Prefix then suffix gives the outputs of
    /// [`Self::forward`] on the concatenation (with `Conditioning::Segments`).
    pub fn forward_cached(
        &self,
        x: &Tensor,
        cond: &Conditioning,
        state: Option<&StackState>,
    ) -> Result<(Tensor, StackState)> {
        let (b, l) = self.check_tokens(x)?;
        self.check_state(state, b)?;
        let cond = detach_cond(cond);
        let mut x = x.detach();
        let mut layer_states = Vec::with_capacity(self.layers.len());
        for (i, layer) in self.layers.iter().enumerate() {
            let layer = layer.detached();
            let modulation = layer.modulation(&cond, b, l)?;
            let previous = state.map(|s| &s.layers[i]);
            let (out, new_state) = layer.forward(&x, &modulation, Some(previous))?;
            x = out;
            layer_states.push(
                new_state.ok_or_else(|| PolicyError::Invalid("MambaStack: a cached layer returned no state".into()))?,
            );
        }
        let out = self.final_norm(&x, &self.final_norm_weight.detach())?;
        let tokens = state.map_or(0, |s| s.tokens) + l;
        Ok((out, StackState { layers: layer_states, tokens }))
    }
}

impl MambaStack {
    /// Inference: the state after x [B, L, d_model] (run from `state`), without the outputs.
    /// Equals the state of [`Self::forward_cached`]; skips the last layer's z, gate, out_proj and
    /// residual and the final norm (an observation prefix, whose outputs nobody reads).
    pub fn forward_state(&self, x: &Tensor, cond: &Conditioning, state: Option<&StackState>) -> Result<StackState> {
        Ok(self.forward_tail(x, cond, state, false)?.1)
    }

    /// Inference: the output of the last token only, [B, d_model] (equal to the last row of
    /// [`Self::forward_cached`]'s output); the new state is not kept. A flow step's suffix,
    /// whose heads read the action token alone.
    pub fn forward_last_token(&self, x: &Tensor, cond: &Conditioning, state: Option<&StackState>) -> Result<Tensor> {
        let out = self.forward_tail(x, cond, state, true)?.0;
        let out = out.ok_or_else(|| PolicyError::Invalid("MambaStack: the last layer returned no output".into()))?;
        Ok(out.squeeze(1)?)
    }

    fn forward_tail(
        &self,
        x: &Tensor,
        cond: &Conditioning,
        state: Option<&StackState>,
        last_token: bool,
    ) -> Result<(Option<Tensor>, StackState)> {
        let Some((last, init)) = self.layers.split_last() else {
            return Err(PolicyError::Invalid("MambaStack: no layers".into()));
        };
        let (b, l) = self.check_tokens(x)?;
        self.check_state(state, b)?;
        let cond = detach_cond(cond);
        let mut x = x.detach();
        let mut layer_states = Vec::with_capacity(self.layers.len());
        for (i, layer) in init.iter().enumerate() {
            let layer = layer.detached();
            let modulation = layer.modulation(&cond, b, l)?;
            let (out, new_state) = layer.forward(&x, &modulation, Some(state.map(|s| &s.layers[i])))?;
            x = out;
            layer_states.push(
                new_state.ok_or_else(|| PolicyError::Invalid("MambaStack: a cached layer returned no state".into()))?,
            );
        }
        let layer = last.detached();
        let modulation = layer.modulation(&cond, b, l)?;
        let (out, new_state) = layer.forward_tail(&x, &modulation, state.map(|s| &s.layers[init.len()]), last_token)?;
        layer_states.push(new_state);
        let out = match out {
            Some(out) => Some(self.final_norm(&out, &self.final_norm_weight.detach())?),
            None => None,
        };
        let tokens = state.map_or(0, |s| s.tokens) + l;
        Ok((out, StackState { layers: layer_states, tokens }))
    }

    fn check_state(&self, state: Option<&StackState>, batch: usize) -> Result<()> {
        match state {
            Some(state) if state.layers.len() != self.layers.len() || state.batch_size() != batch => {
                Err(PolicyError::Invalid(format!(
                    "MambaStack: cached state is for {} layers and batch {}, the stack has {} layers and the tokens batch {batch}",
                    state.layers.len(),
                    state.batch_size(),
                    self.layers.len()
                )))
            }
            _ => Ok(()),
        }
    }
}

fn detach_cond(cond: &Conditioning) -> Conditioning {
    match cond {
        Conditioning::Shared(c) => Conditioning::Shared(c.detach()),
        Conditioning::Segments(s) => Conditioning::Segments(s.iter().map(|(l, c)| (*l, c.detach())).collect()),
        Conditioning::PerToken(c) => Conditioning::PerToken(c.detach()),
    }
}

impl StackState {
    /// The state of a batch-1 prefix repeated for `n` sequences (several action samples from one
    /// cached observation).
    pub fn repeat(&self, n: usize) -> Result<Self> {
        if self.batch_size() != 1 {
            return Err(PolicyError::Invalid(format!(
                "only a batch-1 state can be repeated; this one has batch {}",
                self.batch_size()
            )));
        }
        let layers = self
            .layers
            .iter()
            .map(|l| {
                Ok(LayerState { conv_tail: l.conv_tail.repeat((n, 1, 1))?, ssm_state: l.ssm_state.repeat((n, 1, 1))? })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { layers, tokens: self.tokens })
    }
}
