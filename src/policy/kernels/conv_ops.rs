//! CPU kernels of the image encoder, as candle custom ops with backward:
//! im2col / col2im on channels-last images (so convolutions run as GEMMs),
//! the fused channel LayerNorm + SiLU, and the fused nearest-2x-upsample-add
//! of the feature pyramid. f32 for training; f64 too, for gradient checks.
//! Parallel over image rows with rayon; reductions are summed in a fixed
//! order, so results do not depend on the thread count.

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp1, DType, Layout, Shape, Tensor};
use rayon::prelude::*;

/// Geometry of a square convolution window on a channels-last image.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Window {
    pub(crate) kernel: usize,
    pub(crate) stride: usize,
    pub(crate) padding: usize,
}

impl Window {
    pub(crate) fn out_size(&self, size: usize) -> usize {
        (size + 2 * self.padding - self.kernel) / self.stride + 1
    }
}

/// `[N, H, W, C]` -> `[N * Ho * Wo, k * k * C]`, columns ordered (ky, kx, c);
/// out-of-image taps are zero.
pub(crate) struct Im2Col(pub(crate) Window);

/// The adjoint of [`Im2Col`]: scatters-and-adds columns back to `[N, H, W, C]`.
struct Col2Im {
    window: Window,
    dims: (usize, usize, usize, usize),
}

fn im2col_typed<T: Copy + Default + Send + Sync>(
    src: &[T],
    (n, h, w, c): (usize, usize, usize, usize),
    win: Window,
) -> Vec<T> {
    let (ho, wo) = (win.out_size(h), win.out_size(w));
    let k = win.kernel;
    let row_len = k * k * c;
    let mut dst = vec![T::default(); n * ho * wo * row_len];
    // One parallel task per output image row.
    dst.par_chunks_mut(wo * row_len).enumerate().for_each(|(row, out)| {
        let (img, oy) = (row / ho, row % ho);
        let base = img * h * w * c;
        for ox in 0..wo {
            let out_px = &mut out[ox * row_len..(ox + 1) * row_len];
            for ky in 0..k {
                let iy = (oy * win.stride + ky) as isize - win.padding as isize;
                if iy < 0 || iy >= h as isize {
                    continue;
                }
                for kx in 0..k {
                    let ix = (ox * win.stride + kx) as isize - win.padding as isize;
                    if ix < 0 || ix >= w as isize {
                        continue;
                    }
                    let s = base + (iy as usize * w + ix as usize) * c;
                    let d = (ky * k + kx) * c;
                    out_px[d..d + c].copy_from_slice(&src[s..s + c]);
                }
            }
        }
    });
    dst
}

fn col2im_typed<T: Copy + Default + Send + Sync + std::ops::AddAssign>(
    cols: &[T],
    (n, h, w, c): (usize, usize, usize, usize),
    win: Window,
) -> Vec<T> {
    let (ho, wo) = (win.out_size(h), win.out_size(w));
    let k = win.kernel;
    let row_len = k * k * c;
    let mut dst = vec![T::default(); n * h * w * c];
    // One parallel task per *input* image row: it gathers every (oy, ky) that
    // reads it, so no two tasks write the same element.
    dst.par_chunks_mut(w * c).enumerate().for_each(|(row, out)| {
        let (img, iy) = (row / h, row % h);
        for ky in 0..k {
            let num = iy as isize + win.padding as isize - ky as isize;
            if num < 0 || num % win.stride as isize != 0 {
                continue;
            }
            let oy = (num / win.stride as isize) as usize;
            if oy >= ho {
                continue;
            }
            for ox in 0..wo {
                let col_row = ((img * ho + oy) * wo + ox) * row_len;
                for kx in 0..k {
                    let ix = (ox * win.stride + kx) as isize - win.padding as isize;
                    if ix < 0 || ix >= w as isize {
                        continue;
                    }
                    let s = col_row + (ky * k + kx) * c;
                    let d = ix as usize * c;
                    for (o, &v) in out[d..d + c].iter_mut().zip(&cols[s..s + c]) {
                        *o += v;
                    }
                }
            }
        }
    });
    dst
}

fn contiguous_slice<'a, T>(data: &'a [T], layout: &Layout, op: &str) -> candle_core::Result<&'a [T]> {
    match layout.contiguous_offsets() {
        Some((start, end)) => Ok(&data[start..end]),
        None => candle_core::bail!("{op}: input must be contiguous"),
    }
}

impl CustomOp1 for Im2Col {
    fn name(&self) -> &'static str {
        "im2col-nhwc"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let dims = layout.shape().dims4()?;
        let (n, h, w, c) = dims;
        let win = self.0;
        if h + 2 * win.padding < win.kernel || w + 2 * win.padding < win.kernel {
            candle_core::bail!("im2col: {h}x{w} image is smaller than the {0}x{0} window", win.kernel)
        }
        let shape = Shape::from((n * win.out_size(h) * win.out_size(w), win.kernel * win.kernel * c));
        let out = match storage {
            CpuStorage::F32(d) => CpuStorage::F32(im2col_typed(contiguous_slice(d, layout, "im2col")?, dims, win)),
            CpuStorage::F64(d) => CpuStorage::F64(im2col_typed(contiguous_slice(d, layout, "im2col")?, dims, win)),
            other => candle_core::bail!("im2col: unsupported dtype {:?} (use f32)", other.dtype()),
        };
        Ok((out, shape))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> candle_core::Result<Option<Tensor>> {
        let op = Col2Im { window: self.0, dims: arg.dims4()? };
        Ok(Some(grad_res.contiguous()?.apply_op1(op)?))
    }
}

impl CustomOp1 for Col2Im {
    fn name(&self) -> &'static str {
        "col2im-nhwc"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let (n, h, w, c) = self.dims;
        let win = self.window;
        let expected = (n * win.out_size(h) * win.out_size(w), win.kernel * win.kernel * c);
        if layout.shape().dims2()? != expected {
            candle_core::bail!("col2im: columns {:?}, expected {expected:?}", layout.shape())
        }
        let out = match storage {
            CpuStorage::F32(d) => CpuStorage::F32(col2im_typed(contiguous_slice(d, layout, "col2im")?, self.dims, win)),
            CpuStorage::F64(d) => CpuStorage::F64(col2im_typed(contiguous_slice(d, layout, "col2im")?, self.dims, win)),
            other => candle_core::bail!("col2im: unsupported dtype {:?} (use f32)", other.dtype()),
        };
        Ok((out, Shape::from(self.dims)))
    }

    fn bwd(&self, _arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> candle_core::Result<Option<Tensor>> {
        Ok(Some(grad_res.contiguous()?.apply_op1(Im2Col(self.window))?))
    }
}

/// `fine + up2(coarse)` for channels-last maps, fine `[N, H, W, C]`, coarse
/// `[N, H/2, W/2, C]` (nearest-neighbour 2x upsampling), in one pass; the
/// backward sums each 2x2 block of the gradient for `coarse`.
pub(crate) struct AddUpsampled2;

fn add_upsampled2_typed<T: NormScalar>(fine: &[T], coarse: &[T], (_, h, w, c): (usize, usize, usize, usize)) -> Vec<T> {
    let mut out = vec![T::ZERO; fine.len()];
    out.par_chunks_mut(w * c).zip(fine.par_chunks(w * c)).enumerate().for_each(|(row, (out, fine))| {
        let (img, y) = (row / h, row % h);
        let coarse_row = ((img * (h / 2)) + y / 2) * (w / 2) * c;
        for x in 0..w {
            let src = &coarse[coarse_row + (x / 2) * c..coarse_row + (x / 2 + 1) * c];
            for i in 0..c {
                out[x * c + i] = fine[x * c + i] + src[i];
            }
        }
    });
    out
}

fn sum_blocks2_typed<T: NormScalar>(grad: &[T], (n, h, w, c): (usize, usize, usize, usize)) -> Vec<T> {
    let (hc, wc) = (h / 2, w / 2);
    let mut out = vec![T::ZERO; n * hc * wc * c];
    out.par_chunks_mut(wc * c).enumerate().for_each(|(row, out)| {
        let (img, yc) = (row / hc, row % hc);
        for dy in 0..2 {
            let g_row = ((img * h) + 2 * yc + dy) * w * c;
            for xc in 0..wc {
                for dx in 0..2 {
                    let g = &grad[g_row + (2 * xc + dx) * c..g_row + (2 * xc + dx + 1) * c];
                    for i in 0..c {
                        out[xc * c + i] += g[i];
                    }
                }
            }
        }
    });
    out
}

impl candle_core::CustomOp2 for AddUpsampled2 {
    fn name(&self) -> &'static str {
        "add-upsampled2-nhwc"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let dims = l1.shape().dims4()?;
        let (n, h, w, c) = dims;
        if h % 2 != 0 || w % 2 != 0 || l2.shape().dims4()? != (n, h / 2, w / 2, c) {
            candle_core::bail!(
                "add-upsampled2: fine {:?} needs coarse [N, H/2, W/2, C], got {:?}",
                l1.shape(),
                l2.shape()
            )
        }
        let out = match (s1, s2) {
            (CpuStorage::F32(f), CpuStorage::F32(c)) => CpuStorage::F32(add_upsampled2_typed(
                contiguous_slice(f, l1, "add-upsampled2")?,
                contiguous_slice(c, l2, "add-upsampled2")?,
                dims,
            )),
            (CpuStorage::F64(f), CpuStorage::F64(c)) => CpuStorage::F64(add_upsampled2_typed(
                contiguous_slice(f, l1, "add-upsampled2")?,
                contiguous_slice(c, l2, "add-upsampled2")?,
                dims,
            )),
            _ => candle_core::bail!("add-upsampled2: both inputs must be f32 (or both f64)"),
        };
        Ok((out, l1.shape().clone()))
    }

    fn bwd(
        &self,
        fine: &Tensor,
        coarse: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let dims = fine.dims4()?;
        let d_coarse = match grad_res.dtype() {
            DType::F32 => {
                let g = grad_res.flatten_all()?.to_vec1::<f32>()?;
                Tensor::from_vec(sum_blocks2_typed(&g, dims), coarse.shape(), coarse.device())?
            }
            DType::F64 => {
                let g = grad_res.flatten_all()?.to_vec1::<f64>()?;
                Tensor::from_vec(sum_blocks2_typed(&g, dims), coarse.shape(), coarse.device())?
            }
            other => candle_core::bail!("add-upsampled2 backward: unsupported dtype {other:?}"),
        };
        Ok((Some(grad_res.clone()), Some(d_coarse)))
    }
}

/// `x + bias` for `x` `[M, C]` and `bias` `[C]`: a convolution's bias after its GEMM. Fused so
/// that the bias gradient is a row sum over fixed blocks of rows; candle's broadcast-add
/// backward reduces the leading dimension with a generic strided loop, 9 % of a `cpu.toml`
/// training step.
pub(crate) struct AddBias;

/// Rows per parallel task of [`AddBias`] (fixed, so the bias gradient is summed in the same
/// order on any machine).
const BIAS_ROWS_PER_TASK: usize = 256;

/// One pass: each output element is written once, from `x` and `bias` (`x.len()` is a multiple
/// of `bias.len()`, checked by the caller).
fn add_bias_typed<T: NormScalar>(x: &[T], bias: &[T]) -> Vec<T> {
    let c = bias.len();
    // whole rows only: the unsafe set_len below relies on it
    assert!(c > 0 && x.len().is_multiple_of(c), "add-bias: {} values are not rows of {c}", x.len());
    let mut out = Vec::with_capacity(x.len());
    out.spare_capacity_mut()[..x.len()]
        .par_chunks_mut(c * BIAS_ROWS_PER_TASK)
        .zip(x.par_chunks(c * BIAS_ROWS_PER_TASK))
        .for_each(|(out, x)| {
            for (out_row, x_row) in out.chunks_exact_mut(c).zip(x.chunks_exact(c)) {
                for ((o, &v), &b) in out_row.iter_mut().zip(x_row).zip(bias) {
                    o.write(v + b);
                }
            }
        });
    // SAFETY: the chunks above cover the first x.len() elements (whole rows of c), and every
    // one of them was written.
    unsafe { out.set_len(x.len()) };
    out
}

/// Column sums of `[M, C]` rows: per block of rows in row order, then the blocks in order.
fn sum_rows_typed<T: NormScalar>(grad: &[T], c: usize) -> Vec<T> {
    let partial: Vec<Vec<T>> = grad
        .par_chunks(c * BIAS_ROWS_PER_TASK)
        .map(|rows| {
            let mut sum = vec![T::ZERO; c];
            for row in rows.chunks_exact(c) {
                for (s, &g) in sum.iter_mut().zip(row) {
                    *s += g;
                }
            }
            sum
        })
        .collect();
    let mut total = vec![T::ZERO; c];
    for block in partial {
        for (t, b) in total.iter_mut().zip(block) {
            *t += b;
        }
    }
    total
}

impl candle_core::CustomOp2 for AddBias {
    fn name(&self) -> &'static str {
        "add-bias-rows"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (_, c) = l1.shape().dims2()?;
        if c == 0 || l2.shape().dims() != [c] {
            candle_core::bail!("add-bias: x {:?} (C > 0) needs a bias [C], got {:?}", l1.shape(), l2.shape())
        }
        let out = match (s1, s2) {
            (CpuStorage::F32(x), CpuStorage::F32(b)) => CpuStorage::F32(add_bias_typed(
                contiguous_slice(x, l1, "add-bias")?,
                contiguous_slice(b, l2, "add-bias")?,
            )),
            (CpuStorage::F64(x), CpuStorage::F64(b)) => CpuStorage::F64(add_bias_typed(
                contiguous_slice(x, l1, "add-bias")?,
                contiguous_slice(b, l2, "add-bias")?,
            )),
            _ => candle_core::bail!("add-bias: both inputs must be f32 (or both f64)"),
        };
        Ok((out, l1.shape().clone()))
    }

    fn bwd(
        &self,
        _x: &Tensor,
        bias: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let c = bias.dim(0)?;
        let grad = grad_res.contiguous()?;
        let d_bias = {
            let (storage, layout) = grad.storage_and_layout();
            match &*storage {
                candle_core::Storage::Cpu(CpuStorage::F32(g)) => {
                    Tensor::from_vec(sum_rows_typed(contiguous_slice(g, layout, "add-bias")?, c), c, bias.device())?
                }
                candle_core::Storage::Cpu(CpuStorage::F64(g)) => {
                    Tensor::from_vec(sum_rows_typed(contiguous_slice(g, layout, "add-bias")?, c), c, bias.device())?
                }
                _ => candle_core::bail!("add-bias backward: f32 or f64 on the CPU only"),
            }
        };
        Ok((Some(grad), Some(d_bias)))
    }
}

/// Rows of a channels-last tensor processed per parallel task in the fused
/// norm (fixed, so reductions are summed in the same order on any machine).
const NORM_ROWS_PER_TASK: usize = 64;

/// Scalar types the fused norm runs on (f32 for training, f64 for gradient
/// checks); the arithmetic is done in the type itself.
trait NormScalar:
    Copy
    + Send
    + Sync
    + 'static
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Div<Output = Self>
    + std::ops::AddAssign
{
    const ZERO: Self;
    const ONE: Self;
    fn from_usize(v: usize) -> Self;
    fn from_f64(v: f64) -> Self;
    fn exp(self) -> Self;
    fn sqrt(self) -> Self;
}
impl NormScalar for f32 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
    fn from_usize(v: usize) -> Self {
        v as f32
    }
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    fn exp(self) -> Self {
        fast_exp_f32(self)
    }
    fn sqrt(self) -> Self {
        f32::sqrt(self)
    }
}
impl NormScalar for f64 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
    fn from_usize(v: usize) -> Self {
        v as f64
    }
    fn from_f64(v: f64) -> Self {
        v
    }
    fn exp(self) -> Self {
        f64::exp(self)
    }
    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
}

/// `e^x` for f32 without a libm call, so loops over it vectorise: x = n ln2 + r
/// with integer n (2^n built in the exponent bits) and |r| <= ln2 / 2 (ln2
/// split in two for an exact reduction), e^r by its degree-6 Taylor
/// polynomial. Relative error below 3e-7 for x in [-87, 88]; inputs outside
/// are clamped (e^x saturates at ~1.6e-38 / ~1.7e38).
#[inline(always)]
fn fast_exp_f32(x: f32) -> f32 {
    const ROUND: f32 = 12_582_912.0; // 1.5 * 2^23: adding it rounds to an integer
    const LN2_HI: f32 = 0.693_359_4; // exactly representable, few mantissa bits
    const LN2_LO: f32 = -2.121_944_4e-4;
    let x = x.clamp(-87.0, 88.0);
    let shifted = x * std::f32::consts::LOG2_E + ROUND;
    let n = shifted.to_bits().wrapping_sub(ROUND.to_bits()) as i32;
    let nf = shifted - ROUND;
    let r = (x - nf * LN2_HI) - nf * LN2_LO;
    let p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    p * f32::from_bits(((n + 127) as u32) << 23)
}

/// Fused `silu(gamma * layer_norm(x) + beta)` over the last axis of a
/// channels-last tensor (inputs: x `[.., C]`, gamma `[C]`, beta `[C]`).
/// One pass forward, one pass backward, instead of ~12 elementwise ops.
pub(crate) struct LayerNormSilu {
    pub(crate) eps: f64,
}

fn sigmoid<T: NormScalar>(z: T) -> T {
    T::ONE / (T::ONE + (T::ZERO - z).exp())
}

/// Mean and 1/std of one row.
fn row_stats<T: NormScalar>(row: &[T], eps: T) -> (T, T) {
    let n = T::from_usize(row.len());
    let mut sum = T::ZERO;
    for &v in row {
        sum += v;
    }
    let mean = sum / n;
    let mut sq = T::ZERO;
    for &v in row {
        let d = v - mean;
        sq += d * d;
    }
    (mean, T::ONE / (sq / n + eps).sqrt())
}

fn layer_norm_silu_fwd<T: NormScalar>(x: &[T], gamma: &[T], beta: &[T], eps: f64) -> Vec<T> {
    let c = gamma.len();
    let eps = T::from_f64(eps);
    let mut out = vec![T::ZERO; x.len()];
    out.par_chunks_mut(c * NORM_ROWS_PER_TASK).zip(x.par_chunks(c * NORM_ROWS_PER_TASK)).for_each(|(out, x)| {
        for (o_row, x_row) in out.chunks_mut(c).zip(x.chunks(c)) {
            let (mean, rstd) = row_stats(x_row, eps);
            // Branch-free, index-free loop: vectorises (see fast_exp_f32).
            for (((o, &xv), &g), &b) in o_row.iter_mut().zip(x_row).zip(gamma).zip(beta) {
                let z = (xv - mean) * rstd * g + b;
                *o = z * sigmoid(z);
            }
        }
    });
    out
}

/// Returns (dx, dgamma, dbeta).
fn layer_norm_silu_bwd<T: NormScalar>(
    x: &[T],
    gamma: &[T],
    beta: &[T],
    dy: &[T],
    eps: f64,
) -> (Vec<T>, Vec<T>, Vec<T>) {
    let c = gamma.len();
    let eps = T::from_f64(eps);
    let mut dx = vec![T::ZERO; x.len()];
    let partials: Vec<(Vec<T>, Vec<T>)> = dx
        .par_chunks_mut(c * NORM_ROWS_PER_TASK)
        .zip(x.par_chunks(c * NORM_ROWS_PER_TASK))
        .zip(dy.par_chunks(c * NORM_ROWS_PER_TASK))
        .map(|((dx, x), dy)| {
            let mut dgamma = vec![T::ZERO; c];
            let mut dbeta = vec![T::ZERO; c];
            let mut xhat = vec![T::ZERO; c];
            let mut dxhat = vec![T::ZERO; c];
            let mut z = vec![T::ZERO; c];
            let mut sig = vec![T::ZERO; c];
            for ((dx_row, x_row), dy_row) in dx.chunks_mut(c).zip(x.chunks(c)).zip(dy.chunks(c)) {
                let (mean, rstd) = row_stats(x_row, eps);
                // Vectorisable part first: normalised input, pre-activation, sigmoid.
                for ((((xh, zi), &xv), &g), &b) in xhat.iter_mut().zip(z.iter_mut()).zip(x_row).zip(gamma).zip(beta) {
                    *xh = (xv - mean) * rstd;
                    *zi = *xh * g + b;
                }
                for (si, &zi) in sig.iter_mut().zip(&z) {
                    *si = sigmoid(zi);
                }
                let (mut sum_dxhat, mut sum_dxhat_xhat) = (T::ZERO, T::ZERO);
                for i in 0..c {
                    let (xh, z, s) = (xhat[i], z[i], sig[i]);
                    let dz = dy_row[i] * s * (T::ONE + z * (T::ONE - s));
                    dgamma[i] += dz * xh;
                    dbeta[i] += dz;
                    dxhat[i] = dz * gamma[i];
                    sum_dxhat += dxhat[i];
                    sum_dxhat_xhat += dxhat[i] * xh;
                }
                let n = T::from_usize(c);
                let (m1, m2) = (sum_dxhat / n, sum_dxhat_xhat / n);
                for i in 0..c {
                    dx_row[i] = rstd * (dxhat[i] - m1 - xhat[i] * m2);
                }
            }
            (dgamma, dbeta)
        })
        .collect();
    // Sum the per-task partials in task order (deterministic).
    let mut dgamma = vec![T::ZERO; c];
    let mut dbeta = vec![T::ZERO; c];
    for (g, b) in partials {
        for i in 0..c {
            dgamma[i] += g[i];
            dbeta[i] += b[i];
        }
    }
    (dx, dgamma, dbeta)
}

impl candle_core::CustomOp3 for LayerNormSilu {
    fn name(&self) -> &'static str {
        "layer-norm-silu"
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
        let c = l2.shape().elem_count();
        if l1.shape().dims().last() != Some(&c) || l3.shape().elem_count() != c {
            candle_core::bail!("layer-norm-silu: x {:?}, gamma {:?}, beta {:?}", l1.shape(), l2.shape(), l3.shape())
        }
        let out = match (s1, s2, s3) {
            (CpuStorage::F32(x), CpuStorage::F32(g), CpuStorage::F32(b)) => CpuStorage::F32(layer_norm_silu_fwd(
                contiguous_slice(x, l1, "layer-norm-silu")?,
                contiguous_slice(g, l2, "layer-norm-silu")?,
                contiguous_slice(b, l3, "layer-norm-silu")?,
                self.eps,
            )),
            (CpuStorage::F64(x), CpuStorage::F64(g), CpuStorage::F64(b)) => CpuStorage::F64(layer_norm_silu_fwd(
                contiguous_slice(x, l1, "layer-norm-silu")?,
                contiguous_slice(g, l2, "layer-norm-silu")?,
                contiguous_slice(b, l3, "layer-norm-silu")?,
                self.eps,
            )),
            _ => candle_core::bail!("layer-norm-silu: x, gamma, beta must all be f32 (or all f64)"),
        };
        Ok((out, l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        gamma: &Tensor,
        beta: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        fn run<T: NormScalar + candle_core::WithDType>(
            x: &Tensor,
            gamma: &Tensor,
            beta: &Tensor,
            dy: &Tensor,
            eps: f64,
        ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
            let xs = x.flatten_all()?.to_vec1::<T>()?;
            let gs = gamma.flatten_all()?.to_vec1::<T>()?;
            let bs = beta.flatten_all()?.to_vec1::<T>()?;
            let dys = dy.flatten_all()?.to_vec1::<T>()?;
            let (dx, dg, db) = layer_norm_silu_bwd(&xs, &gs, &bs, &dys, eps);
            Ok((
                Some(Tensor::from_vec(dx, x.shape(), x.device())?),
                Some(Tensor::from_vec(dg, gamma.shape(), gamma.device())?),
                Some(Tensor::from_vec(db, beta.shape(), beta.device())?),
            ))
        }
        match x.dtype() {
            DType::F32 => run::<f32>(x, gamma, beta, grad_res, self.eps),
            DType::F64 => run::<f64>(x, gamma, beta, grad_res, self.eps),
            other => candle_core::bail!("layer-norm-silu backward: unsupported dtype {other:?}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    #[test]
    fn col2im_is_the_adjoint_of_im2col() {
        // <im2col(x), y> == <x, col2im(y)> for random x, y: the backward is right.
        let dev = Device::Cpu;
        for win in [
            Window { kernel: 3, stride: 1, padding: 1 },
            Window { kernel: 3, stride: 2, padding: 1 },
            Window { kernel: 2, stride: 2, padding: 0 },
        ] {
            let dims = (2, 7, 6, 4);
            let x = Var::from_tensor(&Tensor::randn(0f64, 1.0, dims, &dev).unwrap()).unwrap();
            let cols = x.as_tensor().apply_op1(Im2Col(win)).unwrap();
            let y = Tensor::randn(0f64, 1.0, cols.shape(), &dev).unwrap();
            let lhs = (&cols * &y).unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap();
            let grads = (&cols * &y).unwrap().sum_all().unwrap().backward().unwrap();
            let gx = grads.get(&x).unwrap();
            let rhs = (x.as_tensor() * gx).unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap();
            assert!((lhs - rhs).abs() < 1e-9 * lhs.abs().max(1.0), "{win:?}: {lhs} vs {rhs}");
        }
    }

    #[test]
    fn fast_exp_is_accurate() {
        let mut worst = 0f64;
        for i in 0..=200_000 {
            let x = -87.0 + 175.0 * i as f32 / 200_000.0;
            let exact = (x as f64).exp();
            let rel = ((fast_exp_f32(x) as f64 - exact) / exact).abs();
            worst = worst.max(rel);
        }
        assert!(worst < 3e-7, "worst relative error {worst}");
        assert!(fast_exp_f32(-1000.0) >= 0.0 && fast_exp_f32(1000.0).is_finite());
    }

    #[test]
    fn fused_norm_silu_and_upsample_add_match_composed_ops() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f64, 2.0, (2, 4, 6, 5), &dev).unwrap();
        let gamma = Tensor::randn(1f64, 0.3, 5, &dev).unwrap();
        let beta = Tensor::randn(0f64, 0.3, 5, &dev).unwrap();
        let fused = x.apply_op3(&gamma, &beta, LayerNormSilu { eps: 1e-5 }).unwrap();
        let mean = x.mean_keepdim(3).unwrap();
        let centred = x.broadcast_sub(&mean).unwrap();
        let var = centred.sqr().unwrap().mean_keepdim(3).unwrap();
        let composed = centred
            .broadcast_div(&(var + 1e-5).unwrap().sqrt().unwrap())
            .unwrap()
            .broadcast_mul(&gamma)
            .unwrap()
            .broadcast_add(&beta)
            .unwrap()
            .silu()
            .unwrap();
        let diff = (fused - composed).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f64>().unwrap();
        assert!(diff < 1e-12, "norm-silu {diff}");

        let coarse = Tensor::randn(0f64, 1.0, (2, 2, 3, 5), &dev).unwrap();
        let fused = x.apply_op2(&coarse, AddUpsampled2).unwrap();
        let up = coarse
            .reshape((2, 2, 1, 3, 1, 5))
            .unwrap()
            .broadcast_as((2, 2, 2, 3, 2, 5))
            .unwrap()
            .reshape((2, 4, 6, 5))
            .unwrap();
        let diff = (fused - (&x + up).unwrap()).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f64>().unwrap();
        assert_eq!(diff, 0.0);
    }

    #[test]
    fn fused_bias_add_and_its_gradient_match_the_broadcast_add() {
        let dev = Device::Cpu;
        let c = 5;
        // more rows than one parallel block with a partial last block; one row; no rows
        for (dtype, rows, tolerance) in [
            (DType::F64, 3 * BIAS_ROWS_PER_TASK + 17, 1e-9),
            (DType::F32, 3 * BIAS_ROWS_PER_TASK + 17, 1e-3),
            (DType::F32, 1, 1e-6),
            (DType::F32, 0, 0.0), // forward only
        ] {
            let randn = |shape: &[usize]| Tensor::randn(0f64, 1.0, shape, &dev).unwrap().to_dtype(dtype).unwrap();
            let x = Var::from_tensor(&randn(&[rows, c])).unwrap();
            let b = Var::from_tensor(&randn(&[c])).unwrap();
            let w = randn(&[rows, c]);
            let max_abs = |t: Tensor| {
                t.abs()
                    .unwrap()
                    .flatten_all()
                    .unwrap()
                    .to_dtype(DType::F64)
                    .unwrap()
                    .to_vec1::<f64>()
                    .unwrap()
                    .into_iter()
                    .fold(0.0, f64::max)
            };
            let fused = x.as_tensor().apply_op2(b.as_tensor(), AddBias).unwrap();
            let composed = x.as_tensor().broadcast_add(b.as_tensor()).unwrap();
            assert_eq!(fused.dims(), [rows, c]);
            assert_eq!(max_abs((&fused - &composed).unwrap()), 0.0, "{dtype:?}, {rows} rows: forward");
            if rows == 0 {
                continue; // candle returns no gradients for these empty tensors
            }
            let g_fused = (fused * &w).unwrap().sum_all().unwrap().backward().unwrap();
            let g_composed = (composed * &w).unwrap().sum_all().unwrap().backward().unwrap();
            for var in [&x, &b] {
                let (a, e) = (g_fused.get(var).unwrap(), g_composed.get(var).unwrap());
                let diff = max_abs((a - e).unwrap());
                assert!(diff <= tolerance, "{dtype:?}, {rows} rows: gradient differs by {diff}");
            }
            // the bias gradient is the column sum of the upstream gradient
            let expected = w.sum(0).unwrap();
            let diff = max_abs((g_fused.get(&b).unwrap() - expected).unwrap());
            assert!(diff <= tolerance, "{dtype:?}, {rows} rows: bias gradient off by {diff}");
        }
        // a bias of the wrong length, or a non-contiguous x, is an error, not a panic
        let x = Tensor::randn(0f64, 1.0, (4, 5), &dev).unwrap();
        let short = Tensor::zeros(4, DType::F64, &dev).unwrap();
        assert!(x.apply_op2(&short, AddBias).is_err());
        let bias = Tensor::zeros(4, DType::F64, &dev).unwrap();
        assert!(x.t().unwrap().apply_op2(&bias, AddBias).is_err());
    }
}
