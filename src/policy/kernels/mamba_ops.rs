//! Fused element-wise ops of the Mamba block, as candle custom ops with
//! backward passes: RMSNorm with AdaLN modulation, the causal depthwise
//! convolution with SiLU, the SiLU gate, and the gated residual. Each replaces
//! 3 to 10 single-threaded candle ops (with libm `exp`) by one parallel pass
//! that the SIMD dispatch of [`crate::policy::kernels::simd`] vectorises.
//!
//! Shapes: tokens are `[B, L, width]` with the last dimension contiguous; the
//! modulation operands may be strided views, including stride-0 broadcasts
//! over L (one AdaLN condition shared by all tokens of a segment).

use crate::policy::error::{PolicyError, Result};
use crate::policy::kernels::simd::{
    LANES, RowView, contiguous_data, f32_data, lane_sum, madd, map_in_place, silu, silu_grad, simd_kernel,
    with_captured,
};
use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Shape, Tensor};
use rayon::prelude::*;

/// Token rows per rayon task of the row-wise ops.
const ROWS_PER_TASK: usize = 64;

fn check_rank3(t: &Tensor, what: &str) -> Result<(usize, usize, usize)> {
    t.dims3()
        .map_err(|_| PolicyError::Invalid(format!("{what}: expected [batch, seq_len, width], got {:?}", t.shape())))
}

fn check_shape(t: &Tensor, shape: &[usize], what: &str) -> Result<()> {
    if t.dims() != shape {
        return Err(PolicyError::Invalid(format!("{what}: expected shape {shape:?}, got {:?}", t.shape())));
    }
    Ok(())
}

/// sum_i a_i b_i with 16 partial sums (a sequential float sum cannot be
/// vectorised).
#[inline(always)]
fn dot<const FMA: bool>(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; LANES];
    let mut chunks_a = a.chunks_exact(LANES);
    let mut chunks_b = b.chunks_exact(LANES);
    for (ca, cb) in (&mut chunks_a).zip(&mut chunks_b) {
        for k in 0..LANES {
            acc[k] = madd::<FMA>(ca[k], cb[k], acc[k]);
        }
    }
    let mut tail = 0f32;
    for (x, y) in chunks_a.remainder().iter().zip(chunks_b.remainder()) {
        tail = madd::<FMA>(*x, *y, tail);
    }
    lane_sum(&acc) + tail
}

// ---------------------------------------------------------------------------
// RMSNorm + AdaLN modulation

/// `rms_norm(x) * weight * (1 + scale) + shift` per token, with
/// `rms_norm(x) = x / sqrt(mean(x^2) + eps)`.
///
/// - `x`: [B, L, C]
/// - `weight`: `[C]`, the RMSNorm gain
/// - `shift_scale`: [B, L, 2C] (shift in the first C, scale in the next C);
///   usually a broadcast view of a per-segment [B, 1, 2C]
///
/// Differentiable with respect to all three.
pub fn ada_rms_norm(x: &Tensor, weight: &Tensor, shift_scale: &Tensor, eps: f64) -> Result<Tensor> {
    let (b, l, c) = check_rank3(x, "AdaLN RMSNorm x")?;
    check_shape(weight, &[c], "AdaLN RMSNorm weight")?;
    check_shape(shift_scale, &[b, l, 2 * c], "AdaLN RMSNorm shift/scale")?;
    Ok(x.apply_op3(&weight.contiguous()?, shift_scale, AdaRmsNorm { eps: eps as f32 })?)
}

struct AdaRmsNorm {
    eps: f32,
}

impl CustomOp3 for AdaRmsNorm {
    fn name(&self) -> &'static str {
        "ada-rms-norm"
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
        let (x, xv) = (f32_data(s1, "AdaLN RMSNorm x")?, RowView::new(l1, "AdaLN RMSNorm x")?);
        let weight = contiguous_data(s2, l2, "AdaLN RMSNorm weight")?;
        let (m, mv) = (f32_data(s3, "AdaLN shift/scale")?, RowView::new(l3, "AdaLN shift/scale")?);
        let [batch, seq_len, c] = xv.dims;
        let mut out = vec![0f32; batch * seq_len * c];
        out.par_chunks_mut(ROWS_PER_TASK * c)
            .enumerate()
            .for_each(|(task, out)| ada_rms_norm_rows(x, xv, weight, m, mv, self.eps, task * ROWS_PER_TASK, out));
        Ok((CpuStorage::F32(out), Shape::from((batch, seq_len, c))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        shift_scale: &Tensor,
        _out: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (b, l, c) = x.dims3()?;
        let op = AdaRmsNormBackward { eps: self.eps, grad: grad.contiguous()? };
        let grads = x.apply_op3_no_bwd(weight, shift_scale, &op)?;
        let n = b * l * c;
        Ok((
            Some(grads.narrow(0, 0, n)?.reshape((b, l, c))?),
            Some(grads.narrow(0, n, c)?),
            Some(grads.narrow(0, n + c, 2 * n)?.reshape((b, l, 2 * c))?),
        ))
    }
}

simd_kernel! {
    fn ada_rms_norm_rows<FMA>(
        x: &[f32], xv: RowView, weight: &[f32], m: &[f32], mv: RowView, eps: f32,
        first_row: usize, out: &mut [f32],
    ) {
        let [_, seq_len, c] = xv.dims;
        for (i, out) in out.chunks_exact_mut(c).enumerate() {
            let row = first_row + i;
            let (b, t) = (row / seq_len, row % seq_len);
            let x = xv.slice(x, b, t);
            let mr = mv.slice(m, b, t);
            let (shift, scale) = mr.split_at(c);
            let r = 1.0 / (dot::<FMA>(x, x) / c as f32 + eps).sqrt();
            for j in 0..c {
                out[j] = madd::<FMA>(x[j] * r * weight[j], 1.0 + scale[j], shift[j]);
            }
        }
    }
}

/// Captured: dL/dout [B, L, C]. Output, flat: dL/dx [B·L·C], dL/dweight [C],
/// dL/dshift_scale [B·L·2C].
struct AdaRmsNormBackward {
    eps: f32,
    grad: Tensor,
}

impl CustomOp3 for AdaRmsNormBackward {
    fn name(&self) -> &'static str {
        "ada-rms-norm-backward"
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
        let (x, xv) = (f32_data(s1, "AdaLN RMSNorm x")?, RowView::new(l1, "AdaLN RMSNorm x")?);
        let weight = contiguous_data(s2, l2, "AdaLN RMSNorm weight")?;
        let (m, mv) = (f32_data(s3, "AdaLN shift/scale")?, RowView::new(l3, "AdaLN shift/scale")?);
        let [batch, seq_len, c] = xv.dims;
        let n = batch * seq_len * c;
        with_captured(&self.grad, "AdaLN RMSNorm dL/dout", |grad| {
            let mut out = vec![0f32; n + c + 2 * n];
            let (grad_x, rest) = out.split_at_mut(n);
            let (grad_w, grad_m) = rest.split_at_mut(c);
            let partial_w = grad_x
                .par_chunks_mut(ROWS_PER_TASK * c)
                .zip(grad_m.par_chunks_mut(ROWS_PER_TASK * 2 * c))
                .enumerate()
                .map(|(task, (gx, gm))| {
                    ada_rms_norm_backward_rows(x, xv, weight, m, mv, self.eps, grad, task * ROWS_PER_TASK, gx, gm)
                })
                .collect::<Vec<Vec<f32>>>();
            let partial_w = sum_in_task_order(&partial_w, c);
            grad_w.copy_from_slice(&partial_w);
            let len = out.len();
            Ok((CpuStorage::F32(out), Shape::from(len)))
        })
    }
}

/// The sum of per-task partial gradients, added in task order. A rayon `reduce` would add
/// them in an order that depends on work stealing, so the same step could give different bits
/// (and `--resume` would no longer continue exactly).
fn sum_in_task_order(parts: &[Vec<f32>], len: usize) -> Vec<f32> {
    let mut sum = vec![0f32; len];
    for part in parts {
        sum.iter_mut().zip(part).for_each(|(s, p)| *s += p);
    }
    sum
}

simd_kernel! {
    /// Returns this task's share of dL/dweight.
    fn ada_rms_norm_backward_rows<FMA>(
        x: &[f32], xv: RowView, weight: &[f32], m: &[f32], mv: RowView, eps: f32,
        grad: &[f32], first_row: usize, grad_x: &mut [f32], grad_m: &mut [f32],
    ) -> Vec<f32> {
        let [_, seq_len, c] = xv.dims;
        let mut grad_w = vec![0f32; c];
        let mut g_norm = vec![0f32; c];
        for (i, (gx, gm)) in grad_x.chunks_exact_mut(c).zip(grad_m.chunks_exact_mut(2 * c)).enumerate() {
            let row = first_row + i;
            let (b, t) = (row / seq_len, row % seq_len);
            let x = xv.slice(x, b, t);
            let scale = &mv.slice(m, b, t)[c..];
            let g = &grad[row * c..(row + 1) * c];
            let r = 1.0 / (dot::<FMA>(x, x) / c as f32 + eps).sqrt();
            let (g_shift, g_scale) = gm.split_at_mut(c);
            // x_hat = x r; out = x_hat w (1 + scale) + shift
            for j in 0..c {
                let x_hat = x[j] * r;
                let gw = g[j] * (1.0 + scale[j]);
                grad_w[j] = madd::<FMA>(gw, x_hat, grad_w[j]);
                g_scale[j] = g[j] * x_hat * weight[j];
                g_shift[j] = g[j];
                g_norm[j] = gw * weight[j];
            }
            // d x_hat / dx: r (I - x_hat x_hat^T / C)
            let mean_dot = dot::<FMA>(&g_norm, x) * r / c as f32;
            for j in 0..c {
                gx[j] = r * madd::<FMA>(-x[j] * r, mean_dot, g_norm[j]);
            }
        }
        grad_w
    }
}

// ---------------------------------------------------------------------------
// Causal depthwise convolution + SiLU

/// `silu(bias[d] + sum_k weight[d, k] x[t - (K-1) + k, d])`, the causal
/// depthwise conv1d of Mamba (PyTorch `Conv1d(groups = Di, padding = K-1)`
/// truncated to L) fused with its SiLU.
///
/// - `x`: [B, L, Di] (may be a strided view, e.g. the x half of `in_proj`)
/// - `weight`: `[Di, K]`; `bias`: `[Di]`
/// - `tail`: the last K-1 inputs before `x`, [B, K-1, Di] (inference with a
///   cached prefix), or `None` for zeros. With a tail the op has no backward.
///
/// Returns u: [B, L, Di].
pub fn causal_conv_silu(x: &Tensor, weight: &Tensor, bias: &Tensor, tail: Option<&Tensor>) -> Result<Tensor> {
    let (b, _, di) = check_rank3(x, "causal conv x")?;
    let (di_w, k) = weight
        .dims2()
        .map_err(|_| PolicyError::Invalid(format!("causal conv weight: expected [Di, K], got {:?}", weight.shape())))?;
    if di_w != di || k == 0 {
        return Err(PolicyError::Invalid(format!(
            "causal conv weight: expected [{di}, K>0], got {:?}",
            weight.shape()
        )));
    }
    check_shape(bias, &[di], "causal conv bias")?;
    let (weight, bias) = (weight.contiguous()?, bias.contiguous()?);
    match tail {
        None => Ok(x.apply_op3(&weight, &bias, CausalConvSilu { tail: None })?),
        Some(tail) => {
            check_shape(tail, &[b, k - 1, di], "causal conv tail (cached state)")?;
            let op = CausalConvSilu { tail: Some(tail.contiguous()?) };
            Ok(x.apply_op3_no_bwd(&weight, &bias, &op)?)
        }
    }
}

struct CausalConvSilu {
    tail: Option<Tensor>,
}

/// The input row feeding tap `k` of output row `t`: from x, the tail, or none.
#[inline(always)]
fn conv_source<'a>(
    x: &'a [f32],
    xv: RowView,
    tail: Option<&'a [f32]>,
    b: usize,
    t: usize,
    k: usize,
    taps: usize,
) -> Option<&'a [f32]> {
    let di = xv.dims[2];
    if t + k >= taps - 1 {
        Some(xv.slice(x, b, t + k - (taps - 1)))
    } else {
        // row t + k of the tail, which holds inputs -(K-1) .. -1
        tail.map(|tail| {
            let start = (b * (taps - 1) + t + k) * di;
            &tail[start..start + di]
        })
    }
}

/// Weight transposed to [K][Di] so taps run over contiguous channels.
fn taps_major(weight: &[f32], di: usize, taps: usize) -> Vec<f32> {
    let mut w = vec![0f32; di * taps];
    for d in 0..di {
        for k in 0..taps {
            w[k * di + d] = weight[d * taps + k];
        }
    }
    w
}

impl CustomOp3 for CausalConvSilu {
    fn name(&self) -> &'static str {
        "causal-conv-silu"
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
        let (x, xv) = (f32_data(s1, "causal conv x")?, RowView::new(l1, "causal conv x")?);
        let weight = contiguous_data(s2, l2, "causal conv weight")?;
        let bias = contiguous_data(s3, l3, "causal conv bias")?;
        let [batch, seq_len, di] = xv.dims;
        let taps = weight.len() / di;
        let w = taps_major(weight, di, taps);
        let run = |tail: Option<&[f32]>| {
            let mut out = vec![0f32; batch * seq_len * di];
            out.par_chunks_mut(seq_len * di).enumerate().for_each(|(b, out)| {
                out.par_chunks_mut(ROWS_PER_TASK * di)
                    .enumerate()
                    .for_each(|(task, out)| conv_silu_rows(x, xv, tail, &w, bias, b, task * ROWS_PER_TASK, out))
            });
            Ok((CpuStorage::F32(out), Shape::from((batch, seq_len, di))))
        };
        match &self.tail {
            None => run(None),
            Some(tail) => with_captured(tail, "causal conv tail", |tail| run(Some(tail))),
        }
    }

    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        bias: &Tensor,
        _out: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        if self.tail.is_some() {
            candle_core::bail!("causal conv: no backward through a conv from a cached tail")
        }
        let (b, l, di) = x.dims3()?;
        let taps = weight.dim(1)?;
        let op = CausalConvSiluBackward { grad: grad.contiguous()? };
        let grads = x.apply_op3_no_bwd(weight, bias, &op)?;
        let n = b * l * di;
        Ok((
            Some(grads.narrow(0, 0, n)?.reshape((b, l, di))?),
            Some(grads.narrow(0, n, di * taps)?.reshape((di, taps))?),
            Some(grads.narrow(0, n + di * taps, di)?),
        ))
    }
}

simd_kernel! {
    /// Pre-activation conv output of rows `first_row..` of batch `b` into
    /// `out`, then SiLU in place if `activate`.
    fn conv_silu_rows<FMA>(
        x: &[f32], xv: RowView, tail: Option<&[f32]>, w: &[f32], bias: &[f32],
        b: usize, first_row: usize, out: &mut [f32],
    ) {
        conv_rows_body::<FMA>(x, xv, tail, w, bias, b, first_row, out);
        map_in_place(out, silu::<FMA>);
    }
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn conv_rows_body<const FMA: bool>(
    x: &[f32],
    xv: RowView,
    tail: Option<&[f32]>,
    w: &[f32],
    bias: &[f32],
    b: usize,
    first_row: usize,
    out: &mut [f32],
) {
    let di = xv.dims[2];
    let taps = w.len() / di;
    for (i, out) in out.chunks_exact_mut(di).enumerate() {
        let t = first_row + i;
        out.copy_from_slice(bias);
        for k in 0..taps {
            if let Some(src) = conv_source(x, xv, tail, b, t, k, taps) {
                let wk = &w[k * di..(k + 1) * di];
                for ((o, &s), &wv) in out.iter_mut().zip(src).zip(wk) {
                    *o = madd::<FMA>(wv, s, *o);
                }
            }
        }
    }
}

/// Captured: dL/du [B, L, Di]. Output, flat: dL/dx [B·L·Di], dL/dweight
/// [Di·K], dL/dbias [Di].
struct CausalConvSiluBackward {
    grad: Tensor,
}

impl CustomOp3 for CausalConvSiluBackward {
    fn name(&self) -> &'static str {
        "causal-conv-silu-backward"
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
        let (x, xv) = (f32_data(s1, "causal conv x")?, RowView::new(l1, "causal conv x")?);
        let weight = contiguous_data(s2, l2, "causal conv weight")?;
        let bias = contiguous_data(s3, l3, "causal conv bias")?;
        let [batch, seq_len, di] = xv.dims;
        let taps = weight.len() / di;
        let w = taps_major(weight, di, taps);
        with_captured(&self.grad, "causal conv dL/du", |grad| {
            let n = batch * seq_len * di;
            let mut out = vec![0f32; n + di * taps + di];
            let (grad_x, rest) = out.split_at_mut(n);
            let (grad_w, grad_b) = rest.split_at_mut(di * taps);
            // per task: dL/dw as [K][Di] followed by dL/dbias [Di]
            let partial = grad_x
                .par_chunks_mut(seq_len * di)
                .enumerate()
                .flat_map(|(b, gx)| {
                    gx.par_chunks_mut(ROWS_PER_TASK * di).enumerate().map(move |(task, gx)| (b, task, gx))
                })
                .map(|(b, task, gx)| conv_silu_backward_rows(x, xv, &w, bias, grad, b, task * ROWS_PER_TASK, gx))
                .collect::<Vec<Vec<f32>>>();
            let partial = sum_in_task_order(&partial, (taps + 1) * di);
            for d in 0..di {
                for k in 0..taps {
                    grad_w[d * taps + k] = partial[k * di + d];
                }
            }
            grad_b.copy_from_slice(&partial[taps * di..]);
            let len = out.len();
            Ok((CpuStorage::F32(out), Shape::from(len)))
        })
    }
}

simd_kernel! {
    /// dL/dx for rows `first_row..` of batch `b` (into `grad_x`); returns this
    /// task's dL/dweight ([K][Di]) and dL/dbias ([Di]), concatenated.
    fn conv_silu_backward_rows<FMA>(
        x: &[f32], xv: RowView, w: &[f32], bias: &[f32], grad: &[f32],
        b: usize, first_row: usize, grad_x: &mut [f32],
    ) -> Vec<f32> {
        let [_, seq_len, di] = xv.dims;
        let taps = w.len() / di;
        let rows = grad_x.len() / di;
        // dL/dv (pre-activation) for rows first_row .. first_row + rows + K - 1
        let halo_rows = (rows + taps - 1).min(seq_len - first_row);
        let mut grad_v = vec![0f32; halo_rows * di];
        conv_rows_body::<FMA>(x, xv, None, w, bias, b, first_row, &mut grad_v);
        let g = &grad[(b * seq_len + first_row) * di..(b * seq_len + first_row + halo_rows) * di];
        for (v, &g) in grad_v.iter_mut().zip(g) {
            *v = g * silu_grad::<FMA>(*v);
        }
        let mut partial = vec![0f32; (taps + 1) * di];
        for (i, gx) in grad_x.chunks_exact_mut(di).enumerate() {
            let s = first_row + i;
            // input s feeds output s + (K-1) - k through tap k
            for k in 0..taps {
                let i_out = i + taps - 1 - k;
                if first_row + i_out < seq_len {
                    let gv = &grad_v[i_out * di..(i_out + 1) * di];
                    let wk = &w[k * di..(k + 1) * di];
                    for ((o, &g), &wv) in gx.iter_mut().zip(gv).zip(wk) {
                        *o = madd::<FMA>(wv, g, *o);
                    }
                }
            }
            // output s reads input s - (K-1) + k through tap k
            let gv = &grad_v[i * di..(i + 1) * di];
            for k in 0..taps {
                if s + k >= taps - 1 {
                    let src = xv.slice(x, b, s + k - (taps - 1));
                    let pw = &mut partial[k * di..(k + 1) * di];
                    for ((p, &g), &xv) in pw.iter_mut().zip(gv).zip(src) {
                        *p = madd::<FMA>(g, xv, *p);
                    }
                }
            }
            for (p, &g) in partial[taps * di..].iter_mut().zip(gv) {
                *p += g;
            }
        }
        partial
    }
}

// ---------------------------------------------------------------------------
// SiLU gate

/// `y * silu(z)`, the output gate of the Mamba mixer. `y`: [B, L, Di]; `z`:
/// [B, L, Di], may be a strided view (the z half of `in_proj`).
pub fn silu_gate(y: &Tensor, z: &Tensor) -> Result<Tensor> {
    let (b, l, di) = check_rank3(y, "SiLU gate y")?;
    check_shape(z, &[b, l, di], "SiLU gate z")?;
    Ok(y.contiguous()?.apply_op2(z, SiluGate)?)
}

struct SiluGate;

impl CustomOp2 for SiluGate {
    fn name(&self) -> &'static str {
        "silu-gate"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let y = contiguous_data(s1, l1, "SiLU gate y")?;
        let (z, zv) = (f32_data(s2, "SiLU gate z")?, RowView::new(l2, "SiLU gate z")?);
        let [batch, seq_len, di] = zv.dims;
        let mut out = vec![0f32; y.len()];
        out.par_chunks_mut(ROWS_PER_TASK * di)
            .enumerate()
            .for_each(|(task, out)| silu_gate_rows(y, z, zv, None, task * ROWS_PER_TASK, out, &mut []));
        Ok((CpuStorage::F32(out), Shape::from((batch, seq_len, di))))
    }

    fn bwd(
        &self,
        y: &Tensor,
        z: &Tensor,
        _out: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let grads = y.apply_op3_no_bwd(z, &grad.contiguous()?, &SiluGateBackward)?;
        let n = y.elem_count();
        Ok((Some(grads.narrow(0, 0, n)?.reshape(y.shape())?), Some(grads.narrow(0, n, n)?.reshape(y.shape())?)))
    }
}

/// Operands y, z, dL/dout; output, flat: dL/dy, dL/dz.
struct SiluGateBackward;

impl CustomOp3 for SiluGateBackward {
    fn name(&self) -> &'static str {
        "silu-gate-backward"
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
        let y = contiguous_data(s1, l1, "SiLU gate y")?;
        let (z, zv) = (f32_data(s2, "SiLU gate z")?, RowView::new(l2, "SiLU gate z")?);
        let grad = contiguous_data(s3, l3, "SiLU gate dL/dout")?;
        let di = zv.dims[2];
        let n = y.len();
        let mut out = vec![0f32; 2 * n];
        let (gy, gz) = out.split_at_mut(n);
        gy.par_chunks_mut(ROWS_PER_TASK * di)
            .zip(gz.par_chunks_mut(ROWS_PER_TASK * di))
            .enumerate()
            .for_each(|(task, (gy, gz))| silu_gate_rows(y, z, zv, Some(grad), task * ROWS_PER_TASK, gy, gz));
        Ok((CpuStorage::F32(out), Shape::from(2 * n)))
    }
}

simd_kernel! {
    /// Forward (`grad` None): `out = y silu(z)`. Backward: `out = dL/dy`,
    /// `grad_z = dL/dz`.
    fn silu_gate_rows<FMA>(
        y: &[f32], z: &[f32], zv: RowView, grad: Option<&[f32]>, first_row: usize,
        out: &mut [f32], grad_z: &mut [f32],
    ) {
        let [_, seq_len, di] = zv.dims;
        for (i, out) in out.chunks_exact_mut(di).enumerate() {
            let row = first_row + i;
            let zr = zv.slice(z, row / seq_len, row % seq_len);
            let yr = &y[row * di..(row + 1) * di];
            match grad {
                None => {
                    for ((o, &y), &z) in out.iter_mut().zip(yr).zip(zr) {
                        *o = y * silu::<FMA>(z);
                    }
                }
                Some(grad) => {
                    let g = &grad[row * di..(row + 1) * di];
                    let gz = &mut grad_z[i * di..(i + 1) * di];
                    for j in 0..di {
                        out[j] = g[j] * silu::<FMA>(zr[j]);
                        gz[j] = g[j] * yr[j] * silu_grad::<FMA>(zr[j]);
                    }
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------
// Gated residual

/// `x + gate * mixed`, the AdaLN-Zero residual. `x`, `mixed`: [B, L, C];
/// `gate`: [B, L, C], usually a broadcast view of a per-segment [B, 1, C].
pub fn gated_residual(x: &Tensor, mixed: &Tensor, gate: &Tensor) -> Result<Tensor> {
    let (b, l, c) = check_rank3(x, "gated residual x")?;
    check_shape(mixed, &[b, l, c], "gated residual mixer output")?;
    check_shape(gate, &[b, l, c], "gated residual gate")?;
    Ok(x.apply_op3(&mixed.contiguous()?, gate, GatedResidual)?)
}

struct GatedResidual;

impl CustomOp3 for GatedResidual {
    fn name(&self) -> &'static str {
        "gated-residual"
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
        let (x, xv) = (f32_data(s1, "gated residual x")?, RowView::new(l1, "gated residual x")?);
        let mixed = contiguous_data(s2, l2, "gated residual mixer output")?;
        let (gate, gv) = (f32_data(s3, "gated residual gate")?, RowView::new(l3, "gated residual gate")?);
        let [batch, seq_len, c] = xv.dims;
        let mut out = vec![0f32; batch * seq_len * c];
        out.par_chunks_mut(ROWS_PER_TASK * c)
            .enumerate()
            .for_each(|(task, out)| gated_residual_rows(x, xv, mixed, gate, gv, task * ROWS_PER_TASK, out));
        Ok((CpuStorage::F32(out), Shape::from((batch, seq_len, c))))
    }

    fn bwd(
        &self,
        _x: &Tensor,
        mixed: &Tensor,
        gate: &Tensor,
        _out: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        Ok((Some(grad.clone()), Some(grad.mul(gate)?), Some(grad.mul(mixed)?)))
    }
}

simd_kernel! {
    fn gated_residual_rows<FMA>(
        x: &[f32], xv: RowView, mixed: &[f32], gate: &[f32], gv: RowView, first_row: usize,
        out: &mut [f32],
    ) {
        let [_, seq_len, c] = xv.dims;
        for (i, out) in out.chunks_exact_mut(c).enumerate() {
            let row = first_row + i;
            let (b, t) = (row / seq_len, row % seq_len);
            let (xr, gr) = (xv.slice(x, b, t), gv.slice(gate, b, t));
            let mr = &mixed[row * c..(row + 1) * c];
            for j in 0..c {
                out[j] = madd::<FMA>(gr[j], mr[j], xr[j]);
            }
        }
    }
}
