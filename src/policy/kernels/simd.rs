//! CPU plumbing shared by the custom candle ops of the Mamba layers: branch-free
//! `exp`/`softplus`/`sigmoid` written so that LLVM turns loops over `[f32; LANES]`
//! into SIMD, run-time selection of AVX-512 / AVX2+FMA builds of each kernel
//! (the crate is compiled for baseline x86-64, so without this every kernel
//! would be SSE2-only), typed access to candle CPU storage and strided views.
//!
//! Accuracy: `exp` is within 2 ulp on [-87.3, 88.3] (arguments outside are
//! clamped, so `exp(-1000) = 1.2e-38`, not 0); `softplus` and `sigmoid` are
//! within a few ulp. Everything is f32.

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, Layout, Storage, Tensor};
use std::sync::OnceLock;

/// Width of the lane arrays the kernels work on (one AVX-512 register of f32).
pub const LANES: usize = 16;
/// One group of [`LANES`] channels.
pub type Lanes = [f32; LANES];

/// Which build of the kernels runs on this machine.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimdLevel {
    /// AVX-512F (+VL) with FMA: 16 f32 per instruction.
    Avx512,
    /// AVX2 with FMA: 8 f32 per instruction.
    Avx2Fma,
    /// Whatever the compile target allows (SSE2 on x86-64), no FMA.
    Portable,
}

/// The SIMD level the kernels use: the best the CPU supports, or the one named
/// by the environment variable `POLICY_SIMD` (`avx512`, `avx2`, `portable`),
/// read once, for comparing builds. A request the CPU cannot honour falls back
/// to the best supported level.
pub fn simd_level() -> SimdLevel {
    static LEVEL: OnceLock<SimdLevel> = OnceLock::new();
    *LEVEL.get_or_init(|| {
        let supported = detect_simd();
        let rank = |l: SimdLevel| match l {
            SimdLevel::Portable => 0,
            SimdLevel::Avx2Fma => 1,
            SimdLevel::Avx512 => 2,
        };
        let requested = match std::env::var("POLICY_SIMD").as_deref() {
            Ok("avx512") => Some(SimdLevel::Avx512),
            Ok("avx2") => Some(SimdLevel::Avx2Fma),
            Ok("portable") => Some(SimdLevel::Portable),
            _ => None,
        };
        match requested {
            Some(r) if rank(r) <= rank(supported) => r,
            _ => supported,
        }
    })
}

fn detect_simd() -> SimdLevel {
    #[cfg(target_arch = "x86_64")]
    {
        let fma = is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma");
        if fma && is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512vl") {
            return SimdLevel::Avx512;
        }
        if fma {
            return SimdLevel::Avx2Fma;
        }
    }
    SimdLevel::Portable
}

/// Defines a kernel function compiled three times (AVX-512, AVX2+FMA, portable)
/// and dispatched at run time on [`simd_level`]. The body sees a `const $fma:
/// bool` telling whether fused multiply-add is cheap (pass it to [`madd`] and
/// the math functions). Call it from inside rayon tasks, not around them: a
/// closure handed to rayon is compiled without the target features.
macro_rules! simd_kernel {
    ($(#[$meta:meta])* $vis:vis fn $name:ident<$fma:ident>($($arg:ident : $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$meta])*
        #[allow(clippy::too_many_arguments)]
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            #[allow(clippy::too_many_arguments)]
            fn body<const $fma: bool>($($arg: $ty),*) $(-> $ret)? $body

            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
            #[allow(clippy::too_many_arguments)]
            unsafe fn avx512($($arg: $ty),*) $(-> $ret)? { body::<true>($($arg),*) }

            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            #[allow(clippy::too_many_arguments)]
            unsafe fn avx2($($arg: $ty),*) $(-> $ret)? { body::<true>($($arg),*) }

            match $crate::policy::kernels::simd::simd_level() {
                // SAFETY: simd_level() only reports levels the CPU supports.
                #[cfg(target_arch = "x86_64")]
                $crate::policy::kernels::simd::SimdLevel::Avx512 => unsafe { avx512($($arg),*) },
                #[cfg(target_arch = "x86_64")]
                $crate::policy::kernels::simd::SimdLevel::Avx2Fma => unsafe { avx2($($arg),*) },
                _ => body::<false>($($arg),*),
            }
        }
    };
}
pub(crate) use simd_kernel;

/// `a * b + c`, fused when `FMA` (the caller's build has cheap FMA).
#[inline(always)]
pub fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA { a.mul_add(b, c) } else { a * b + c }
}

const EXP_LOG2E: f32 = std::f32::consts::LOG2_E;
const EXP_LN2_HI: f32 = 0.693_359_4; // 0.693359375, exact in few bits
const EXP_LN2_LO: f32 = -2.121_944_4e-4;
const EXP_SHIFTER: f32 = 12_582_912.0; // 1.5 * 2^23: adding it rounds to an integer
const EXP_MIN: f32 = -87.3;
const EXP_MAX: f32 = 88.3;
const EXP_POLY: [f32; 6] = [1.987_569_1e-4, 1.398_199_9e-3, 8.333_452e-3, 4.166_579_6e-2, 1.666_666_5e-1, 0.5];

/// e^x, branch-free (Cody-Waite reduction, cephes polynomial), 2 ulp.
/// Arguments are clamped to [-87.3, 88.3].
#[inline(always)]
pub fn exp<const FMA: bool>(x: f32) -> f32 {
    let x = x.clamp(EXP_MIN, EXP_MAX);
    let shifted = madd::<FMA>(x, EXP_LOG2E, EXP_SHIFTER);
    let k_int = shifted.to_bits() as i32 - EXP_SHIFTER.to_bits() as i32;
    let k = shifted - EXP_SHIFTER;
    let r = madd::<FMA>(k, -EXP_LN2_LO, madd::<FMA>(k, -EXP_LN2_HI, x));
    let mut p = EXP_POLY[0];
    for &c in &EXP_POLY[1..] {
        p = madd::<FMA>(p, r, c);
    }
    (madd::<FMA>(p, r * r, r) + 1.0) * f32::from_bits(((k_int + 127) << 23) as u32)
}

/// `base + ln(1 + e)` for e in (0, 1], as 2 atanh(s), s = e / (2 + e).
#[inline(always)]
fn log1p_atanh<const FMA: bool>(e: f32, base: f32) -> f32 {
    let s = e / (2.0 + e);
    let s2 = s * s;
    let mut p = 1.0 / 13.0;
    for c in [1.0 / 11.0, 1.0 / 9.0, 1.0 / 7.0, 1.0 / 5.0, 1.0 / 3.0, 1.0] {
        p = madd::<FMA>(p, s2, c);
    }
    madd::<FMA>(2.0 * s, p, base)
}

/// softplus(x) = ln(1 + e^x) = max(x, 0) + ln(1 + e^-|x|), with the last term as
/// 2 atanh(s), s = e/(2+e), so it stays accurate when e^-|x| is tiny.
#[inline(always)]
pub fn softplus<const FMA: bool>(x: f32) -> f32 {
    log1p_atanh::<FMA>(exp::<FMA>(-x.abs()), x.max(0.0))
}

/// e^x of `G` independent values, one stage at a time over all of them, so
/// that `G` dependency chains are in flight together. Call it inside a loop
/// over the lanes of a lane group: the loop vectoriser then turns every
/// scalar operation into one vector instruction (one exp alone is a ~15-deep
/// chain of 4-cycle operations and leaves the FP units mostly idle).
#[inline(always)]
pub fn exp_interleaved<const FMA: bool, const G: usize>(x: &mut [f32; G]) {
    let mut scale = [0f32; G];
    for j in 0..G {
        let v = x[j].clamp(EXP_MIN, EXP_MAX);
        let shifted = madd::<FMA>(v, EXP_LOG2E, EXP_SHIFTER);
        let k_int = shifted.to_bits() as i32 - EXP_SHIFTER.to_bits() as i32;
        scale[j] = f32::from_bits(((k_int + 127) << 23) as u32);
        let k = shifted - EXP_SHIFTER;
        x[j] = madd::<FMA>(k, -EXP_LN2_LO, madd::<FMA>(k, -EXP_LN2_HI, v));
    }
    let mut p = [EXP_POLY[0]; G];
    for &c in &EXP_POLY[1..] {
        for j in 0..G {
            p[j] = madd::<FMA>(p[j], x[j], c);
        }
    }
    for j in 0..G {
        x[j] = (madd::<FMA>(p[j], x[j] * x[j], x[j]) + 1.0) * scale[j];
    }
}

/// softplus of `G` independent values, stage by stage (see [`exp_interleaved`]).
#[inline(always)]
pub fn softplus_interleaved<const FMA: bool, const G: usize>(x: &mut [f32; G]) {
    let mut e = [0f32; G];
    for j in 0..G {
        e[j] = -x[j].abs();
    }
    exp_interleaved::<FMA, G>(&mut e);
    for j in 0..G {
        x[j] = log1p_atanh::<FMA>(e[j], x[j].max(0.0));
    }
}

/// sigmoid(x) = 1 / (1 + e^-x), the derivative of softplus.
#[inline(always)]
pub fn sigmoid<const FMA: bool>(x: f32) -> f32 {
    1.0 / (1.0 + exp::<FMA>(-x))
}

/// SiLU(x) = x * sigmoid(x).
#[inline(always)]
pub fn silu<const FMA: bool>(x: f32) -> f32 {
    x * sigmoid::<FMA>(x)
}

/// d SiLU / dx = s (1 + x (1 - s)), s = sigmoid(x).
#[inline(always)]
pub fn silu_grad<const FMA: bool>(x: f32) -> f32 {
    let s = sigmoid::<FMA>(x);
    s * madd::<FMA>(x, 1.0 - s, 1.0)
}

/// Sum of the lanes, as a fixed tree (vectorisable, unlike a sequential sum).
#[inline(always)]
pub fn lane_sum(v: &Lanes) -> f32 {
    let mut s8 = [0.0f32; 8];
    for k in 0..8 {
        s8[k] = v[k] + v[k + 8];
    }
    let mut s4 = [0.0f32; 4];
    for k in 0..4 {
        s4[k] = s8[k] + s8[k + 4];
    }
    (s4[0] + s4[2]) + (s4[1] + s4[3])
}

/// `width` values of `src` from `start`, padded with zeros to [`LANES`].
/// The full-width case is a fixed 64-byte load (written so that LLVM does not
/// merge it with the partial case into a variable-length `memcpy` call).
#[inline(always)]
pub fn load_lanes(src: &[f32], start: usize, width: usize) -> Lanes {
    if width == LANES {
        let full: &Lanes = src[start..start + LANES].try_into().unwrap_or(&[0.0; LANES]);
        *full
    } else {
        let mut v = [0.0f32; LANES];
        for (k, x) in src[start..start + width].iter().enumerate() {
            v[k & (LANES - 1)] = *x;
        }
        v
    }
}

/// Applies `f` to every element of `xs` in place, [`LANES`] at a time.
#[inline(always)]
pub fn map_in_place(xs: &mut [f32], f: impl Fn(f32) -> f32) {
    let mut chunks = xs.chunks_exact_mut(LANES);
    for chunk in &mut chunks {
        let mut v: Lanes = [0.0; LANES];
        v.copy_from_slice(chunk);
        for x in v.iter_mut() {
            *x = f(*x);
        }
        chunk.copy_from_slice(&v);
    }
    for x in chunks.into_remainder() {
        *x = f(*x);
    }
}

/// The f32 data of a CPU storage, or an error naming `what` for other dtypes.
pub(crate) fn f32_data<'a>(s: &'a CpuStorage, what: &str) -> candle_core::Result<&'a [f32]> {
    match s {
        CpuStorage::F32(v) => Ok(v.as_slice()),
        other => candle_core::bail!("{what}: expected f32 data, got {:?}", other.dtype()),
    }
}

/// The `elem_count` elements of a contiguous tensor layout, or an error.
pub(crate) fn contiguous_data<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> candle_core::Result<&'a [f32]> {
    let data = f32_data(s, what)?;
    match l.contiguous_offsets() {
        Some((start, end)) => Ok(&data[start..end]),
        None => candle_core::bail!("{what}: expected a contiguous tensor, got layout {l:?}"),
    }
}

/// Runs `f` on the contiguous f32 data of a tensor captured by an op (for
/// inputs beyond a custom op's three arguments). The tensor must live on the CPU.
pub(crate) fn with_captured<R>(
    t: &Tensor,
    what: &str,
    f: impl FnOnce(&[f32]) -> candle_core::Result<R>,
) -> candle_core::Result<R> {
    let (storage, layout) = t.storage_and_layout();
    match &*storage {
        Storage::Cpu(cpu) => f(contiguous_data(cpu, layout, what)?),
        _ => candle_core::bail!("{what}: expected a CPU tensor"),
    }
}

/// A rank-3 tensor `[d0, d1, d2]` whose last dimension is contiguous, with any
/// strides (including 0, for broadcasts) on the first two.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RowView {
    pub dims: [usize; 3],
    offset: usize,
    strides: [usize; 2],
}

impl RowView {
    pub fn new(l: &Layout, what: &str) -> candle_core::Result<Self> {
        let (dims, strides) = (l.dims(), l.stride());
        if dims.len() != 3 || (strides[2] != 1 && dims[2] > 1) {
            candle_core::bail!("{what}: expected a rank-3 tensor with a contiguous last dimension, got {l:?}")
        }
        Ok(Self { dims: [dims[0], dims[1], dims[2]], offset: l.start_offset(), strides: [strides[0], strides[1]] })
    }

    /// Start of row (i0, i1) in the storage.
    #[inline(always)]
    pub fn row(&self, i0: usize, i1: usize) -> usize {
        self.offset + i0 * self.strides[0] + i1 * self.strides[1]
    }

    /// Row (i0, i1) as a slice of `data`.
    #[inline(always)]
    pub fn slice<'a>(&self, data: &'a [f32], i0: usize, i1: usize) -> &'a [f32] {
        let start = self.row(i0, i1);
        &data[start..start + self.dims[2]]
    }
}

/// A shared handle to an output buffer that several rayon tasks fill at
/// disjoint indices (e.g. the channel groups of one token row).
#[derive(Clone, Copy)]
pub(crate) struct DisjointWriter {
    ptr: *mut f32,
    len: usize,
}

// SAFETY: the handle is only used to write disjoint index sets from different
// threads while the owning buffer is alive (see `write_slice`).
unsafe impl Send for DisjointWriter {}
unsafe impl Sync for DisjointWriter {}

impl DisjointWriter {
    pub fn new(buffer: &mut [f32]) -> Self {
        Self { ptr: buffer.as_mut_ptr(), len: buffer.len() }
    }

    /// Writes `values` at `start..start + values.len()`.
    ///
    /// # Safety
    /// The buffer this was made from must outlive the call and must not be
    /// accessed otherwise meanwhile, and no two concurrent calls may write the
    /// same index.
    #[inline(always)]
    pub unsafe fn write_slice(&self, start: usize, values: &[f32]) {
        assert!(start + values.len() <= self.len, "DisjointWriter: write out of bounds");
        if values.len() == LANES {
            // a fixed-size copy compiles to one vector store instead of a memcpy call
            let lanes: &Lanes = values.try_into().unwrap_or(&[0.0; LANES]);
            unsafe { std::ptr::write_unaligned(self.ptr.add(start) as *mut Lanes, *lanes) };
        } else {
            unsafe { std::ptr::copy_nonoverlapping(values.as_ptr(), self.ptr.add(start), values.len()) };
        }
    }

    /// Writes one value at `index`. Same contract as [`Self::write_slice`].
    #[inline(always)]
    pub unsafe fn write(&self, index: usize, value: f32) {
        assert!(index < self.len, "DisjointWriter: write out of bounds");
        unsafe { *self.ptr.add(index) = value };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    simd_kernel! {
        fn apply_all<FMA>(xs: &[f32], out: &mut [f32], which: u8) {
            for (o, &x) in out.iter_mut().zip(xs) {
                *o = match which {
                    0 => exp::<FMA>(x),
                    1 => softplus::<FMA>(x),
                    _ => sigmoid::<FMA>(x),
                };
            }
        }
    }

    #[test]
    fn math_matches_libm() {
        let xs: Vec<f32> = (0..20001).map(|i| -100.0 + i as f32 * 0.01).collect();
        let mut out = vec![0.0; xs.len()];
        apply_all(&xs, &mut out, 0);
        for (&x, &e) in xs.iter().zip(&out) {
            let r = (x as f64).exp();
            if x > -87.0 && x < 88.0 {
                assert!(((e as f64 - r) / r).abs() < 3e-7, "exp({x}) = {e}, libm {r}");
            }
        }
        apply_all(&xs, &mut out, 1);
        for (&x, &s) in xs.iter().zip(&out) {
            let r = (x as f64).exp().ln_1p();
            if x > -87.0 {
                assert!(((s as f64 - r) / r).abs() < 1e-6, "softplus({x}) = {s}, ref {r}");
            }
        }
        apply_all(&xs, &mut out, 2);
        for (&x, &s) in xs.iter().zip(&out) {
            let r = 1.0 / (1.0 + (-x as f64).exp());
            assert!((s as f64 - r).abs() < 1e-6 * r.max(1e-30) + 1e-38, "sigmoid({x}) = {s}, ref {r}");
        }
        let lanes: Lanes = std::array::from_fn(|k| k as f32);
        assert_eq!(lane_sum(&lanes), 120.0);
    }
}
