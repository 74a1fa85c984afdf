//! The last check between the controller and a real robot: every commanded torque finite,
//! inside the rated torques, and within the torque-rate limit of the torque the robot last
//! received. The controller's QP already keeps to these limits; the guard holds them when
//! something upstream does not (a bug, a NaN, a packet the robot lost).
use crate::robot::{JointLimits, JointVector};

/// The guard keeps this far inside the torque-rate limit (Nm/s), like libfranka's limiter
/// (`kLimitEps`) but wider: 2e-5 Nm per 1 ms cycle also covers the float32 rounding of the
/// robot's echo of the last command (up to ~1e-5 Nm at 87 Nm), which the guard measures from
/// when a command was lost.
const RATE_EPS: f64 = 0.02;
/// Changes below this (Nm) are rounding, not clamping.
const ROUNDING: f64 = 5e-5;

/// Clamps commands to the rated torques and the torque-rate limit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TorqueGuard {
    torque: JointVector,
    /// Largest change per cycle (Nm).
    step: JointVector,
}

/// What the guard let through.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Guarded {
    pub tau: JointVector,
    /// The command was changed (clamped or replaced).
    pub clamped: bool,
    /// The first joint whose commanded torque was NaN or infinite: the command was replaced by
    /// a step from the last received torque toward zero.
    pub non_finite: Option<usize>,
}

impl TorqueGuard {
    /// For an arm with `limits` commanded every `period` seconds.
    pub fn new(limits: &JointLimits, period: f64) -> Self {
        Self { torque: limits.torque, step: limits.torque_rate.map(|r| (r - RATE_EPS) * period) }
    }

    /// The command to send for `tau`, given the torque the robot last received (`last`).
    pub fn apply(&self, tau: &JointVector, last: &JointVector) -> Guarded {
        let non_finite = (0..7).find(|&i| !tau[i].is_finite());
        let mut clamped = non_finite.is_some();
        let mut out = JointVector::zeros();
        for i in 0..7 {
            let wanted = if non_finite.is_some() { 0.0 } else { tau[i] };
            let from = if last[i].is_finite() { last[i] } else { 0.0 };
            let t = wanted.clamp(from - self.step[i], from + self.step[i]).clamp(-self.torque[i], self.torque[i]);
            clamped |= (t - wanted).abs() > ROUNDING;
            out[i] = t;
        }
        Guarded { tau: out, clamped, non_finite }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn guard() -> TorqueGuard {
        TorqueGuard::new(&JointLimits::panda().unwrap(), 0.001)
    }

    #[test]
    fn passes_commands_inside_the_limits_unchanged() {
        let last = JointVector::from_element(5.0);
        let tau = JointVector::from_element(5.5);
        let g = guard().apply(&tau, &last);
        assert_eq!(g.tau, tau);
        assert!(!g.clamped && g.non_finite.is_none());
    }

    #[test]
    fn a_command_at_the_rate_limit_passes_as_rounding() {
        let last = JointVector::zeros();
        let g = guard().apply(&JointVector::from_element(1.0), &last);
        assert!(!g.clamped);
        assert!(g.tau.iter().all(|&t| t < 1.0));
    }

    #[test]
    fn limits_the_rate_against_the_last_received_torque() {
        let last = JointVector::zeros();
        let g = guard().apply(&JointVector::from_element(50.0), &last);
        assert!(g.clamped);
        for i in 0..7 {
            assert!((g.tau[i] - 0.999_98).abs() < 1e-12, "joint {i}: {}", g.tau[i]);
        }
    }

    #[test]
    fn keeps_inside_the_rated_torques() {
        // the wrist's rated torque is 12 Nm: from 11.9 the step up stops at 12
        let last = JointVector::from_element(11.9);
        let g = guard().apply(&JointVector::from_element(40.0), &last);
        assert_eq!(g.tau[6], 12.0);
        assert!((g.tau[0] - 12.899_98).abs() < 1e-12);
    }

    #[test]
    fn replaces_non_finite_commands_with_a_step_toward_zero() {
        let last = JointVector::from_element(3.0);
        let mut tau = JointVector::from_element(1.0);
        tau[4] = f64::NAN;
        let g = guard().apply(&tau, &last);
        assert_eq!(g.non_finite, Some(4));
        assert!(g.tau.iter().all(|t| (t - 2.000_02).abs() < 1e-12), "{:?}", g.tau);
        tau[4] = f64::INFINITY;
        assert_eq!(guard().apply(&tau, &last).non_finite, Some(4));
    }
}
