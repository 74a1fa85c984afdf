//! Inverse kinematics: a keyframe pose (TCP in the base frame) to a joint goal.
//!
//! Damped least squares (Levenberg-Marquardt) on the 6-D pose error, seeded from the current
//! configuration, with a pull toward a neutral posture in the Jacobian's nullspace and every
//! iterate clamped into the joint limits. If the seed does not converge, it restarts from the
//! neutral posture and then from seeded random configurations. A pose that no configuration
//! within the limits reaches to tolerance is an error, never a wrong answer.
use std::f64::consts::{FRAC_PI_2, FRAC_PI_4};

use nalgebra::{Isometry3, Matrix6, Quaternion, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};

use super::pose_error::pose_error;
use crate::robot::{JointLimits, JointVector, Kinematics, KinematicsError};

/// Why a keyframe pose has no joint goal.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IkError {
    #[error("the target pose has a non-finite value ({0})")]
    NonFinite(&'static str),
    #[error("the target quaternion has norm {norm:.6}; expected a unit quaternion [w, x, y, z]")]
    NotUnitQuaternion { norm: f64 },
    #[error("the target is {distance:.3} m from the shoulder; the arm reaches at most {reach:.3} m")]
    OutOfReach { distance: f64, reach: f64 },
    #[error(
        "no configuration within the joint limits reaches the pose: best is {position_error_mm:.1} mm / {orientation_error_deg:.2} deg off"
    )]
    Unreachable { position_error_mm: f64, orientation_error_deg: f64 },
    #[error(transparent)]
    Kinematics(#[from] KinematicsError),
}

/// Settings of the solver (defaults suit the Panda).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkConfig {
    /// A solution is accepted within these (m, rad).
    pub position_tolerance: f64,
    pub orientation_tolerance: f64,
    /// Iteration stops early below these (m, rad).
    pub position_precision: f64,
    pub orientation_precision: f64,
    pub max_iterations: usize,
    /// Random restarts after the seed and the neutral posture.
    pub restarts: usize,
    /// Levenberg-Marquardt damping (added to J J^T's diagonal).
    pub damping: f64,
    /// Goals stay this far inside the joint limits (rad).
    pub limit_margin: f64,
    /// Posture preferred in the nullspace, and the first restart.
    pub neutral: JointVector,
    /// Gain of the nullspace pull toward `neutral` (per iteration).
    pub nullspace_gain: f64,
    /// Shoulder (joint 2 axis) position in the base frame and the arm's reach from it, for a
    /// fast rejection of far targets (m).
    pub shoulder: Vector3<f64>,
    pub reach: f64,
}

impl Default for IkConfig {
    fn default() -> Self {
        Self {
            position_tolerance: 1e-3,
            orientation_tolerance: 0.01,
            position_precision: 1e-5,
            orientation_precision: 1e-5,
            max_iterations: 150,
            restarts: 24,
            damping: 1e-4,
            limit_margin: 0.01,
            neutral: JointVector::from_column_slice(&[
                0.0,
                -FRAC_PI_4,
                0.0,
                -3.0 * FRAC_PI_4,
                0.0,
                FRAC_PI_2,
                FRAC_PI_4,
            ]),
            nullspace_gain: 0.05,
            shoulder: Vector3::new(0.0, 0.0, 0.333),
            // Upper arm 0.316 + forearm 0.384 (+ 0.0825 offsets) + flange 0.107 + TCP 0.1034.
            reach: 0.316 + (0.384f64.powi(2) + 0.0825f64.powi(2)).sqrt() + 0.088 + 0.107 + 0.1034,
        }
    }
}

/// A joint goal and how well it reaches the pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkSolution {
    pub q: JointVector,
    pub position_error: f64,
    pub orientation_error: f64,
    pub iterations: usize,
    /// 0 = converged from the seed.
    pub restarts: usize,
}

/// A keyframe pose from its JSON form (position in m, quaternion [w, x, y, z]), validated.
pub fn target_pose(position: [f64; 3], quat_wxyz: [f64; 4]) -> Result<Isometry3<f64>, IkError> {
    if position.iter().any(|v| !v.is_finite()) {
        return Err(IkError::NonFinite("position"));
    }
    if quat_wxyz.iter().any(|v| !v.is_finite()) {
        return Err(IkError::NonFinite("quaternion"));
    }
    let q = Quaternion::new(quat_wxyz[0], quat_wxyz[1], quat_wxyz[2], quat_wxyz[3]);
    let norm = q.norm();
    if (norm - 1.0).abs() > 1e-3 {
        return Err(IkError::NotUnitQuaternion { norm });
    }
    Ok(Isometry3::from_parts(
        Translation3::new(position[0], position[1], position[2]),
        UnitQuaternion::from_quaternion(q),
    ))
}

/// The solver: configuration and the limits it respects.
#[derive(Debug, Clone)]
pub struct InverseKinematics {
    pub config: IkConfig,
    limits: JointLimits,
}

impl InverseKinematics {
    pub fn new(config: IkConfig, limits: JointLimits) -> Self {
        Self { config, limits }
    }

    /// Joint goal for `target` (TCP in the base frame), starting from `seed`.
    pub fn solve(
        &self,
        kin: &mut Kinematics,
        target: &Isometry3<f64>,
        seed: &JointVector,
    ) -> Result<IkSolution, IkError> {
        let c = &self.config;
        if target.translation.vector.iter().chain(target.rotation.coords.iter()).any(|v| !v.is_finite()) {
            return Err(IkError::NonFinite("pose"));
        }
        let distance = (target.translation.vector - c.shoulder).norm();
        if distance > c.reach {
            return Err(IkError::OutOfReach { distance, reach: c.reach });
        }
        let mut rng = rand::rngs::StdRng::seed_from_u64(restart_seed(target));
        let mut best: Option<IkSolution> = None;
        let mut chosen: Option<(f64, IkSolution)> = None;
        let mut found = 0;
        let mut total_iterations = 0;
        for attempt in 0..c.restarts + 2 {
            let start = match attempt {
                0 => self.limits.clamp(seed, c.limit_margin),
                1 => self.limits.clamp(&c.neutral, c.limit_margin),
                _ => JointVector::from_fn(|i, _| {
                    rng.random_range(
                        self.limits.position_min[i] + c.limit_margin..self.limits.position_max[i] - c.limit_margin,
                    )
                }),
            };
            let mut s = self.descend(kin, target, start)?;
            total_iterations += s.iterations;
            s.iterations = total_iterations;
            s.restarts = attempt;
            if s.position_error <= c.position_tolerance && s.orientation_error <= c.orientation_tolerance {
                // A solution near the seed and away from the limits is taken at once; otherwise
                // a few solutions compete on that same cost (arm branches differ a lot).
                let cost = self.branch_cost(&s.q, seed);
                if attempt == 0 && (s.q - seed).abs().max() < 0.5 && cost < 1.0 {
                    return Ok(s);
                }
                found += 1;
                if chosen.as_ref().is_none_or(|(best_cost, _)| cost < *best_cost) {
                    chosen = Some((cost, s));
                }
                if found >= CANDIDATES {
                    break;
                }
                continue;
            }
            let score = |x: &IkSolution| x.position_error + 0.1 * x.orientation_error;
            if best.as_ref().is_none_or(|b| score(&s) < score(b)) {
                best = Some(s);
            }
        }
        if let Some((_, s)) = chosen {
            return Ok(s);
        }
        let b = best.expect("at least one attempt ran");
        Err(IkError::Unreachable {
            position_error_mm: b.position_error * 1e3,
            orientation_error_deg: b.orientation_error.to_degrees(),
        })
    }

    /// A solution that continues from `seed` (one descent, no restarts), for points along a
    /// path: it fails rather than jump to another arm branch (no joint moves more than
    /// `max_step` rad).
    pub fn solve_near(
        &self,
        kin: &mut Kinematics,
        target: &Isometry3<f64>,
        seed: &JointVector,
        max_step: f64,
    ) -> Result<IkSolution, IkError> {
        let c = &self.config;
        let s = self.descend(kin, target, self.limits.clamp(seed, c.limit_margin))?;
        let converged = s.position_error <= c.position_tolerance && s.orientation_error <= c.orientation_tolerance;
        if converged && (s.q - seed).abs().max() <= max_step {
            Ok(s)
        } else {
            Err(IkError::Unreachable {
                position_error_mm: s.position_error * 1e3,
                orientation_error_deg: s.orientation_error.to_degrees(),
            })
        }
    }

    /// How undesirable a solution is: joint travel from the seed, plus a penalty for joints
    /// within 0.3 rad of a limit.
    fn branch_cost(&self, q: &JointVector, seed: &JointVector) -> f64 {
        let travel = (q - seed).norm_squared();
        let near_limit: f64 = (0..7)
            .map(|i| {
                let d = (q[i] - self.limits.position_min[i]).min(self.limits.position_max[i] - q[i]);
                10.0 * (0.3 - d).max(0.0).powi(2)
            })
            .sum();
        travel + near_limit
    }

    /// One Levenberg-Marquardt descent from `q`: a step is kept only if it lowers the error
    /// (else the damping grows); joints resting on a limit and pushed outward are frozen for the
    /// step (their Jacobian column is removed) instead of stalling the others.
    fn descend(
        &self,
        kin: &mut Kinematics,
        target: &Isometry3<f64>,
        mut q: JointVector,
    ) -> Result<IkSolution, IkError> {
        let c = &self.config;
        let lo = self.limits.position_min.add_scalar(c.limit_margin);
        let hi = self.limits.position_max.add_scalar(-c.limit_margin);
        let (tcp, mut jac) = kin.tcp_and_jacobian(&q)?;
        let mut e = pose_error(target, &tcp);
        let mut lambda = c.damping;
        let mut iterations = 0;
        let done = |e: &nalgebra::Vector6<f64>| (e.fixed_rows::<3>(0).norm(), e.fixed_rows::<3>(3).norm());
        loop {
            let (ep, er) = done(&e);
            if (ep < c.position_precision && er < c.orientation_precision) || iterations >= c.max_iterations {
                return Ok(IkSolution { q, position_error: ep, orientation_error: er, iterations, restarts: 0 });
            }
            iterations += 1;
            let mut j = jac;
            let mut step = JointVector::zeros();
            for _ in 0..2 {
                // dq = J^T (J J^T + lambda I)^-1 e, plus the neutral pull projected into J's nullspace.
                let Some(chol) = (j * j.transpose() + Matrix6::identity() * lambda).cholesky() else { break };
                let pull = (c.neutral - q) * c.nullspace_gain;
                step = j.transpose() * chol.solve(&e) + pull - j.transpose() * chol.solve(&(j * pull));
                let mut frozen = false;
                for i in 0..7 {
                    let blocked = (q[i] <= lo[i] + 1e-9 && step[i] < 0.0) || (q[i] >= hi[i] - 1e-9 && step[i] > 0.0);
                    if blocked && j.column(i).iter().any(|v| *v != 0.0) {
                        j.column_mut(i).fill(0.0);
                        frozen = true;
                    }
                }
                if !frozen {
                    break;
                }
            }
            let candidate = (q + step).zip_zip_map(&lo, &hi, |v, l, h| v.clamp(l, h));
            let (t, jc) = kin.tcp_and_jacobian(&candidate)?;
            let ec = pose_error(target, &t);
            if ec.norm() < e.norm() {
                (q, jac, e) = (candidate, jc, ec);
                lambda = (lambda * 0.5).max(1e-8);
            } else {
                lambda *= 10.0;
                if lambda > 1e2 {
                    let (ep, er) = done(&e);
                    return Ok(IkSolution { q, position_error: ep, orientation_error: er, iterations, restarts: 0 });
                }
            }
        }
    }
}

/// Solutions compared when the seed's own is far or near a limit.
const CANDIDATES: usize = 4;

/// A deterministic seed per target, so a given pose always gets the same restarts.
fn restart_seed(target: &Isometry3<f64>) -> u64 {
    target
        .translation
        .vector
        .iter()
        .chain(target.rotation.coords.iter())
        .fold(0xcbf2_9ce4_8422_2325u64, |h, v| (h ^ v.to_bits()).wrapping_mul(0x0100_0000_01b3))
}
