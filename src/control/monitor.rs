//! The tick monitor: every tick's state and command checked against the arm's limits (torque,
//! torque rate, joint position and velocity) with the worst ratios kept, and the per-tick log
//! rows (t, q, dq, tau, TCP pose, reference) written as CSV.
use nalgebra::Isometry3;

use super::backend::RobotState;
use crate::robot::{JointLimits, JointVector};

/// One tick of the log.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LogRow {
    pub t: f64,
    pub q: JointVector,
    pub dq: JointVector,
    pub tau: JointVector,
    /// Measured TCP pose: x, y, z, qw, qx, qy, qz (base frame).
    pub tcp: [f64; 7],
    /// Reference TCP pose, same layout.
    pub reference: [f64; 7],
    pub q_ref: JointVector,
}

impl LogRow {
    pub const CSV_HEADER: &'static str = "t,q1,q2,q3,q4,q5,q6,q7,dq1,dq2,dq3,dq4,dq5,dq6,dq7,tau1,tau2,tau3,tau4,tau5,tau6,tau7,\
x,y,z,qw,qx,qy,qz,ref_x,ref_y,ref_z,ref_qw,ref_qx,ref_qy,ref_qz,q_ref1,q_ref2,q_ref3,q_ref4,q_ref5,q_ref6,q_ref7";

    pub fn csv_line(&self, out: &mut String) {
        use std::fmt::Write;
        let _ = write!(out, "{:.4}", self.t);
        for v in
            self.q.iter().chain(&self.dq).chain(&self.tau).chain(&self.tcp).chain(&self.reference).chain(&self.q_ref)
        {
            let _ = write!(out, ",{v:.6}");
        }
        out.push('\n');
    }
}

/// A pose in the log's layout: x, y, z, qw, qx, qy, qz.
pub(super) fn pose7(p: &Isometry3<f64>) -> [f64; 7] {
    let t = p.translation.vector;
    let q = p.rotation.quaternion();
    [t.x, t.y, t.z, q.w, q.i, q.j, q.k]
}

/// Watches every tick for limit violations and keeps the worst ratios.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LimitMonitor {
    pub(super) limits: JointLimits,
    dt: f64,
    previous_tau: Option<JointVector>,
    /// Ticks with any violation, and per kind (a tick can count under several kinds).
    pub violations: u64,
    pub torque_violations: u64,
    pub torque_rate_violations: u64,
    pub position_violations: u64,
    pub velocity_violations: u64,
    /// Ticks whose commanded torque had a NaN or infinite value.
    pub non_finite_torques: u64,
    pub max_torque_ratio: f64,
    pub max_torque_rate_ratio: f64,
    pub max_velocity_ratio: f64,
}

impl LimitMonitor {
    pub fn new(limits: JointLimits, dt: f64) -> Self {
        Self {
            limits,
            dt,
            previous_tau: None,
            violations: 0,
            torque_violations: 0,
            torque_rate_violations: 0,
            position_violations: 0,
            velocity_violations: 0,
            non_finite_torques: 0,
            max_torque_ratio: 0.0,
            max_torque_rate_ratio: 0.0,
            max_velocity_ratio: 0.0,
        }
    }

    /// The limits ticks are checked against.
    pub fn limits(&self) -> &JointLimits {
        &self.limits
    }

    /// Checks the state and the command of one tick.
    pub fn check(&mut self, state: &RobotState, tau: &JointVector) {
        let l = &self.limits;
        let (mut torque_over, mut rate_over, mut position_out, mut velocity_over) = (false, false, false, false);
        for i in 0..7 {
            let torque = tau[i].abs() / l.torque[i];
            let velocity = state.dq[i].abs() / l.velocity[i];
            let rate = self.previous_tau.map_or(0.0, |p| (tau[i] - p[i]).abs() / (l.torque_rate[i] * self.dt));
            self.max_torque_ratio = self.max_torque_ratio.max(torque);
            self.max_velocity_ratio = self.max_velocity_ratio.max(velocity);
            self.max_torque_rate_ratio = self.max_torque_rate_ratio.max(rate);
            // a NaN counts as over the limit
            torque_over |= torque > 1.0 + 1e-9 || torque.is_nan();
            rate_over |= rate > 1.0 + 1e-9 || rate.is_nan();
            velocity_over |= velocity > 1.0;
            position_out |= state.q[i] < l.position_min[i] || state.q[i] > l.position_max[i];
        }
        self.non_finite_torques += u64::from(tau.iter().any(|v| !v.is_finite()));
        self.torque_violations += u64::from(torque_over);
        self.torque_rate_violations += u64::from(rate_over);
        self.position_violations += u64::from(position_out);
        self.velocity_violations += u64::from(velocity_over);
        self.violations += u64::from(torque_over || rate_over || position_out || velocity_over);
        self.previous_tau = Some(*tau);
    }
}
