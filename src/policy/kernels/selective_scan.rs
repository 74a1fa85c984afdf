//! Mamba's selective scan (S6) as a candle custom op, with its backward pass
//! and a stateful forward for inference with a cached prefix.
//!
//! For batch b, channel d (of `d_inner` = Di), state n (of `d_state` = N):
//!
//! ```text
//! delta_t = softplus(delta_raw_t[d] + delta_bias[d])
//! h_t[n]  = exp(delta_t A[d,n]) h_{t-1}[n] + delta_t B_t[n] u_t[d]
//! y_t[d]  = sum_n C_t[n] h_t[n] + D[d] u_t[d]
//! ```
//!
//! Layout (all f32, row-major): `u`, `delta_raw`, `y`: [B, L, Di] (channels
//! contiguous); `B`, `C`: [B, L, N]; `A`: [Di, N]; `D`, `delta_bias`: `[Di]`;
//! states `h`: [B, Di, N]. The kernel works on groups of 16 channels (one
//! AVX-512 register), so every inner loop runs over contiguous channels and
//! needs no horizontal sums in the forward pass; rayon spreads the
//! (batch x channel-group) tasks over the cores. softplus and exp are fused
//! into the scan (4 state rows' exps interleaved, 8 tokens' softplus at once,
//! to keep the FP units busy); the [B, L, Di, N] tensors of the naive
//! formulation are never materialised. The inference entry can also fuse
//! Mamba's output gate y * SiLU(z).
//!
//! Operands of the op: u, delta_raw, and the third operand packs B, C, A, D
//! and delta_bias into one flat tensor (a copy of 2 x B x L x N + small;
//! candle custom ops take at most three tensors).
//!
//! Backward: the op stores nothing. Its `bwd` calls a second custom op that,
//! per task, recomputes the forward pass keeping that group's states and
//! decay factors (2 x L x N x 16 floats, 2.3 MB at L = 1100, in a per-thread
//! buffer kept between calls) and then runs one reverse pass producing the
//! gradients of every input; B and C gradients are summed over channel
//! groups afterwards.

use crate::policy::error::{PolicyError, Result};
use crate::policy::kernels::simd::{
    DisjointWriter, LANES, Lanes, contiguous_data, exp_interleaved, lane_sum, load_lanes, madd, sigmoid, silu,
    simd_kernel, softplus_interleaved, with_captured,
};
use candle_core::{CpuStorage, CustomOp3, DType, Device, Layout, Shape, Tensor};
use rayon::prelude::*;

/// Sizes of one selective scan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ScanDims {
    /// B
    pub batch: usize,
    /// L, tokens
    pub seq_len: usize,
    /// Di, channels of the SSM (`expand * d_model` in Mamba)
    pub d_inner: usize,
    /// N, state size per channel
    pub d_state: usize,
}

impl ScanDims {
    fn seq_elems(&self) -> usize {
        self.batch * self.seq_len * self.d_inner
    }
    fn bc_elems(&self) -> usize {
        self.batch * self.seq_len * self.d_state
    }
    fn state_elems(&self) -> usize {
        self.batch * self.d_inner * self.d_state
    }
    /// Length of the packed third operand: B, C, A, D, delta_bias.
    fn packed_len(&self) -> usize {
        2 * self.bc_elems() + self.d_inner * self.d_state + 2 * self.d_inner
    }
    fn groups(&self) -> usize {
        self.d_inner.div_ceil(LANES)
    }
}

/// The inputs of one selective scan. All f32 on the CPU; any layout (the scan
/// copies to contiguous where needed).
#[derive(Clone, Copy, Debug)]
pub struct ScanInputs<'a> {
    /// u: [B, L, Di], the sequence being scanned (the conv + SiLU output in Mamba).
    pub u: &'a Tensor,
    /// delta_raw: [B, L, Di], the step size before bias and softplus (dt_proj output).
    pub delta_raw: &'a Tensor,
    /// B: [B, L, N], input matrix per token.
    pub b: &'a Tensor,
    /// C: [B, L, N], output matrix per token.
    pub c: &'a Tensor,
    /// A: [Di, N], state matrix (negative for a stable scan; Mamba uses -exp(A_log)).
    pub a: &'a Tensor,
    /// D: `[Di]`, skip connection.
    pub d: &'a Tensor,
    /// delta_bias: `[Di]`, added to delta_raw before softplus (dt_proj's bias).
    pub delta_bias: &'a Tensor,
}

impl ScanInputs<'_> {
    /// Checks the shapes against each other and returns the sizes.
    pub fn dims(&self) -> Result<ScanDims> {
        let (batch, seq_len, d_inner) = self.u.dims3().map_err(|_| {
            PolicyError::Invalid(format!(
                "selective scan: u must be [batch, seq_len, d_inner], got {:?}",
                self.u.shape()
            ))
        })?;
        let (d_inner_a, d_state) = self.a.dims2().map_err(|_| {
            PolicyError::Invalid(format!("selective scan: A must be [d_inner, d_state], got {:?}", self.a.shape()))
        })?;
        let dims = ScanDims { batch, seq_len, d_inner, d_state };
        let expect = |name: &str, t: &Tensor, shape: &[usize]| -> Result<()> {
            if t.dims() != shape {
                return Err(PolicyError::Invalid(format!(
                    "selective scan: {name} must have shape {shape:?} (u is {:?}, A is {:?}), got {:?}",
                    self.u.shape(),
                    self.a.shape(),
                    t.shape()
                )));
            }
            if t.dtype() != DType::F32 || !t.device().is_cpu() {
                return Err(PolicyError::Invalid(format!(
                    "selective scan: {name} must be f32 on the CPU, got {:?} on {:?}",
                    t.dtype(),
                    t.device().location()
                )));
            }
            Ok(())
        };
        expect("u", self.u, &[batch, seq_len, d_inner])?;
        expect("delta_raw", self.delta_raw, &[batch, seq_len, d_inner])?;
        expect("B", self.b, &[batch, seq_len, d_state])?;
        expect("C", self.c, &[batch, seq_len, d_state])?;
        expect("A", self.a, &[d_inner, d_state])?;
        expect("D", self.d, &[d_inner])?;
        expect("delta_bias", self.delta_bias, &[d_inner])?;
        if d_inner_a != d_inner || batch == 0 || seq_len == 0 || d_inner == 0 || d_state == 0 {
            return Err(PolicyError::Invalid(format!(
                "selective scan: sizes must be non-zero and agree, got {dims:?}"
            )));
        }
        Ok(dims)
    }

    /// u and delta_raw contiguous, and the third operand: B, C, A, D and
    /// delta_bias flattened and concatenated (a copy of 2 x B x L x N + small).
    fn operands(&self) -> Result<(Tensor, Tensor, Tensor)> {
        let packed = Tensor::cat(
            &[
                self.b.flatten_all()?,
                self.c.flatten_all()?,
                self.a.flatten_all()?,
                self.d.clone(),
                self.delta_bias.clone(),
            ],
            0,
        )?;
        Ok((self.u.contiguous()?, self.delta_raw.contiguous()?, packed))
    }
}

/// The selective scan, differentiable with respect to every input.
/// Returns y: [B, L, Di]. Starts from a zero state.
pub fn selective_scan(inputs: &ScanInputs) -> Result<Tensor> {
    let dims = inputs.dims()?;
    let (u, delta_raw, packed) = inputs.operands()?;
    let op = SelectiveScan { dims, initial_state: None, gate: None };
    Ok(u.apply_op3(&delta_raw, &packed, op)?)
}

/// The selective scan from an initial state, forward only (no gradient), for
/// inference with a cached prefix. `initial_state`: [B, Di, N], `None` for
/// zeros. Returns (y [B, L, Di], final state [B, Di, N]). Scanning a prefix,
/// then the suffix from the prefix's final state, gives the same y as scanning
/// the concatenation.
pub fn selective_scan_with_state(inputs: &ScanInputs, initial_state: Option<&Tensor>) -> Result<(Tensor, Tensor)> {
    scan_with_state(inputs, initial_state, None)
}

/// [`selective_scan_with_state`] with Mamba's output gate fused in: returns
/// (y * SiLU(z), final state) for z: [B, L, Di], saving a pass over y.
pub fn selective_scan_with_state_gated(
    inputs: &ScanInputs,
    initial_state: Option<&Tensor>,
    z: &Tensor,
) -> Result<(Tensor, Tensor)> {
    scan_with_state(inputs, initial_state, Some(z))
}

fn scan_with_state(
    inputs: &ScanInputs,
    initial_state: Option<&Tensor>,
    gate: Option<&Tensor>,
) -> Result<(Tensor, Tensor)> {
    let dims = inputs.dims()?;
    let gate = match gate {
        Some(z) if z.dims() == [dims.batch, dims.seq_len, dims.d_inner] && z.dtype() == DType::F32 => {
            Some(z.contiguous()?)
        }
        Some(z) => {
            return Err(PolicyError::Invalid(format!(
                "selective scan: gate z must be f32 [batch, seq_len, d_inner] like u {:?}, got {:?} {:?}",
                inputs.u.shape(),
                z.dtype(),
                z.shape()
            )));
        }
        None => None,
    };
    let initial_state = match initial_state {
        Some(h0) => {
            let expected = [dims.batch, dims.d_inner, dims.d_state];
            if h0.dims() != expected || h0.dtype() != DType::F32 || !h0.device().is_cpu() {
                return Err(PolicyError::Invalid(format!(
                    "selective scan: initial state must be f32 [batch, d_inner, d_state] = {expected:?} on the CPU, got {:?} {:?}",
                    h0.dtype(),
                    h0.shape()
                )));
            }
            Some(h0.contiguous()?)
        }
        None => Some(Tensor::zeros((dims.batch, dims.d_inner, dims.d_state), DType::F32, &Device::Cpu)?),
    };
    let (u, delta_raw, packed) = inputs.operands()?;
    let op = SelectiveScan { dims, initial_state, gate };
    let out = u.apply_op3_no_bwd(&delta_raw, &packed, &op)?;
    let y = out.narrow(0, 0, dims.seq_elems())?.reshape((dims.batch, dims.seq_len, dims.d_inner))?;
    let h_last =
        out.narrow(0, dims.seq_elems(), dims.state_elems())?.reshape((dims.batch, dims.d_inner, dims.d_state))?;
    Ok((y, h_last))
}

/// The op. Operands: u [B, L, Di], delta_raw [B, L, Di], packed (B, C, A, D,
/// delta_bias, flat). Output: y [B, L, Di]; with an initial state, the flat
/// concatenation of y and the final state [B, Di, N] (no backward then),
/// y multiplied by SiLU(gate) if a gate is given.
struct SelectiveScan {
    dims: ScanDims,
    initial_state: Option<Tensor>,
    gate: Option<Tensor>,
}

/// Borrowed, contiguous inputs of the kernels.
struct ScanData<'a> {
    dims: ScanDims,
    u: &'a [f32],
    delta_raw: &'a [f32],
    b: &'a [f32],
    c: &'a [f32],
    a: &'a [f32],
    d: &'a [f32],
    delta_bias: &'a [f32],
}

impl<'a> ScanData<'a> {
    fn new(
        dims: ScanDims,
        s1: &'a CpuStorage,
        l1: &Layout,
        s2: &'a CpuStorage,
        l2: &Layout,
        s3: &'a CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<Self> {
        let u = contiguous_data(s1, l1, "selective scan u")?;
        let delta_raw = contiguous_data(s2, l2, "selective scan delta_raw")?;
        let packed = contiguous_data(s3, l3, "selective scan packed B/C/A/D/bias")?;
        if u.len() != dims.seq_elems() || delta_raw.len() != dims.seq_elems() || packed.len() != dims.packed_len() {
            candle_core::bail!(
                "selective scan: operand sizes {} {} {} do not match {dims:?}",
                u.len(),
                delta_raw.len(),
                packed.len()
            )
        }
        let (b, rest) = packed.split_at(dims.bc_elems());
        let (c, rest) = rest.split_at(dims.bc_elems());
        let (a, rest) = rest.split_at(dims.d_inner * dims.d_state);
        let (d, delta_bias) = rest.split_at(dims.d_inner);
        Ok(Self { dims, u, delta_raw, b, c, a, d, delta_bias })
    }
}

impl CustomOp3 for SelectiveScan {
    fn name(&self) -> &'static str {
        "selective-scan"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let dims = self.dims;
        let data = ScanData::new(dims, s1, l1, s2, l2, s3, l3)?;
        let tasks: Vec<(usize, usize)> =
            (0..dims.batch).flat_map(|b| (0..dims.groups()).map(move |g| (b, g))).collect();
        match &self.initial_state {
            None => {
                let mut y = vec![0f32; dims.seq_elems()];
                let y_out = DisjointWriter::new(&mut y);
                tasks
                    .par_iter()
                    .for_each(|&(b, g)| scan_group_forward(&data, b, g, None, None, Some(y_out), None, None));
                Ok((CpuStorage::F32(y), Shape::from((dims.batch, dims.seq_len, dims.d_inner))))
            }
            Some(h0) => with_captured(h0, "selective scan initial state", |h0| {
                let run = |gate: Option<&[f32]>| {
                    let mut out = vec![0f32; dims.seq_elems() + dims.state_elems()];
                    let (y, h_last) = out.split_at_mut(dims.seq_elems());
                    let (y_out, h_out) = (DisjointWriter::new(y), DisjointWriter::new(h_last));
                    tasks.par_iter().for_each(|&(b, g)| {
                        scan_group_forward(&data, b, g, Some(h0), gate, Some(y_out), Some(h_out), None)
                    });
                    let n = out.len();
                    Ok((CpuStorage::F32(out), Shape::from(n)))
                };
                match &self.gate {
                    Some(z) => with_captured(z, "selective scan gate z", |z| run(Some(z))),
                    None => run(None),
                }
            }),
        }
    }

    fn bwd(
        &self,
        u: &Tensor,
        delta_raw: &Tensor,
        packed: &Tensor,
        _y: &Tensor,
        grad_y: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        if self.initial_state.is_some() || self.gate.is_some() {
            candle_core::bail!("selective scan: no backward through a stateful or gated scan")
        }
        let dims = self.dims;
        let op = SelectiveScanBackward { dims, grad_y: grad_y.contiguous()? };
        let grads = u.apply_op3_no_bwd(delta_raw, packed, &op)?;
        let n = dims.seq_elems();
        let grad_u = grads.narrow(0, 0, n)?.reshape(u.shape())?;
        let grad_delta_raw = grads.narrow(0, n, n)?.reshape(delta_raw.shape())?;
        let grad_packed = grads.narrow(0, 2 * n, dims.packed_len())?;
        Ok((Some(grad_u), Some(grad_delta_raw), Some(grad_packed)))
    }
}

/// State rows handled together (independent exp chains in flight).
const STATE_BLOCK: usize = 4;
/// Tokens whose step sizes (softplus) are computed together.
const TOKEN_BLOCK: usize = 8;

/// d_state rounded up to a multiple of [`STATE_BLOCK`]; the padding rows have
/// A = B = C = 0, so their states stay 0 and contribute nothing.
fn padded_state(dims: ScanDims) -> usize {
    dims.d_state.div_ceil(STATE_BLOCK) * STATE_BLOCK
}

/// Per-task record of the forward pass, for the reverse pass: states h_t and
/// decay factors exp(delta_t A) ([L][N padded] lane groups) and delta_t ([L]).
struct ScanTrace {
    h: Vec<Lanes>,
    decay: Vec<Lanes>,
    delta: Vec<Lanes>,
}

impl ScanTrace {
    /// Makes room for `dims` (contents are overwritten by the forward pass).
    fn resize(&mut self, dims: ScanDims) {
        let rows = dims.seq_len * padded_state(dims);
        self.h.resize(rows, ZERO);
        self.decay.resize(rows, ZERO);
        self.delta.resize(dims.seq_len, ZERO);
    }

    fn empty() -> Self {
        Self { h: Vec::new(), decay: Vec::new(), delta: Vec::new() }
    }
}

const ZERO: Lanes = [0.0; LANES];

thread_local! {
    /// Each worker thread's trace buffer, kept between backward passes so that
    /// its pages are not faulted in again on every call.
    static TRACE_BUFFER: std::cell::RefCell<ScanTrace> = std::cell::RefCell::new(ScanTrace::empty());
}

/// Channels `group * LANES ..` of batch `b`: first channel and how many.
fn group_span(dims: ScanDims, group: usize) -> (usize, usize) {
    let d0 = group * LANES;
    (d0, LANES.min(dims.d_inner - d0))
}

/// A transposed to [N padded] lane groups for one channel group (padding zero).
fn group_a(data: &ScanData, d0: usize, width: usize) -> Vec<Lanes> {
    let n_state = data.dims.d_state;
    let mut a_t = vec![ZERO; padded_state(data.dims)];
    for k in 0..width {
        for (n, a_n) in a_t.iter_mut().take(n_state).enumerate() {
            a_n[k] = data.a[(d0 + k) * n_state + n];
        }
    }
    a_t
}

/// B_t or C_t values n0 .. n0 + SB of the token starting at `row` (0 for padding).
#[inline(always)]
fn bc_block<const SB: usize>(v: &[f32], row: usize, n0: usize, n_state: usize) -> [f32; SB] {
    let mut out = [0f32; SB];
    for (j, o) in out.iter_mut().enumerate() {
        if n0 + j < n_state {
            *o = v[row + n0 + j];
        }
    }
    out
}

/// SB consecutive lane groups of `v` from `n0` as a fixed-size array.
#[inline(always)]
fn block<const SB: usize>(v: &[Lanes], n0: usize) -> &[Lanes; SB] {
    v[n0..n0 + SB].try_into().expect("state block inside the padded state")
}

#[inline(always)]
fn block_mut<const SB: usize>(v: &mut [Lanes], n0: usize) -> &mut [Lanes; SB] {
    (&mut v[n0..n0 + SB]).try_into().expect("state block inside the padded state")
}

simd_kernel! {
    /// Forward scan of one (batch, channel group): writes y (if given), the
    /// final state (if given) and the trace (if given).
    fn scan_group_forward<FMA>(
        data: &ScanData,
        b: usize,
        group: usize,
        h0: Option<&[f32]>,
        gate: Option<&[f32]>,
        y_out: Option<DisjointWriter>,
        h_out: Option<DisjointWriter>,
        trace: Option<&mut ScanTrace>,
    ) {
        match trace {
            Some(trace) => scan_forward_body::<FMA, true>(data, b, group, h0, gate, y_out, h_out, trace),
            None => {
                let mut no_trace = ScanTrace::empty();
                scan_forward_body::<FMA, false>(data, b, group, h0, gate, y_out, h_out, &mut no_trace)
            }
        }
    }
}

/// The forward scan. Loops over the 16 lanes are innermost with the
/// independent work (SB state rows, TB tokens' softplus) unrolled inside, so
/// that the loop vectoriser widens whole bodies and the exp chains interleave.
/// With `TRACE`, the states and decays go straight into `trace` from the
/// vectorised loop (no copies). With `gate` ([B, L, Di]), y is written as
/// y * SiLU(gate).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn scan_forward_body<const FMA: bool, const TRACE: bool>(
    data: &ScanData,
    b: usize,
    group: usize,
    h0: Option<&[f32]>,
    gate: Option<&[f32]>,
    y_out: Option<DisjointWriter>,
    h_out: Option<DisjointWriter>,
    trace: &mut ScanTrace,
) {
    const SB: usize = STATE_BLOCK;
    const TB: usize = TOKEN_BLOCK;
    let dims = data.dims;
    let (n_state, seq_len, d_inner) = (dims.d_state, dims.seq_len, dims.d_inner);
    let n_pad = padded_state(dims);
    let (d0, width) = group_span(dims, group);
    let a_t = group_a(data, d0, width);
    let mut h = vec![ZERO; n_pad];
    if let Some(h0) = h0 {
        for k in 0..width {
            for (n, h_n) in h.iter_mut().take(n_state).enumerate() {
                h_n[k] = h0[(b * d_inner + d0 + k) * n_state + n];
            }
        }
    }
    let bias = load_lanes(data.delta_bias, d0, width);
    let skip = load_lanes(data.d, d0, width);
    for t0 in (0..seq_len).step_by(TB) {
        let tokens = TB.min(seq_len - t0);
        let mut u = [ZERO; TB];
        let mut delta = [ZERO; TB];
        for i in 0..tokens {
            let row = (b * seq_len + t0 + i) * d_inner + d0;
            u[i] = load_lanes(data.u, row, width);
            delta[i] = load_lanes(data.delta_raw, row, width);
        }
        for k in 0..LANES {
            let mut x = [0f32; TB];
            for i in 0..TB {
                x[i] = delta[i][k] + bias[k];
            }
            softplus_interleaved::<FMA, TB>(&mut x);
            for i in 0..TB {
                delta[i][k] = x[i];
            }
        }
        for i in 0..tokens {
            let t = t0 + i;
            let bc_row = (b * seq_len + t) * n_state;
            let (delta_t, u_t) = (&delta[i], &u[i]);
            let mut du = ZERO;
            // y in SB parts: SB independent FMA chains
            let mut y = [ZERO; SB];
            for k in 0..LANES {
                du[k] = delta_t[k] * u_t[k];
                y[0][k] = skip[k] * u_t[k];
            }
            for n0 in (0..n_pad).step_by(SB) {
                let b_n = bc_block::<SB>(data.b, bc_row, n0, n_state);
                let c_n = bc_block::<SB>(data.c, bc_row, n0, n_state);
                let a_n = block::<SB>(&a_t, n0);
                let h_n = block_mut::<SB>(&mut h, n0);
                // without TRACE the stores go to dead locals and are optimised away
                let (mut no_h, mut no_decay) = ([ZERO; SB], [ZERO; SB]);
                let (trace_h, trace_decay) = if TRACE {
                    let row = t * n_pad + n0;
                    (block_mut::<SB>(&mut trace.h, row), block_mut::<SB>(&mut trace.decay, row))
                } else {
                    (&mut no_h, &mut no_decay)
                };
                for k in 0..LANES {
                    let mut e = [0f32; SB];
                    for j in 0..SB {
                        e[j] = delta_t[k] * a_n[j][k];
                    }
                    exp_interleaved::<FMA, SB>(&mut e);
                    for j in 0..SB {
                        h_n[j][k] = madd::<FMA>(e[j], h_n[j][k], du[k] * b_n[j]);
                        y[j][k] = madd::<FMA>(c_n[j], h_n[j][k], y[j][k]);
                        trace_decay[j][k] = e[j];
                        trace_h[j][k] = h_n[j][k];
                    }
                }
            }
            let mut y_sum = ZERO;
            for k in 0..LANES {
                let mut acc = y[0][k];
                for y_j in &y[1..] {
                    acc += y_j[k];
                }
                y_sum[k] = acc;
            }
            if TRACE {
                trace.delta[t] = *delta_t;
            }
            let row = (b * seq_len + t) * d_inner + d0;
            if let Some(gate) = gate {
                let z = load_lanes(gate, row, width);
                for k in 0..LANES {
                    y_sum[k] *= silu::<FMA>(z[k]);
                }
            }
            if let Some(y_out) = y_out {
                // SAFETY: task (b, group) is the only writer of these channels of row t.
                unsafe { y_out.write_slice(row, &y_sum[..width]) };
            }
        }
    }
    if let Some(h_out) = h_out {
        for k in 0..width {
            for (n, h_n) in h.iter().take(n_state).enumerate() {
                // SAFETY: task (b, group) is the only writer of these channels' state.
                unsafe { h_out.write((b * d_inner + d0 + k) * n_state + n, h_n[k]) };
            }
        }
    }
}

/// Gradients of one (batch, channel group) that other tasks also contribute
/// to: B and C per token ([L][N] each, summed over the group's channels), and
/// A, D, delta_bias for the group's channels (summed over tokens).
struct GroupGradients {
    b: usize,
    group: usize,
    grad_b: Vec<f32>,
    grad_c: Vec<f32>,
    grad_a: Vec<Lanes>,
    grad_d: Lanes,
    grad_bias: Lanes,
}

/// Backward op. Operands as [`SelectiveScan`]; captured: dL/dy [B, L, Di].
/// Output, flat: dL/du [B·L·Di], dL/d delta_raw [B·L·Di], dL/d packed.
struct SelectiveScanBackward {
    dims: ScanDims,
    grad_y: Tensor,
}

impl CustomOp3 for SelectiveScanBackward {
    fn name(&self) -> &'static str {
        "selective-scan-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let dims = self.dims;
        let data = ScanData::new(dims, s1, l1, s2, l2, s3, l3)?;
        with_captured(&self.grad_y, "selective scan dL/dy", |grad_y| {
            if grad_y.len() != dims.seq_elems() {
                candle_core::bail!("selective scan backward: dL/dy has {} elements", grad_y.len())
            }
            let n_seq = dims.seq_elems();
            let mut out = vec![0f32; 2 * n_seq + dims.packed_len()];
            let (grad_u, rest) = out.split_at_mut(n_seq);
            let (grad_raw, grad_packed) = rest.split_at_mut(n_seq);
            let (gu_out, graw_out) = (DisjointWriter::new(grad_u), DisjointWriter::new(grad_raw));
            let tasks: Vec<(usize, usize)> =
                (0..dims.batch).flat_map(|b| (0..dims.groups()).map(move |g| (b, g))).collect();
            let parts: Vec<GroupGradients> = tasks
                .par_iter()
                .map(|&(b, g)| {
                    TRACE_BUFFER.with(|buffer| {
                        let mut trace = buffer.borrow_mut();
                        trace.resize(dims);
                        scan_group_backward(&data, b, g, grad_y, &mut trace, gu_out, graw_out)
                    })
                })
                .collect();
            reduce_group_gradients(dims, &parts, grad_packed);
            let n = out.len();
            Ok((CpuStorage::F32(out), Shape::from(n)))
        })
    }
}

/// Sums the per-task partial gradients into the packed gradient (B, C, A, D,
/// delta_bias); B and C in parallel over batches.
fn reduce_group_gradients(dims: ScanDims, parts: &[GroupGradients], grad_packed: &mut [f32]) {
    let per_batch = dims.seq_len * dims.d_state;
    let (grad_b, rest) = grad_packed.split_at_mut(dims.bc_elems());
    let (grad_c, rest) = rest.split_at_mut(dims.bc_elems());
    let (grad_a, rest) = rest.split_at_mut(dims.d_inner * dims.d_state);
    let (grad_d, grad_bias) = rest.split_at_mut(dims.d_inner);
    grad_b.par_chunks_mut(per_batch).zip(grad_c.par_chunks_mut(per_batch)).enumerate().for_each(|(b, (gb, gc))| {
        for part in parts.iter().filter(|p| p.b == b) {
            for (acc, v) in gb.iter_mut().zip(&part.grad_b) {
                *acc += v;
            }
            for (acc, v) in gc.iter_mut().zip(&part.grad_c) {
                *acc += v;
            }
        }
    });
    for part in parts {
        let (d0, width) = group_span(dims, part.group);
        for k in 0..width {
            for (n, ga) in part.grad_a.iter().take(dims.d_state).enumerate() {
                grad_a[(d0 + k) * dims.d_state + n] += ga[k];
            }
            grad_d[d0 + k] += part.grad_d[k];
            grad_bias[d0 + k] += part.grad_bias[k];
        }
    }
}

simd_kernel! {
    /// Backward of one (batch, channel group): recomputes the forward pass into
    /// `trace`, then walks the tokens backwards. Writes dL/du and
    /// dL/d delta_raw for the group's channels; returns the shared gradients.
    fn scan_group_backward<FMA>(
        data: &ScanData,
        b: usize,
        group: usize,
        grad_y: &[f32],
        trace: &mut ScanTrace,
        gu_out: DisjointWriter,
        graw_out: DisjointWriter,
    ) -> GroupGradients {
        const SB: usize = STATE_BLOCK;
        scan_forward_body::<FMA, true>(data, b, group, None, None, None, None, trace);
        let dims = data.dims;
        let (n_state, seq_len, d_inner) = (dims.d_state, dims.seq_len, dims.d_inner);
        let n_pad = padded_state(dims);
        let (d0, width) = group_span(dims, group);
        let a_t = group_a(data, d0, width);
        let bias = load_lanes(data.delta_bias, d0, width);
        let skip = load_lanes(data.d, d0, width);
        let zero_state = vec![ZERO; n_pad];
        // dL/dh_t carried from token t+1 (already multiplied by its decay).
        let mut grad_h = vec![ZERO; n_pad];
        let mut part = GroupGradients {
            b,
            group,
            grad_b: vec![0f32; seq_len * n_state],
            grad_c: vec![0f32; seq_len * n_state],
            grad_a: vec![ZERO; n_pad],
            grad_d: ZERO,
            grad_bias: ZERO,
        };
        for t in (0..seq_len).rev() {
            let row = (b * seq_len + t) * d_inner + d0;
            let bc_row = (b * seq_len + t) * n_state;
            let u = load_lanes(data.u, row, width);
            let raw = load_lanes(data.delta_raw, row, width);
            let gy = load_lanes(grad_y, row, width);
            let delta = trace.delta[t];
            let h_t = &trace.h[t * n_pad..(t + 1) * n_pad];
            let h_prev = if t > 0 { &trace.h[(t - 1) * n_pad..t * n_pad] } else { &zero_state[..] };
            let decay_t = &trace.decay[t * n_pad..(t + 1) * n_pad];
            let mut du = ZERO;
            // dL/du and dL/d delta in SB parts: independent FMA chains
            let mut gu = [ZERO; SB];
            let mut gdelta = [ZERO; SB];
            for k in 0..LANES {
                du[k] = delta[k] * u[k];
                gu[0][k] = gy[k] * skip[k];
                part.grad_d[k] = madd::<FMA>(gy[k], u[k], part.grad_d[k]);
            }
            for n0 in (0..n_pad).step_by(SB) {
                let b_n = bc_block::<SB>(data.b, bc_row, n0, n_state);
                let c_n = bc_block::<SB>(data.c, bc_row, n0, n_state);
                let (a_n, h_n, h_p, dec) =
                    (block::<SB>(&a_t, n0), block::<SB>(h_t, n0), block::<SB>(h_prev, n0), block::<SB>(decay_t, n0));
                // stack copies of the blocks written to: the vectoriser must see that
                // nothing written aliases the trace it reads
                let mut g_h = *block::<SB>(&grad_h, n0);
                let mut g_a = *block::<SB>(&part.grad_a, n0);
                let mut gy_h = [ZERO; SB];
                let mut g_du = [ZERO; SB];
                for j in 0..SB {
                    let (b_j, c_j) = (b_n[j], c_n[j]);
                    let (a_j, h_j, hp_j, dec_j) = (&a_n[j], &h_n[j], &h_p[j], &dec[j]);
                    let (gh_j, ga_j) = (&mut g_h[j], &mut g_a[j]);
                    let (gu_j, gdelta_j) = (&mut gu[j], &mut gdelta[j]);
                    let (gyh_j, gdu_j) = (&mut gy_h[j], &mut g_du[j]);
                    // (two simple lane loops: one big body defeats the SLP vectoriser)
                    let mut g = ZERO;
                    for k in 0..LANES {
                        // total dL/dh_t[n]
                        g[k] = madd::<FMA>(gy[k], c_j, gh_j[k]);
                        gyh_j[k] = gy[k] * h_j[k];
                        gdu_j[k] = g[k] * du[k];
                        gh_j[k] = g[k] * dec_j[k];
                    }
                    for k in 0..LANES {
                        let h_decay = hp_j[k] * dec_j[k];
                        gu_j[k] = madd::<FMA>(g[k] * delta[k], b_j, gu_j[k]);
                        let d_delta = madd::<FMA>(b_j, u[k], a_j[k] * h_decay);
                        gdelta_j[k] = madd::<FMA>(g[k], d_delta, gdelta_j[k]);
                        ga_j[k] = madd::<FMA>(g[k] * h_decay, delta[k], ga_j[k]);
                    }
                }
                *block_mut::<SB>(&mut grad_h, n0) = g_h;
                *block_mut::<SB>(&mut part.grad_a, n0) = g_a;
                let tn = t * n_state;
                for j in 0..SB.min(n_state.saturating_sub(n0)) {
                    part.grad_c[tn + n0 + j] = lane_sum(&gy_h[j]);
                    part.grad_b[tn + n0 + j] = lane_sum(&g_du[j]);
                }
            }
            let mut gu_sum = ZERO;
            let mut graw = ZERO;
            for k in 0..LANES {
                let (mut acc_u, mut acc_delta) = (gu[0][k], gdelta[0][k]);
                for j in 1..SB {
                    acc_u += gu[j][k];
                    acc_delta += gdelta[j][k];
                }
                gu_sum[k] = acc_u;
                graw[k] = acc_delta * sigmoid::<FMA>(raw[k] + bias[k]);
                part.grad_bias[k] += graw[k];
            }
            // SAFETY: task (b, group) is the only writer of these channels of row t.
            unsafe {
                gu_out.write_slice(row, &gu_sum[..width]);
                graw_out.write_slice(row, &graw[..width]);
            }
        }
        part
    }
}
