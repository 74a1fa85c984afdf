//! Rotation representations of the action: matrices, quaternions and the continuous 6D form.
//!
//! Conventions:
//! - Rotation matrices are `[[f32; 3]; 3]` indexed `m[row][col]`, mapping body to world
//!   (columns are the body axes in the world frame). Quaternions are `[w, x, y, z]`, unit,
//!   canonical with `w >= 0`.
//! - The 6D rotation (Zhou et al., CVPR 2019) is the first two columns of the matrix,
//!   `[m00, m10, m20, m01, m11, m21]`, as in 3D Diffuser Actor.
use crate::policy::error::{PolicyError, Result};

/// A rotation matrix, `m[row][col]`.
pub type RotationMatrix = [[f32; 3]; 3];

/// Rotation matrix of the quaternion `q = [w, x, y, z]` (normalised first, so any non-zero
/// scaling of a unit quaternion gives the same rotation).
///
/// Errors: [`PolicyError::Invalid`] when `q` has a non-finite entry or (nearly) zero norm.
pub fn matrix_from_quaternion(q: [f32; 4]) -> Result<RotationMatrix> {
    let q64 = q.map(f64::from);
    let norm = q64.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !norm.is_finite() || norm < 1e-12 {
        return Err(PolicyError::Invalid(format!(
            "quaternion [w, x, y, z] = {q:?} has norm {norm}: expected a finite, non-zero quaternion"
        )));
    }
    let [w, x, y, z] = q64.map(|v| v / norm);
    let m = [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ];
    Ok(m.map(|row| row.map(|v| v as f32)))
}

/// Canonical unit quaternion `[w, x, y, z]` (`w >= 0`; when `w == 0`, the first non-zero of
/// x, y, z is positive) of a rotation matrix (Shepperd's method). `m` should be a rotation; pass
/// anything else through [`rotation_from_6d`] first. Never returns NaN for finite input.
pub fn quaternion_from_matrix(m: &RotationMatrix) -> [f32; 4] {
    let m = m.map(|row| row.map(f64::from));
    let trace = m[0][0] + m[1][1] + m[2][2];
    let q = if trace > 0.0 {
        let s = (trace + 1.0).sqrt() * 2.0; // 4w
        [0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).max(1e-300).sqrt() * 2.0; // 4x
        [(m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).max(1e-300).sqrt() * 2.0; // 4y
        [(m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).max(1e-300).sqrt() * 2.0; // 4z
        [(m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s]
    };
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !norm.is_finite() || norm == 0.0 {
        return [1.0, 0.0, 0.0, 0.0];
    }
    let mut q = q.map(|v| v / norm);
    let first_nonzero = q.iter().copied().find(|v| *v != 0.0).unwrap_or(1.0);
    if first_nonzero < 0.0 {
        q = q.map(|v| -v);
    }
    q.map(|v| v as f32)
}

/// The 6D representation: first column then second column of `m`,
/// `[m00, m10, m20, m01, m11, m21]`.
pub fn rotation_to_6d(m: &RotationMatrix) -> [f32; 6] {
    [m[0][0], m[1][0], m[2][0], m[0][1], m[1][1], m[2][1]]
}

/// A proper rotation from any 6D vector by Gram-Schmidt (Zhou et al.): `b1 = a1 / |a1|`,
/// `b2 = normalise(a2 - (b1 . a2) b1)`, `b3 = b1 x b2`, columns `[b1 b2 b3]`. Computed in f64.
///
/// Never returns NaN; always orthonormal with det = +1. Deterministic fallbacks for degenerate
/// input (non-finite entries are first replaced by 0):
/// - `|a1| <= 1e-12`: `b1 = e_x`;
/// - `a2` (nearly) parallel to `b1` or zero (`|a2 - (b1 . a2) b1| <= 1e-6 |a2|` or `<= 1e-12`):
///   `b2` is Gram-Schmidt of the world axis `e_k` least aligned with `b1` (smallest `|b1_k|`,
///   lowest k on ties).
///
/// So all zeros give the identity, and `[1, 0, 0, 1, 0, 0]` gives the identity too.
pub fn rotation_from_6d(r: [f32; 6]) -> RotationMatrix {
    let clean = r.map(|v| if v.is_finite() { f64::from(v) } else { 0.0 });
    let a1 = [clean[0], clean[1], clean[2]];
    let a2 = [clean[3], clean[4], clean[5]];
    // f32 inputs cannot overflow or underflow squared in f64, so no rescaling is needed.
    let b1 = normalised(a1).unwrap_or([1.0, 0.0, 0.0]);
    let b2 = {
        let residual = sub64(a2, scale64(b1, dot64(b1, a2)));
        match normalised(residual) {
            Some(b2) if norm64(residual) > 1e-6 * norm64(a2) => b2,
            _ => {
                let k = (0..3).min_by(|&i, &j| b1[i].abs().total_cmp(&b1[j].abs())).unwrap_or(0);
                let mut axis = [0.0; 3];
                axis[k] = 1.0;
                // |b1_k| <= 1/sqrt(3), so this residual has norm >= sqrt(2/3).
                normalised(sub64(axis, scale64(b1, b1[k]))).unwrap_or([0.0, 1.0, 0.0])
            }
        }
    };
    let b3 = normalised(cross64(b1, b2)).unwrap_or([0.0, 0.0, 1.0]);
    let m = [[b1[0], b2[0], b3[0]], [b1[1], b2[1], b3[1]], [b1[2], b2[2], b3[2]]];
    m.map(|row| row.map(|v| v as f32))
}

/// `rotation_to_6d(matrix_from_quaternion(q))`.
pub fn quaternion_to_6d(q: [f32; 4]) -> Result<[f32; 6]> {
    Ok(rotation_to_6d(&matrix_from_quaternion(q)?))
}

/// `quaternion_from_matrix(rotation_from_6d(r))`: canonical quaternion of any 6D vector.
pub fn quaternion_from_6d(r: [f32; 6]) -> [f32; 4] {
    quaternion_from_matrix(&rotation_from_6d(r))
}

fn dot64(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn sub64(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn scale64(a: [f64; 3], s: f64) -> [f64; 3] {
    a.map(|v| v * s)
}
fn cross64(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
fn norm64(a: [f64; 3]) -> f64 {
    dot64(a, a).sqrt()
}
/// `a / |a|`, or None when `|a| <= 1e-12`.
fn normalised(a: [f64; 3]) -> Option<[f64; 3]> {
    let n = norm64(a);
    if n > 1e-12 && n.is_finite() { Some(a.map(|v| v / n)) } else { None }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_quaternion(rng: &mut ChaCha8Rng) -> [f32; 4] {
        loop {
            let q: [f32; 4] = std::array::from_fn(|_| rng.random_range(-1.0f32..1.0));
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            if n > 0.1 && n <= 1.0 {
                return q.map(|v| v / n);
            }
        }
    }

    fn canonical(q: [f32; 4]) -> [f32; 4] {
        if q[0] < 0.0 { q.map(|v| -v) } else { q }
    }

    fn assert_close<const N: usize>(a: [f32; N], b: [f32; N], tol: f32, what: &str) {
        for i in 0..N {
            assert!((a[i] - b[i]).abs() <= tol, "{what}: {a:?} vs {b:?}");
        }
    }

    fn assert_proper_rotation(m: &RotationMatrix, what: &str) {
        for i in 0..3 {
            for j in 0..3 {
                assert!(m[i][j].is_finite(), "{what}: NaN/inf in {m:?}");
                let dot: f32 = (0..3).map(|k| m[k][i] * m[k][j]).sum();
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((dot - want).abs() < 1e-5, "{what}: columns {i},{j} dot {dot} in {m:?}");
            }
        }
        let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
        assert!((det - 1.0).abs() < 1e-5, "{what}: det {det} of {m:?}");
    }

    #[test]
    fn rotation_round_trips() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut quaternions: Vec<[f32; 4]> = (0..2000).map(|_| random_quaternion(&mut rng)).collect();
        // Half-turns and near half-turns exercise every branch of Shepperd's method.
        quaternions.extend([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0], [1e-4, 0.7, 0.7, 0.1]]);
        for q in quaternions {
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            let q = q.map(|v| v / n);
            let m = matrix_from_quaternion(q).unwrap();
            assert_proper_rotation(&m, "from quaternion");
            let back = quaternion_from_matrix(&m);
            assert!(back[0] >= 0.0);
            // q and -q are the same rotation; compare the canonical forms (w = 0 ties aside).
            let same = (0..4).all(|i| (back[i] - canonical(q)[i]).abs() < 1e-5)
                || (q[0].abs() < 1e-5 && (0..4).all(|i| (back[i] + canonical(q)[i]).abs() < 1e-5));
            assert!(same, "quaternion {q:?} -> {back:?}");
            let m6 = rotation_from_6d(rotation_to_6d(&m));
            for r in 0..3 {
                assert_close(m6[r], m[r], 1e-5, "matrix -> 6D -> matrix");
            }
            let q6 = quaternion_from_6d(quaternion_to_6d(q).unwrap());
            assert_close(
                rotation_to_6d(&matrix_from_quaternion(q6).unwrap()),
                rotation_to_6d(&m),
                1e-5,
                "q -> 6D -> q",
            );
        }
    }

    #[test]
    fn known_rotation_and_6d_layout() {
        let h = 0.5f32.sqrt();
        let m = matrix_from_quaternion([h, 0.0, 0.0, h]).unwrap(); // +90 deg about z
        let want = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        for r in 0..3 {
            assert_close(m[r], want[r], 1e-6, "90 deg about z");
        }
        assert_close(rotation_to_6d(&m), [0.0, 1.0, 0.0, -1.0, 0.0, 0.0], 1e-6, "6D = first two columns");
        assert_close(quaternion_from_matrix(&m), [h, 0.0, 0.0, h], 1e-6, "back");
        // Scaling does not matter; zero and NaN quaternions are refused.
        assert_close(matrix_from_quaternion([2.0 * h, 0.0, 0.0, 2.0 * h]).unwrap()[0], want[0], 1e-6, "scaled");
        assert!(matrix_from_quaternion([0.0; 4]).is_err());
        assert!(matrix_from_quaternion([f32::NAN, 0.0, 0.0, 1.0]).is_err());
    }

    #[test]
    fn gram_schmidt_of_noisy_6d_keeps_the_first_column_direction() {
        let m = rotation_from_6d([2.0, 0.0, 0.0, 0.5, 3.0, 0.0]);
        assert_close(rotation_to_6d(&m), [1.0, 0.0, 0.0, 0.0, 1.0, 0.0], 1e-6, "gram-schmidt");
        let m = rotation_from_6d([0.0, 0.0, 1.0, 1.0, 0.0, 0.2]);
        assert_close([m[0][0], m[1][0], m[2][0]], [0.0, 0.0, 1.0], 1e-6, "b1");
        assert_close([m[0][1], m[1][1], m[2][1]], [1.0, 0.0, 0.0], 1e-6, "b2");
    }

    #[test]
    fn degenerate_6d_gives_proper_rotations() {
        let big = 3.0e38f32;
        let cases: [[f32; 6]; 12] = [
            [0.0; 6],
            [1.0, 2.0, 3.0, 2.0, 4.0, 6.0],      // parallel
            [1.0, 2.0, 3.0, -1.0, -2.0, -3.0],   // antiparallel
            [0.0, 0.0, 0.0, 0.3, -0.2, 0.9],     // zero first column
            [0.3, -0.2, 0.9, 0.0, 0.0, 0.0],     // zero second column
            [f32::NAN, 1.0, 0.0, 0.0, 1.0, 0.0], // NaN
            [f32::INFINITY, 0.0, 0.0, f32::NEG_INFINITY, 1.0, f32::NAN],
            [big, big, big, big, big, -big],    // huge
            [1e-30, 0.0, 0.0, 0.0, 1e-30, 0.0], // tiny
            [1.0, 1e-8, 0.0, 1.0, 0.0, 0.0],    // nearly parallel
            [0.0, 0.0, 1.0, 0.0, 0.0, 1.0],     // parallel to e_z
            [0.577, 0.577, 0.577, 0.577, 0.577, 0.577],
        ];
        for r in cases {
            assert_proper_rotation(&rotation_from_6d(r), &format!("6D {r:?}"));
            let q = quaternion_from_6d(r);
            assert!(q.iter().all(|v| v.is_finite()) && q[0] >= 0.0, "{r:?} -> {q:?}");
        }
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(rotation_from_6d([0.0; 6]), identity);
        assert_eq!(rotation_from_6d([1.0, 0.0, 0.0, 3.0, 0.0, 0.0]), identity);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..2000 {
            let r: [f32; 6] = std::array::from_fn(|_| rng.random_range(-1.0f32..1.0));
            assert_proper_rotation(&rotation_from_6d(r), "random 6D");
        }
    }
}
