//! Sinusoidal encodings: the 3D positional encoding of token positions (normalised workspace
//! coordinates) and the flow-time embedding.
use std::f32::consts::PI;

use candle_core::{D, DType, Tensor};

use crate::policy::error::{PolicyError, Result};

pub const POSITIONAL_OCTAVES: f32 = 6.0;

/// The frequencies (radians per normalised unit) of [`positional_encoding`] for `per_axis`
/// frequencies: `omega_k = pi * 2^(k * 6 / (F - 1) - 1)`, k = 0..F-1, geometric from pi/2 to
/// 32 pi (`[pi / 2]` when F = 1).
pub fn positional_frequencies(per_axis: usize) -> Vec<f32> {
    (0..per_axis)
        .map(|k| {
            let step = if per_axis > 1 { POSITIONAL_OCTAVES / (per_axis - 1) as f32 } else { 0.0 };
            PI * (k as f32 * step - 1.0).exp2()
        })
        .collect()
}

/// Sinusoidal (Fourier-feature) encoding of normalised positions: `xyz` `[.., 3]` ->
/// `[.., channels]`, same dtype and device.
///
/// Channel layout: `channels = 6 F` (F = channels / 6 frequencies per axis, 20 for C = 120),
/// three blocks of `2 F` for x, y, z; each block is `sin(omega_0 a) .. sin(omega_{F-1} a)`
/// then `cos(omega_0 a) .. cos(omega_{F-1} a)` with the frequencies of
/// [`positional_frequencies`].
///
/// Positions are data (point cloud, noisy action), so no gradient flows back to `xyz` (it is
/// detached). CPU f32 tensors take a fused kernel (branch-free sin/cos, accurate to about 1e-6
/// for |x| <= 100, where it switches to the standard library); other dtypes and devices use
/// candle ops.
///
/// Errors: [`PolicyError::Invalid`] when the last dimension is not 3 or `channels` is not a
/// positive multiple of 6.
pub fn positional_encoding(xyz: &Tensor, channels: usize) -> Result<Tensor> {
    if xyz.dims().last() != Some(&3) {
        return Err(PolicyError::Invalid(format!(
            "positional encoding expects positions [.., 3], got shape {:?}",
            xyz.dims()
        )));
    }
    if channels == 0 || !channels.is_multiple_of(6) {
        return Err(PolicyError::Invalid(format!(
            "positional encoding channels must be a positive multiple of 6 (sin and cos per axis); got {channels}"
        )));
    }
    let per_axis = channels / 6;
    let xyz = xyz.detach();
    if xyz.device().is_cpu() && xyz.dtype() == DType::F32 {
        let positions = xyz.flatten_all()?.to_vec1::<f32>()?;
        let mut shape = xyz.dims().to_vec();
        if let Some(last) = shape.last_mut() {
            *last = channels;
        }
        let encoded = encode_positions(&positions, per_axis);
        return Ok(Tensor::from_vec(encoded, shape, xyz.device())?);
    }
    let freqs = Tensor::new(positional_frequencies(per_axis), xyz.device())?.to_dtype(xyz.dtype())?;
    let angles = xyz.unsqueeze(D::Minus1)?.broadcast_mul(&freqs)?; // [.., 3, F]
    let features = Tensor::cat(&[angles.sin()?, angles.cos()?], D::Minus1)?; // [.., 3, 2F]
    Ok(features.flatten_from(features.rank() - 2)?)
}

/// The CPU kernel of [`positional_encoding`]: `positions` (3 per point) -> `6 F` per point.
fn encode_positions(positions: &[f32], per_axis: usize) -> Vec<f32> {
    let freqs = positional_frequencies(per_axis);
    let width = 2 * per_axis; // one axis block: F sines, F cosines
    let mut out = vec![0.0f32; positions.len() * width];
    let largest = positions.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let fast = largest <= 100.0; // |angle| <= 100 * 32 pi: the reduction below stays exact enough
    let encode_block = |(block, &x): (&mut [f32], &f32)| {
        let (sines, cosines) = block.split_at_mut(per_axis);
        for ((s, c), w) in sines.iter_mut().zip(cosines.iter_mut()).zip(&freqs) {
            (*s, *c) = if fast { sin_cos(w * x) } else { (w * x).sin_cos() };
        }
    };
    const PARALLEL_MIN_VALUES: usize = 1 << 18;
    if out.len() >= PARALLEL_MIN_VALUES {
        use rayon::prelude::*;
        out.par_chunks_mut(width).zip(positions.par_iter()).with_min_len(1024).for_each(encode_block);
    } else {
        out.chunks_mut(width).zip(positions.iter()).for_each(encode_block);
    }
    out
}

/// `(sin a, cos a)` without branches (vectorisable): reduction by pi/2 (Cody-Waite, three
/// parts) and Cephes' single-precision polynomials on [-pi/4, pi/4]. Absolute error about 1e-7
/// for |a| up to a few thousand.
#[inline(always)]
fn sin_cos(a: f32) -> (f32, f32) {
    const FRAC_2_PI: f32 = std::f32::consts::FRAC_2_PI;
    const ROUND: f32 = 12_582_912.0; // 1.5 * 2^23: (v + ROUND) - ROUND rounds v to an integer
    let q = (a * FRAC_2_PI + ROUND) - ROUND;
    let r = ((a - q * 1.570_312_5) - q * 4.837_513e-4) - q * 7.549_79e-8;
    let r2 = r * r;
    let s = r + r * r2 * (-1.666_665_5e-1 + r2 * (8.332_161e-3 + r2 * -1.951_529_6e-4));
    let c = 1.0 - 0.5 * r2 + r2 * r2 * (4.166_664_6e-2 + r2 * (-1.388_731_6e-3 + r2 * 2.443_315_7e-5));
    let quadrant = (q as i32) & 3;
    let (s, c) = if quadrant & 1 != 0 { (c, s) } else { (s, c) };
    let sin = if quadrant & 2 != 0 { -s } else { s };
    let cos = if (quadrant + 1) & 2 != 0 { -c } else { c };
    (sin, cos)
}

/// Sinusoidal embedding of the flow time t in [0, 1] (as DiT, with t scaled by 1000):
/// [B] -> [B, C], half sines, half cosines, periods from 2 pi / 1000 to 2 pi * 10.
pub fn time_embedding(t: &Tensor, channels: usize) -> Result<Tensor> {
    if !channels.is_multiple_of(2) {
        return Err(PolicyError::Invalid(format!("time embedding needs an even width, got {channels}")));
    }
    let half = channels / 2;
    let freqs: Vec<f32> = (0..half).map(|k| (-(10_000f32.ln()) * k as f32 / half as f32).exp()).collect();
    let freqs = Tensor::from_vec(freqs, (1, half), t.device())?;
    let angles = t.to_dtype(DType::F32)?.affine(1000.0, 0.0)?.unsqueeze(1)?.broadcast_mul(&freqs)?;
    Ok(Tensor::cat(&[angles.sin()?, angles.cos()?], D::Minus1)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn branch_free_sin_cos_is_accurate() {
        let mut worst = 0.0f32;
        for k in -400_000..=400_000 {
            let a = k as f32 * 0.01 + 0.003; // [-4000, 4000]
            let (s, c) = sin_cos(a);
            let (s64, c64) = (a as f64).sin_cos();
            worst = worst.max((s as f64 - s64).abs() as f32).max((c as f64 - c64).abs() as f32);
        }
        assert!(worst < 1e-6, "largest error {worst}");
    }

    #[test]
    fn positional_encoding_layout() {
        let device = Device::Cpu;
        let xyz = Tensor::new(&[[[0.1f32, -0.5, 0.9], [1.0, 0.0, -1.0]], [[0.3, 0.3, 0.3], [-0.2, 0.7, 0.0]]], &device)
            .unwrap();
        let encoded = positional_encoding(&xyz, 120).unwrap();
        assert_eq!(encoded.dims(), &[2, 2, 120]);
        let values = encoded.to_vec3::<f32>().unwrap();
        let freqs = positional_frequencies(20);
        assert!((freqs[0] - PI / 2.0).abs() < 1e-6 && (freqs[19] - 32.0 * PI).abs() < 1e-4);
        let position = [0.1f32, -0.5, 0.9];
        for axis in 0..3 {
            for (k, w) in freqs.iter().enumerate() {
                let sin = values[0][0][axis * 40 + k];
                let cos = values[0][0][axis * 40 + 20 + k];
                assert!((sin - (w * position[axis]).sin()).abs() < 1e-5, "axis {axis} sin {k}");
                assert!((cos - (w * position[axis]).cos()).abs() < 1e-5, "axis {axis} cos {k}");
            }
        }
        assert_eq!(positional_encoding(&xyz, 6).unwrap().dims(), &[2, 2, 6]);
        // The fused CPU f32 kernel agrees with the candle-op path (taken for f64).
        let ops = positional_encoding(&xyz.to_dtype(candle_core::DType::F64).unwrap(), 120).unwrap();
        let diff = (ops.to_dtype(candle_core::DType::F32).unwrap() - &encoded).unwrap().abs().unwrap();
        let diff = diff.max_all().unwrap().to_scalar::<f32>().unwrap();
        // Rounding the angle w * x (up to 32 pi) in f32 rather than f64 alone costs a few 1e-6.
        assert!(diff < 1e-5, "fused kernel vs candle ops: {diff}");
        // Large coordinates take the standard library's sin/cos.
        let far = Tensor::new(&[[150.0f32, -1.0, 0.0]], &device).unwrap();
        let far_encoded = positional_encoding(&far, 12).unwrap().to_vec2::<f32>().unwrap();
        assert!((far_encoded[0][1] - (positional_frequencies(2)[1] * 150.0).sin()).abs() < 1e-6);
        assert!(positional_encoding(&xyz, 100).is_err());
        assert!(positional_encoding(&Tensor::zeros((4, 2), candle_core::DType::F32, &device).unwrap(), 120).is_err());
    }
}
