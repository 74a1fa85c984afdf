//! The 6-vector error between two TCP poses, as used by IK and the operational-space
//! controller: position difference and rotation vector, both in base-frame axes.
use nalgebra::{Isometry3, UnitQuaternion, Vector3, Vector6};

/// Rotation vector (axis * angle, rad) of `target * current^-1`, in base-frame axes, with the
/// angle in [0, pi]. Uses atan2, so it stays exact near zero (acos-based angles do not).
pub fn rotation_error(target: &UnitQuaternion<f64>, current: &UnitQuaternion<f64>) -> Vector3<f64> {
    let mut q = (target * current.inverse()).into_inner();
    if q.w < 0.0 {
        q = -q; // shortest way round
    }
    let v = q.imag();
    let s = v.norm();
    if s < 1e-12 {
        return v * 2.0; // first-order: angle ~ 2|v|
    }
    v * (2.0 * s.atan2(q.w) / s)
}

/// `[target.p - current.p; rotation_error(target.R, current.R)]`.
pub fn pose_error(target: &Isometry3<f64>, current: &Isometry3<f64>) -> Vector6<f64> {
    let dp = target.translation.vector - current.translation.vector;
    let dr = rotation_error(&target.rotation, &current.rotation);
    Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_error_recovers_axis_angle_including_tiny_and_large_angles() {
        for angle in [1e-9, 1e-4, 0.5, 3.0, std::f64::consts::PI - 1e-6] {
            let axis = Vector3::new(1.0, -2.0, 0.5).normalize();
            let current = UnitQuaternion::from_euler_angles(0.3, -0.2, 1.0);
            let target = UnitQuaternion::from_scaled_axis(axis * angle) * current;
            let e = rotation_error(&target, &current);
            assert!((e - axis * angle).norm() < 1e-12 * angle.max(1.0), "angle {angle}: {e:?}");
        }
    }
}
