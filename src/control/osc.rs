//! The operational-space controller, solved as a QP with OSQP every tick.
//!
//! Decision variable: the joint accelerations q̈ (7). With gravity compensated by the robot
//! (the real Panda in torque mode, MuJoCo's gravcomp in simulation), the torque is
//! tau = M q̈ + C q̇ + F, with F the model's joint friction (compensated to the configured
//! fraction). Cost:
//!
//!   |J q̈ + J̇q̇ - a_des|²_W  +  w_n |N (q̈ - q̈_posture)|²  +  eps |q̈|²
//!
//! with a_des = a_ref + Kp e + Kd ė + Ki ∫e (the TCP pose error e against the reference, the
//! integral only near the reference), N = I - J⁺J the Jacobian's nullspace projector, and
//! q̈_posture a PD pull to the reference joint posture. Constraints: joint torques within the
//! rated torques and within 1 Nm of the previous tick's (torque rate); joint accelerations
//! within bounds that keep positions and velocities inside their limits over a short horizon.
//!
//! Most ticks no row is active: the cost's unconstrained minimum -H⁻¹g (a 7x7 Cholesky solve)
//! meets every row, and since the QP is convex that minimum, with zero slack, is its exact
//! solution, so OSQP is skipped (counted: [`OscStats::qp_solves`] are the ticks it ran). The
//! matrices keep one dense sparsity pattern (the `*_dense` constructors keep explicit zeros),
//! are updated in place, and the solver is warm-started (from that minimum when the previous
//! tick did not run it): nothing allocates per tick.
//! If OSQP fails or runs past its time limit, the tick uses a damping torque instead (within
//! the same torque and rate limits), counted in [`OscStats`]. The output is never NaN.
use std::time::Duration;

use nalgebra::{Isometry3, Matrix6, SMatrix, Vector3, Vector6};
use osqp::{CscMatrix, Problem, Settings, Status};

use super::osc_config::OscConfig;
use super::pose_error::pose_error;
use super::trajectory::JointSetpoint;
use crate::robot::{Dynamics, Jacobian, JointLimits, JointMatrix, JointVector, TaskKinematics};

const N: usize = 7;
/// Variables: q̈ (7) and the slack of the acceleration rows (7).
const NX: usize = 14;
/// Constraint rows: 7 torque rows (A = [M 0]), 7 acceleration rows (A = [I I]).
const M: usize = 14;
/// Within this distance of a position limit (rad), a joint's limit row stiffens.
const LIMIT_BAND: f64 = 0.3;
/// OSQP needs a positive time limit; this one never triggers.
const NO_TIME_LIMIT_S: f64 = 1e6;
/// The friction compensation changes by at most this fraction of the torque-rate limit per tick.
const FRICTION_RAMP: f64 = 0.25;

/// Where the TCP and the posture should be at this tick (base frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TaskReference {
    pub pose: Isometry3<f64>,
    /// Linear and angular velocity (m/s, rad/s).
    pub twist: Vector6<f64>,
    /// Linear and angular acceleration (feed-forward).
    pub acceleration: Vector6<f64>,
    /// Joint posture for the nullspace (the trajectory's joint reference).
    pub posture: JointSetpoint,
}

impl TaskReference {
    /// The Cartesian reference of a joint reference: FK, J q̇, J q̈ + J̇ q̇ at the reference.
    pub fn from_joint_setpoint(setpoint: &JointSetpoint, at_reference: &TaskKinematics) -> Self {
        Self {
            pose: at_reference.tcp,
            twist: at_reference.jacobian * setpoint.dq,
            acceleration: at_reference.jacobian * setpoint.ddq + at_reference.jdot_qdot,
            posture: *setpoint,
        }
    }
}

/// Counts over the controller's life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct OscStats {
    pub ticks: u64,
    /// Ticks where the QP failed or timed out and the damping torque was used.
    pub fallbacks: u64,
    /// Of those: infeasible constraints, iteration limit, time limit, anything else.
    pub infeasible: u64,
    pub iteration_limit: u64,
    pub time_limit: u64,
    pub other: u64,
    /// Ticks where OSQP ran: the cost's unconstrained minimum left a row (a torque, torque-rate,
    /// acceleration, velocity or position bound). On the others that minimum is the solution.
    pub qp_solves: u64,
}

/// One tick's result.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OscOutput {
    /// Joint torques to send (gravity excluded: the robot compensates it).
    pub tau: JointVector,
    /// The TCP pose error against the reference (position m, rotation vector rad).
    pub error: Vector6<f64>,
    pub fallback: bool,
}

#[derive(Debug, thiserror::Error)]
#[error("cannot set up the OSC's QP: {0}")]
pub struct OscSetupError(String);

/// The arm's joint friction as the controller models it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointFriction {
    /// Dry friction (Nm).
    pub coulomb: JointVector,
    /// Viscous damping (Nm s/rad).
    pub viscous: JointVector,
}

impl JointFriction {
    pub fn of(description: &crate::robot::ArmDescription) -> Self {
        Self {
            coulomb: JointVector::from_fn(|i, _| description.links[i].friction),
            viscous: JointVector::from_fn(|i, _| description.links[i].damping),
        }
    }
}

/// The controller and its solver state.
pub struct Osc {
    config: OscConfig,
    limits: JointLimits,
    friction: JointFriction,
    dt: f64,
    problem: Problem,
    p: CscMatrix<'static>,
    a: CscMatrix<'static>,
    lin: [f64; NX],
    lower: [f64; M],
    upper: [f64; M],
    tau_prev: JointVector,
    friction_torque: JointVector,
    integral: Vector6<f64>,
    stats: OscStats,
    /// Whether OSQP ran on the previous tick (its solution is then the warm start).
    osqp_current: bool,
}

impl std::fmt::Debug for Osc {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Osc").field("stats", &self.stats).field("tau_prev", &self.tau_prev).finish()
    }
}

impl Osc {
    pub fn new(
        config: OscConfig,
        limits: JointLimits,
        friction: JointFriction,
        dt: f64,
    ) -> Result<Self, OscSetupError> {
        // Fixed sparsity patterns, built explicitly so that no entry is ever dropped:
        // P = [H 0; 0 w_s I] (H's dense upper triangle, 28 + 7 entries),
        // A = [M 0; I I] (M dense, identities: 56 + 7 entries).
        let mut p = p_pattern();
        let mut a = a_pattern();
        write_upper(p.data.to_mut(), &JointMatrix::identity(), &JointVector::repeat(config.slack_weight));
        write_constraints(a.data.to_mut(), &JointMatrix::identity());
        let lin = [0.0; NX];
        let (lower, upper) = ([-1.0; M], [1.0; M]);
        let settings = Settings::default()
            .verbose(false)
            .warm_starting(true)
            .polishing(false)
            .scaling(Some(config.scaling_iterations).filter(|&n| n > 0))
            .adaptive_rho(true)
            .adaptive_rho_interval(Some(25))
            .eps_abs(1e-5)
            .eps_rel(1e-5)
            .max_iter(config.max_iterations)
            .check_termination(Some(10))
            .time_limit(Some(Duration::from_secs_f64(if config.time_limit > 0.0 {
                config.time_limit
            } else {
                NO_TIME_LIMIT_S
            })));
        let problem =
            Problem::new(&p, &lin, &a, &lower, &upper, &settings).map_err(|e| OscSetupError(format!("{e:?}")))?;
        Ok(Self {
            config,
            limits,
            friction,
            dt,
            problem,
            p,
            a,
            lin,
            lower,
            upper,
            tau_prev: JointVector::zeros(),
            friction_torque: JointVector::zeros(),
            integral: Vector6::zeros(),
            stats: OscStats::default(),
            osqp_current: false,
        })
    }

    pub fn config(&self) -> &OscConfig {
        &self.config
    }

    pub fn stats(&self) -> OscStats {
        self.stats
    }

    /// Forget the integral; `tau` is the torque currently applied (rate limits start from it).
    pub fn reset(&mut self, tau: &JointVector) {
        self.tau_prev = *tau;
        self.friction_torque = JointVector::zeros();
        self.integral = Vector6::zeros();
        self.osqp_current = false;
    }

    /// The torque for this tick. `dynamics` is the model at the measured state (q, q̇);
    /// `external` the measured external torque (contacts, end stops), which the joint-limit
    /// constraints account for: an obstacle pushing a joint toward its limit is braked against,
    /// not only the arm's own motion. The task does not compensate it (a contact stays
    /// compliant).
    pub fn compute(
        &mut self,
        q: &JointVector,
        dq: &JointVector,
        dynamics: &Dynamics,
        reference: &TaskReference,
        external: &JointVector,
    ) -> OscOutput {
        self.stats.ticks += 1;
        let (tau_lo, tau_hi) = self.torque_bounds();
        let error = pose_error(&reference.pose, &dynamics.tcp);
        if !(q.iter().chain(dq.iter()).all(|v| v.is_finite()) && error.iter().all(|v| v.is_finite())) {
            return self.fallback(dq, &tau_lo, &tau_hi, error);
        }
        let jac = &dynamics.jacobian;
        self.integrate_error(&error, reference);
        let a_des = self.task_acceleration(jac, dq, &error, reference);
        let b = a_des - dynamics.jdot_qdot;
        let Some((posture, null_sq)) = self.nullspace_posture(jac, q, dq, reference) else {
            return self.fallback(dq, &tau_lo, &tau_hi, error);
        };
        let (hessian, gradient) = self.task_cost(jac, b, posture, null_sq);
        self.compensate_friction(q, dq, reference);
        let offset = dynamics.coriolis + self.friction_torque;
        let mass = &dynamics.mass;
        // The acceleration the external torque adds to the model's: M^-1 tau_ext.
        let external = external.map(|v| if v.is_finite() { v } else { 0.0 });
        let external_acceleration = if !self.config.external_torque_in_limits || external.iter().all(|&v| v == 0.0) {
            JointVector::zeros()
        } else {
            mass.cholesky().map_or_else(JointVector::zeros, |c| c.solve(&external))
        };
        let ddq_bounds = self.acceleration_bounds(q, dq, &external_acceleration, mass);
        self.write_bounds(&tau_lo, &tau_hi, &offset, &ddq_bounds);
        let unconstrained = unconstrained_minimum(&hessian, &gradient);
        let ddq = match unconstrained.filter(|ddq| self.within_rows(ddq, mass)) {
            // The cost's minimum meets every row, so it is the QP's solution (the QP is convex,
            // and its slack is zero there): OSQP is not needed this tick.
            Some(ddq) => {
                self.osqp_current = false;
                ddq
            }
            None => {
                let start = if self.osqp_current { None } else { unconstrained };
                self.osqp_current = true;
                let Some(ddq) = self.solve_qp(q, &hessian, &gradient, mass, start.as_ref()) else {
                    return self.fallback(dq, &tau_lo, &tau_hi, error);
                };
                ddq
            }
        };
        let tau = mass * ddq + offset;
        if !tau.iter().all(|v| v.is_finite()) {
            return self.fallback(dq, &tau_lo, &tau_hi, error);
        }
        // OSQP meets its bounds to its tolerance; the clamp makes the limits exact.
        let tau = tau.zip_zip_map(&tau_lo, &tau_hi, |t, lo, hi| t.clamp(lo, hi));
        self.tau_prev = tau;
        OscOutput { tau, error, fallback: false }
    }

    /// The integral term ∫e: integrated only near a reference at rest (conditional integration:
    /// while the reference moves, or in contact that holds the TCP off, it would wind up), and
    /// bounded per part (position, orientation) by the gains' integral limits.
    fn integrate_error(&mut self, error: &Vector6<f64>, reference: &TaskReference) {
        let c = &self.config;
        let at_rest = reference.posture.dq.norm() < 1e-6;
        for (part, gains) in [(0usize, &c.position), (3usize, &c.orientation)] {
            let e = error.fixed_rows::<3>(part).into_owned();
            let mut sum = self.integral.fixed_rows::<3>(part).into_owned();
            if at_rest && e.norm() < gains.integral_zone {
                sum += e * self.dt;
            }
            let push = gains.integral.component_mul(&sum).norm();
            if push > gains.integral_limit {
                sum *= gains.integral_limit / push;
            }
            self.integral.fixed_rows_mut::<3>(part).copy_from(&sum);
        }
    }

    /// Task-space feedback: the desired TCP acceleration a_des = a_ref + Kd (v_des - v) + Ki ∫e
    /// from the pose error, with the approach speed and the feedback's acceleration bounded.
    fn task_acceleration(
        &self,
        jac: &Jacobian,
        dq: &JointVector,
        error: &Vector6<f64>,
        reference: &TaskReference,
    ) -> Vector6<f64> {
        let c = &self.config;
        let gains6 = |f: fn(&super::osc_config::AxisGains) -> Vector3<f64>| -> Vector6<f64> {
            let (p, o) = (f(&c.position), f(&c.orientation));
            Vector6::new(p.x, p.y, p.z, o.x, o.y, o.z)
        };
        let kp = gains6(|g| g.stiffness);
        let kd = gains6(|g| g.damping());
        let ki = gains6(|g| g.integral);
        // PD with the approach speed bounded: v_des = v_ref + sat(Kp/Kd e); a_des = a_ref +
        // Kd (v_des - v) + Ki ∫e (the same as a_ref + Kp e + Kd ė while unsaturated).
        let mut correction = kp.zip_map(&kd, |p, d| if d > 0.0 { p / d } else { 0.0 }).component_mul(error);
        for (part, limit) in [(0usize, c.position.max_speed), (3usize, c.orientation.max_speed)] {
            let n = correction.fixed_rows::<3>(part).norm();
            if n > limit {
                correction.fixed_rows_mut::<3>(part).scale_mut(limit / n);
            }
        }
        let velocity = jac * dq;
        let desired_velocity = reference.twist + correction;
        // The feedback's acceleration is bounded per part: in contact (a blocked TCP) the
        // error would otherwise grow into forces that make the wrist give way.
        let mut feedback = kd.component_mul(&(desired_velocity - velocity)) + ki.component_mul(&self.integral);
        for (part, limit) in [(0usize, c.position.max_acceleration), (3usize, c.orientation.max_acceleration)] {
            let n = feedback.fixed_rows::<3>(part).norm();
            if n > limit {
                feedback.fixed_rows_mut::<3>(part).scale_mut(limit / n);
            }
        }
        reference.acceleration + feedback
    }

    /// Posture in the nullspace: the PD pull q̈_posture to the reference joint posture and NᵀN,
    /// with N = I - J⁺J (J⁺ through a damped JJᵀ). None if JJᵀ has no Cholesky factor.
    fn nullspace_posture(
        &self,
        jac: &Jacobian,
        q: &JointVector,
        dq: &JointVector,
        reference: &TaskReference,
    ) -> Option<(JointVector, JointMatrix)> {
        let c = &self.config;
        let kn = c.nullspace_stiffness;
        let dn = 2.0 * c.nullspace_damping_ratio * kn.sqrt();
        let posture = reference.posture.ddq + (reference.posture.q - q) * kn + (reference.posture.dq - dq) * dn;
        let jjt = jac * jac.transpose() + Matrix6::identity() * 1e-6;
        let ch = jjt.cholesky()?;
        let pinv: SMatrix<f64, 7, 6> = jac.transpose() * ch.inverse();
        let null = JointMatrix::identity() - pinv * jac;
        let null_sq = null.transpose() * null;
        Some((posture, null_sq))
    }

    /// The QP's cost in q̈ (as robosuite's `opspace_matrices()`): the Hessian
    /// JᵀWJ + w_n NᵀN + eps I and the gradient -(JᵀW b + w_n NᵀN q̈_posture), b = a_des - J̇q̇.
    fn task_cost(
        &self,
        jac: &Jacobian,
        b: Vector6<f64>,
        posture: JointVector,
        null_sq: JointMatrix,
    ) -> (JointMatrix, JointVector) {
        let c = &self.config;
        let w = Vector6::new(
            c.position_weight,
            c.position_weight,
            c.position_weight,
            c.orientation_weight,
            c.orientation_weight,
            c.orientation_weight,
        );
        let jtw = jac.transpose() * Matrix6::from_diagonal(&w);
        let hessian = jtw * jac + null_sq * c.posture_weight + JointMatrix::identity() * c.regularization;
        let gradient = -(jtw * b + null_sq * posture * c.posture_weight);
        (hessian, gradient)
    }

    /// Friction compensation (model-based): dry friction toward where the posture should go,
    /// viscous on the measured velocity. Updates `friction_torque`, ramped toward it.
    fn compensate_friction(&mut self, q: &JointVector, dq: &JointVector, reference: &TaskReference) {
        let c = &self.config;
        let toward = reference.posture.dq + (reference.posture.q - q) * c.friction_direction_gain;
        let target = (self.friction.coulomb.component_mul(&toward.map(|v| (v / c.friction_smoothing).tanh()))
            + self.friction.viscous.component_mul(dq))
            * c.friction_compensation;
        // Ramp it: it switches sign with the direction, and a jump would eat the torque-rate
        // budget of the tick.
        let ramp = self.limits.torque_rate * self.dt * FRICTION_RAMP;
        self.friction_torque =
            self.friction_torque.zip_zip_map(&target, &ramp, |prev, t, r| t.clamp(prev - r, prev + r));
    }

    /// Bounds of the QP's rows: torque rows (on M q̈ = tau - C q̇ - friction, `offset` being
    /// C q̇ + friction) and acceleration rows (`ddq_bounds`, from [`Self::acceleration_bounds`]).
    fn write_bounds(
        &mut self,
        tau_lo: &JointVector,
        tau_hi: &JointVector,
        offset: &JointVector,
        ddq_bounds: &(JointVector, JointVector),
    ) {
        for i in 0..N {
            self.lower[i] = tau_lo[i] - offset[i];
            self.upper[i] = tau_hi[i] - offset[i];
            self.lower[N + i] = ddq_bounds.0[i];
            self.upper[N + i] = ddq_bounds.1[i];
        }
    }

    /// Whether `ddq` meets every row of the QP (bounds from [`Self::write_bounds`]) with zero
    /// slack: the torque rows on M q̈ and the acceleration rows on q̈.
    fn within_rows(&self, ddq: &JointVector, mass: &JointMatrix) -> bool {
        let torque_rows = mass * ddq;
        (0..N).all(|i| {
            (self.lower[i]..=self.upper[i]).contains(&torque_rows[i])
                && (self.lower[N + i]..=self.upper[N + i]).contains(&ddq[i])
        })
    }

    /// The QP update and solve: the linear cost, the slack weights, P and A written in place
    /// (bounds from [`Self::write_bounds`]), then OSQP warm-started: from `start` (the cost's
    /// unconstrained minimum, zero slack and zero duals: where the ticks that did not need OSQP
    /// left the problem) when given, else from OSQP's last solution. The joint accelerations,
    /// or None if OSQP did not solve (counted by cause in the stats; the caller falls back to
    /// the damping torque).
    fn solve_qp(
        &mut self,
        q: &JointVector,
        hessian: &JointMatrix,
        gradient: &JointVector,
        mass: &JointMatrix,
        start: Option<&JointVector>,
    ) -> Option<JointVector> {
        self.stats.qp_solves += 1;
        for i in 0..N {
            self.lin[i] = gradient[i];
        }
        // The slack of a joint's limit row stiffens as the joint nears a position limit, so a
        // task pushed by a contact cannot drive a joint into its limit.
        let c = &self.config;
        let l = &self.limits;
        let slack = JointVector::from_fn(|i, _| {
            let d = (q[i] - l.position_min[i]).min(l.position_max[i] - q[i]).max(0.01);
            c.slack_weight * (1.0 + (LIMIT_BAND / d).powi(2))
        });
        write_upper(self.p.data.to_mut(), hessian, &slack);
        write_constraints(self.a.data.to_mut(), mass);
        // One call for both: OSQP rescales and refactors its KKT matrix once (twice with
        // `update_P` then `update_A`, about 7 us more per tick).
        if self.problem.update_P_A(&self.p, &self.a).is_err() {
            // OSQP refused the data (e.g. a zero pivot: the KKT matrix not quasidefinite): the
            // caller falls back to damping, as for a failed solve.
            self.stats.other += 1;
            return None;
        }
        self.problem.update_lin_cost(&self.lin);
        self.problem.update_bounds(&self.lower, &self.upper);
        if let Some(start) = start {
            let mut x = [0.0; NX];
            x[..N].copy_from_slice(start.as_slice());
            self.problem.warm_start(&x, &[0.0; M]);
        }

        match self.problem.solve() {
            Status::Solved(s) | Status::SolvedInaccurate(s) => Some(JointVector::from_column_slice(&s.x()[..N])),
            status => {
                let counter = match status {
                    Status::PrimalInfeasible(_) | Status::PrimalInfeasibleInaccurate(_) => &mut self.stats.infeasible,
                    Status::MaxIterationsReached(_) => &mut self.stats.iteration_limit,
                    Status::TimeLimitReached(_) => &mut self.stats.time_limit,
                    _ => &mut self.stats.other,
                };
                *counter += 1;
                None
            }
        }
    }

    /// The damping torque within this tick's limits, for ticks where no model is available
    /// (counted as a fallback).
    pub fn safe_torque(&mut self, dq: &JointVector) -> OscOutput {
        let (lo, hi) = self.torque_bounds();
        self.fallback(dq, &lo, &hi, Vector6::zeros())
    }

    /// Torque bounds for this tick: rated torque, and at most the rated rate times dt away
    /// from the previous tick's torque.
    fn torque_bounds(&self) -> (JointVector, JointVector) {
        let step = self.limits.torque_rate * self.dt;
        let lo = JointVector::from_fn(|i, _| (-self.limits.torque[i]).max(self.tau_prev[i] - step[i]));
        let hi = JointVector::from_fn(|i, _| self.limits.torque[i].min(self.tau_prev[i] + step[i]));
        (lo, hi)
    }

    /// Accelerations that keep the joints inside their position limits (less the margin) and
    /// velocity limits over the horizon, and within the acceleration limits, all for the
    /// acceleration the joints will have: the commanded one plus `external` (M^-1 tau_ext). A
    /// push that would drive a joint toward a limit, or accelerate it past its acceleration
    /// limit, is braked against (within the torque and torque-rate limits); a gentler contact is
    /// left to the compliant task. The external acceleration counts only as far as the joint
    /// already moves the way it pushes: a contact's reaction to the arm's own press does not move
    /// the joint, and braking against it ran the press up to the rated torques. (Shifting only
    /// the position and velocity bounds was tried: 3 of 12 fault runs then still left a limit.)
    ///
    /// Counting the external acceleration lets the commanded torque lean on the contact; if the
    /// contact lets go at once (a hand slipping off an edge), the joint gets the model's
    /// acceleration `ddq`, and the torque unwinds only at its rated rate. So `ddq` itself stays
    /// within what that unwinding stops short of the velocity limit (`unwind_cap`).
    fn acceleration_bounds(
        &self,
        q: &JointVector,
        dq: &JointVector,
        external: &JointVector,
        mass: &JointMatrix,
    ) -> (JointVector, JointVector) {
        let h = self.config.limit_horizon;
        let margin = self.config.limit_margin;
        let l = &self.limits;
        let mut lo = JointVector::zeros();
        let mut hi = JointVector::zeros();
        for i in 0..N {
            let pos_lo = 2.0 * (l.position_min[i] + margin - q[i] - dq[i] * h) / (h * h);
            let pos_hi = 2.0 * (l.position_max[i] - margin - q[i] - dq[i] * h) / (h * h);
            let vel_lo = (-l.velocity[i] - dq[i]) / h;
            let vel_hi = (l.velocity[i] - dq[i]) / h;
            lo[i] = pos_lo.max(vel_lo).max(-l.acceleration[i]);
            hi[i] = pos_hi.min(vel_hi).min(l.acceleration[i]);
            if lo[i] > hi[i] {
                // Already outside what the horizon allows: brake toward the safe side.
                let brake = (-dq[i] / h).clamp(-l.acceleration[i], l.acceleration[i]);
                lo[i] = brake;
                hi[i] = brake;
            }
            // A contact's reaction to the arm's own push does not move the joint: counting it
            // as an acceleration to brake against would push harder, raising the reaction
            // (a run-away to the rated torques against the table). Count the external
            // acceleration only as far as the joint already moves the way it pushes.
            let moving = (dq[i] * external[i].signum() / EXTERNAL_MOTION).clamp(0.0, 1.0);
            if external[i] != 0.0 && moving > 0.0 {
                let cap = unwind_cap(l.torque_rate[i], mass[(i, i)], l.velocity[i], dq[i]).max(l.acceleration[i]);
                (lo[i], hi[i]) = within_cap(lo[i] - external[i] * moving, hi[i] - external[i] * moving, cap);
            }
        }
        (lo, hi)
    }

    fn fallback(&mut self, dq: &JointVector, lo: &JointVector, hi: &JointVector, error: Vector6<f64>) -> OscOutput {
        self.stats.fallbacks += 1;
        let damping = -self.config.fallback_damping.component_mul(&dq.map(|v| if v.is_finite() { v } else { 0.0 }));
        let tau = damping.zip_zip_map(lo, hi, |t, l, h| t.clamp(l, h));
        self.tau_prev = tau;
        OscOutput { tau, error: error.map(|v| if v.is_finite() { v } else { 0.0 }), fallback: true }
    }
}

/// Joint speed (rad/s) in the direction of an external push at which the push counts fully in
/// the limit rows (`acceleration_bounds`); below it, in proportion.
const EXTERNAL_MOTION: f64 = 0.05;

/// The share of a joint's velocity headroom that unwinding a torque leaning on a contact may use
/// (`unwind_cap`); the rest covers the coupling between joints that the cap's one-joint model
/// leaves out.
const UNWIND_HEADROOM: f64 = 0.5;

/// The largest model acceleration (rad/s^2) of a joint whose torque, were the contact it leans
/// on to vanish, unwinds at `torque_rate` (Nm/s) before the joint, at speed `dq`, passes
/// `UNWIND_HEADROOM` of the way to `velocity_limit`: the torque falls to zero in a M / rate,
/// adding a^2 M / (2 rate) of speed, with M the joint's own inertia (`inertia`, the mass
/// matrix's diagonal entry).
fn unwind_cap(torque_rate: f64, inertia: f64, velocity_limit: f64, dq: f64) -> f64 {
    let headroom = (velocity_limit - dq.abs()).max(0.0) * UNWIND_HEADROOM;
    (2.0 * torque_rate * headroom / inertia.max(1e-6)).sqrt()
}

/// `[lo, hi]` intersected with `[-cap, cap]`; when they do not meet, the end of the cap nearest
/// to the interval (brake as hard as is safe, never harder).
fn within_cap(lo: f64, hi: f64, cap: f64) -> (f64, f64) {
    if lo > cap {
        (cap, cap)
    } else if hi < -cap {
        (-cap, -cap)
    } else {
        (lo.max(-cap), hi.min(cap))
    }
}

/// The minimum of the cost 1/2 q̈ᵀHq̈ + gᵀq̈ without the rows: -H⁻¹g (H is positive definite:
/// `regularization` > 0), or None if the factorisation fails or the result is not finite.
fn unconstrained_minimum(hessian: &JointMatrix, gradient: &JointVector) -> Option<JointVector> {
    let ddq = hessian.cholesky()?.solve(&(-gradient));
    ddq.iter().all(|v| v.is_finite()).then_some(ddq)
}

/// P's pattern: column j < 7 holds rows 0..=j (H), column j >= 7 holds row j (slack).
fn p_pattern() -> CscMatrix<'static> {
    let (mut indptr, mut indices) = (vec![0], Vec::new());
    for j in 0..NX {
        if j < N {
            indices.extend(0..=j)
        } else {
            indices.push(j)
        }
        indptr.push(indices.len());
    }
    let nnz = indices.len();
    CscMatrix { nrows: NX, ncols: NX, indptr: indptr.into(), indices: indices.into(), data: vec![0.0; nnz].into() }
}

/// A's pattern: column j < 7 holds rows 0..7 (M) and row 7 + j; column j >= 7 holds row j.
fn a_pattern() -> CscMatrix<'static> {
    let (mut indptr, mut indices) = (vec![0], Vec::new());
    for j in 0..NX {
        if j < N {
            indices.extend(0..N);
            indices.push(N + j);
        } else {
            indices.push(j);
        }
        indptr.push(indices.len());
    }
    let nnz = indices.len();
    CscMatrix { nrows: M, ncols: NX, indptr: indptr.into(), indices: indices.into(), data: vec![0.0; nnz].into() }
}

/// Values of P in `p_pattern` order.
fn write_upper(data: &mut [f64], h: &JointMatrix, slack_weights: &JointVector) {
    let mut k = 0;
    for j in 0..N {
        for i in 0..=j {
            data[k] = 0.5 * (h[(i, j)] + h[(j, i)]);
            k += 1;
        }
    }
    for (v, w) in data[k..].iter_mut().zip(slack_weights.iter()) {
        *v = *w;
    }
}

/// Values of A in `a_pattern` order.
fn write_constraints(data: &mut [f64], mass: &JointMatrix) {
    let mut k = 0;
    for j in 0..N {
        for i in 0..N {
            data[k] = mass[(i, j)];
            k += 1;
        }
        data[k] = 1.0;
        k += 1;
    }
    for v in &mut data[k..] {
        *v = 1.0;
    }
}

#[cfg(test)]
mod tests {
    use super::{JointFriction, N, Osc, UNWIND_HEADROOM, unconstrained_minimum, unwind_cap, within_cap};
    use crate::robot::{JointLimits, JointMatrix, JointVector};

    /// An SPD 7x7 matrix: AᵀA + diag, A fixed.
    fn spd(scale: f64, diag: f64) -> JointMatrix {
        let a = JointMatrix::from_fn(|i, j| ((i * 7 + j) as f64 * 0.37).sin() * scale);
        a.transpose() * a + JointMatrix::identity() * diag
    }

    fn osc() -> Osc {
        let config = crate::rollout::stack::load_controller_config(None).expect("controllers/osc.toml");
        let limits = JointLimits::panda().expect("controllers/panda_limits.toml");
        let friction = JointFriction { coulomb: JointVector::zeros(), viscous: JointVector::zeros() };
        Osc::new(config, limits, friction, 1e-3).expect("the QP sets up")
    }

    /// Where no row is active, the unconstrained minimum is what OSQP finds; where one is, the
    /// minimum is refused and OSQP's solution meets the row.
    #[test]
    fn the_unconstrained_minimum_is_the_qp_solution_exactly_when_no_row_is_active() {
        let mut osc = osc();
        let (hessian, mass) = (spd(1.0, 0.5), spd(0.3, 0.2));
        let gradient = JointVector::from_fn(|i, _| (i as f64 - 3.0) * 0.8);
        let q = JointLimits::panda().unwrap().mid();
        let minimum = unconstrained_minimum(&hessian, &gradient).expect("H is positive definite");
        assert!((hessian * minimum + gradient).norm() < 1e-9, "not the cost's stationary point");

        let wide = (JointVector::repeat(-1e3), JointVector::repeat(1e3));
        osc.write_bounds(&wide.0, &wide.1, &JointVector::zeros(), &wide);
        assert!(osc.within_rows(&minimum, &mass));
        let solved = osc.solve_qp(&q, &hessian, &gradient, &mass, None).expect("OSQP solves");
        assert!((solved - minimum).norm() <= 1e-3 * minimum.norm(), "OSQP {solved} vs the minimum {minimum}");

        // Cap the first joint's acceleration below the minimum's: that row is active now.
        let mut hi = wide.1;
        hi[0] = minimum[0] - 0.5;
        osc.write_bounds(&wide.0, &wide.1, &JointVector::zeros(), &(wide.0, hi));
        assert!(!osc.within_rows(&minimum, &mass), "a violated acceleration row was accepted");
        let solved = osc.solve_qp(&q, &hessian, &gradient, &mass, Some(&minimum)).expect("OSQP solves");
        assert!((solved - minimum).norm() > 0.1, "the active row changed nothing");
        // The acceleration rows are soft (slack), but heavily weighted: the row nearly holds.
        assert!(solved[0] < minimum[0] - 0.4, "OSQP's q̈_1 {} ignores the bound {}", solved[0], hi[0]);

        // A torque row: cap M q̈ on the last joint below the minimum's torque.
        let torque = mass * minimum;
        let mut tau_hi = wide.1;
        tau_hi[N - 1] = torque[N - 1] - 1.0;
        osc.write_bounds(&wide.0, &tau_hi, &JointVector::zeros(), &wide);
        assert!(!osc.within_rows(&minimum, &mass), "a violated torque row was accepted");
        let solved = osc.solve_qp(&q, &hessian, &gradient, &mass, Some(&minimum)).expect("OSQP solves");
        assert!((mass * solved)[N - 1] <= tau_hi[N - 1] + 1e-3, "the torque row does not hold");
        assert_eq!(osc.stats().qp_solves, 3);
    }

    /// The speed a joint gains while its torque unwinds from `inertia * a` to zero at `rate`.
    fn unwind_speed(a: f64, inertia: f64, rate: f64) -> f64 {
        a * a * inertia / (2.0 * rate)
    }

    #[test]
    fn unwinding_from_the_cap_uses_the_headroom_share_and_no_more() {
        // Panda joint 1 and joint 7 figures: rated rate 1000 Nm/s, inertias 0.5 and 0.01 kg m^2.
        for (rate, inertia, limit, dq) in
            [(1000.0, 0.5, 2.175, 0.0), (1000.0, 0.01, 2.61, -1.2), (500.0, 2.0, 2.1, 1.9)]
        {
            let cap = unwind_cap(rate, inertia, limit, dq);
            let gained = unwind_speed(cap, inertia, rate);
            let allowed = (limit - f64::abs(dq)) * UNWIND_HEADROOM;
            assert!((gained - allowed).abs() <= 1e-9 * allowed.max(1.0), "gained {gained}, allowed {allowed}");
            assert!(f64::abs(dq) + gained < limit, "unwinding from the cap would pass the velocity limit");
        }
    }

    #[test]
    fn the_cap_closes_at_the_velocity_limit_and_stays_finite() {
        assert_eq!(unwind_cap(1000.0, 0.5, 2.0, 2.0), 0.0);
        assert_eq!(unwind_cap(1000.0, 0.5, 2.0, -2.5), 0.0, "past the limit the cap is zero, not NaN");
        let heavy = unwind_cap(1000.0, 0.5, 2.0, 0.0);
        let light = unwind_cap(1000.0, 0.05, 2.0, 0.0);
        assert!(light > heavy, "a lighter joint unwinds its torque faster: {light} vs {heavy}");
        assert!(unwind_cap(1000.0, 0.0, 2.0, 0.0).is_finite(), "a zero inertia entry must not divide by zero");
    }

    #[test]
    fn within_cap_intersects_or_brakes_at_the_nearest_end() {
        assert_eq!(within_cap(-1.0, 1.0, 3.0), (-1.0, 1.0));
        assert_eq!(within_cap(-5.0, 5.0, 3.0), (-3.0, 3.0));
        assert_eq!(within_cap(4.0, 6.0, 3.0), (3.0, 3.0));
        assert_eq!(within_cap(-6.0, -4.0, 3.0), (-3.0, -3.0));
    }
}
