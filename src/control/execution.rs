//! One keyframe's execution, tick by tick: feed its straight-line joint goals to the trajectory,
//! wait until the TCP has settled on the target (or the settle time-out passes), then open or
//! close the gripper if the keyframe asks for it and wait until the fingers stop. The lock-step
//! [`super::runner::Runner`] and the real-time runtime's control thread both drive it, one call
//! of [`Execution::before_tick`] and [`Execution::after_tick`] around each controller tick, so a
//! keyframe is executed the same way in both. Nothing here allocates: a [`MotionPlan`] is a
//! fixed-size value that can cross a lock-free queue.
use nalgebra::{Isometry3, Vector6};

use super::backend::RobotState;
use super::controller::ArmController;
use super::gripper::{GraspState, Gripper};
use super::pose_error::pose_error;
use super::waypoints::WAYPOINT_SWITCH;
use crate::robot::{JointLimits, JointVector};

/// Most joint goals one motion may have (the straight-line waypoints stop at 100).
pub const MAX_WAYPOINTS: usize = 100;

/// Consecutive settled ticks that count as arrived.
const SETTLED_TICKS: u32 = 50;

/// A planned keyframe: the TCP target (base frame), the joint goals that lead there and the
/// gripper state once it is reached.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionPlan {
    pub target: Isometry3<f64>,
    pub gripper_open: bool,
    goals: [JointVector; MAX_WAYPOINTS],
    len: usize,
}

/// Why joint goals cannot form a plan.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum PlanError {
    #[error("a motion needs 1 to {MAX_WAYPOINTS} joint goals, got {0}")]
    GoalCount(usize),
    #[error("joint goal {index} is not finite or lies outside the joint limits")]
    OutsideLimits { index: usize },
    #[error("the target pose is not finite")]
    NonFiniteTarget,
}

impl MotionPlan {
    pub fn new(target: Isometry3<f64>, goals: &[JointVector], gripper_open: bool) -> Result<Self, PlanError> {
        if goals.is_empty() || goals.len() > MAX_WAYPOINTS {
            return Err(PlanError::GoalCount(goals.len()));
        }
        let mut plan = Self { target, gripper_open, goals: [JointVector::zeros(); MAX_WAYPOINTS], len: goals.len() };
        plan.goals[..goals.len()].copy_from_slice(goals);
        Ok(plan)
    }

    pub fn goals(&self) -> &[JointVector] {
        &self.goals[..self.len]
    }

    /// Rejects a plan the arm must not follow: a non-finite target, or a goal that is not finite
    /// or lies outside `limits`' joint range. Cheap enough for the control tick.
    pub fn check(&self, limits: &JointLimits) -> Result<(), PlanError> {
        let t = &self.target;
        if !(t.translation.vector.iter().all(|v| v.is_finite()) && t.rotation.coords.iter().all(|v| v.is_finite())) {
            return Err(PlanError::NonFiniteTarget);
        }
        for (index, q) in self.goals().iter().enumerate() {
            let inside =
                (0..7).all(|i| q[i].is_finite() && q[i] >= limits.position_min[i] && q[i] <= limits.position_max[i]);
            if !inside {
                return Err(PlanError::OutsideLimits { index });
            }
        }
        Ok(())
    }
}

/// Where an execution is.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    Moving,
    /// The collision reflex fired; the arm is told to back off at the next tick.
    ReflexPending,
    /// Backing off after the reflex.
    Stopping {
        since: f64,
    },
    /// Settled; the gripper command is applied at the next tick.
    GripperPending,
    Gripper {
        since: f64,
    },
    Done,
}

/// How an execution ended.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExecutionOutcome {
    /// TCP error (position m, rotation rad; target frame) when the motion settled or timed out,
    /// before the gripper moved.
    pub error: Vector6<f64>,
    /// What the gripper did, if the keyframe changed its state.
    pub gripper: Option<GraspState>,
    /// The collision reflex stopped the motion (the gripper was then left as it was).
    pub reflex: Option<Reflex>,
}

/// Why the collision reflex fired: the first joint whose external torque exceeded its threshold.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reflex {
    /// Joint index, 0 (base) to 6.
    pub joint: usize,
    /// External torque there (Nm) and the threshold.
    pub torque: f64,
    pub threshold: f64,
}

impl std::fmt::Display for Reflex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "stopped by the collision reflex and backed off: external torque {:.1} Nm on joint {} (threshold {:.1} Nm)",
            self.torque,
            self.joint + 1,
            self.threshold
        )
    }
}

/// After the reflex, the arm counts as backed off once its trajectory has ended and it moves
/// slower than this (rad/s), or after [`REFLEX_STOP_TIMEOUT`] seconds.
const REFLEX_STILL: f64 = 0.01;
const REFLEX_STOP_TIMEOUT: f64 = 3.0;

impl ExecutionOutcome {
    /// Whether the keyframe was reached: settled within the profile's tolerances, and not
    /// stopped by the collision reflex.
    pub fn reached(&self, config: &super::osc_config::OscConfig) -> bool {
        self.reflex.is_none()
            && self.position_error() <= config.reached_position
            && self.rotation_error() <= config.reached_orientation
    }

    /// Why the keyframe was not reached (`None` if it was).
    pub fn problem(&self, config: &super::osc_config::OscConfig) -> Option<String> {
        let (ep, er) = (self.position_error() * 1e3, self.rotation_error().to_degrees());
        match self.reflex {
            Some(reflex) => Some(format!("{reflex}, {ep:.2} mm from the keyframe")),
            None => (!self.reached(config)).then(|| format!("settled {ep:.2} mm / {er:.3} deg from the keyframe")),
        }
    }

    pub fn position_error(&self) -> f64 {
        self.error.fixed_rows::<3>(0).norm()
    }

    pub fn rotation_error(&self) -> f64 {
        self.error.fixed_rows::<3>(3).norm()
    }
}

/// One keyframe being executed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Execution {
    plan: MotionPlan,
    next: usize,
    settle_start: Option<f64>,
    within: u32,
    error: Vector6<f64>,
    actuate: bool,
    gripper_timeout: f64,
    grasp: Option<GraspState>,
    reflex: Option<Reflex>,
    /// The measured joints when the motion started: where the collision reflex backs off to.
    start: Option<crate::robot::JointVector>,
    phase: Phase,
}

impl Execution {
    /// Starts `plan`; the gripper is actuated after the motion if its commanded state differs
    /// from the plan's, and given at most `gripper_timeout` seconds to settle.
    pub fn start(plan: MotionPlan, gripper: &Gripper, gripper_timeout: f64) -> Self {
        Self {
            actuate: plan.gripper_open != gripper.is_open_commanded(),
            plan,
            next: 0,
            settle_start: None,
            within: 0,
            error: Vector6::zeros(),
            gripper_timeout,
            grasp: None,
            reflex: None,
            start: None,
            phase: Phase::Moving,
        }
    }

    pub fn plan(&self) -> &MotionPlan {
        &self.plan
    }

    pub fn is_done(&self) -> bool {
        self.phase == Phase::Done
    }

    /// The outcome once [`Execution::is_done`].
    pub fn outcome(&self) -> ExecutionOutcome {
        ExecutionOutcome { error: self.error, gripper: self.grasp, reflex: self.reflex }
    }

    /// Call before the controller's tick: feeds the next waypoint as soon as the reference nears
    /// the current one (so the motion flows through them), or starts the gripper.
    pub fn before_tick(&mut self, controller: &mut ArmController, gripper: &mut Gripper, state: &RobotState) {
        match self.phase {
            Phase::Moving => {
                self.start.get_or_insert(state.q);
                let goals = self.plan.goals();
                if self.next < goals.len()
                    && (self.next == 0 || (controller.reference().q - goals[self.next - 1]).norm() < WAYPOINT_SWITCH)
                {
                    controller.set_goal(&goals[self.next]);
                    self.next += 1;
                }
            }
            Phase::ReflexPending => {
                // Back off to where the motion started (free of the contact, as the arm came
                // from there), rather than hold: holding in contact keeps the obstacle pushing
                // on joints weaker than the ones pressing. The reference first jumps to the
                // measured joints: it was still driving into the obstacle (a jerk-limited
                // trajectory takes about 0.5 s to turn), and pressing on while backing off piled
                // up torque that, when the hand slipped free, whipped joints 1 and 3 past their
                // velocity limits (37 of 1000 fault runs; the README's "bench faults").
                controller.jump_reference(&state.q);
                controller.set_goal(&self.start.unwrap_or(state.q));
                self.phase = Phase::Stopping { since: state.time };
            }
            Phase::GripperPending => {
                controller.set_gripper(self.plan.gripper_open);
                gripper.command(self.plan.gripper_open);
                self.phase = Phase::Gripper { since: state.time };
            }
            Phase::Gripper { .. } | Phase::Stopping { .. } | Phase::Done => {}
        }
    }

    /// Call after the controller's tick with the same state. Returns true when this tick ended
    /// the execution (its command is the last one of the keyframe).
    pub fn after_tick(&mut self, controller: &ArmController, gripper: &mut Gripper, state: &RobotState) -> bool {
        match self.phase {
            Phase::Moving => {
                let c = controller.osc().config();
                self.error = pose_error(&self.plan.target, controller.tcp());
                let limit = &c.reflex_external_torque;
                if let Some(joint) = (0..7).find(|&i| c.reflex_enabled && state.tau_ext[i].abs() > limit[i]) {
                    self.reflex = Some(Reflex { joint, torque: state.tau_ext[joint].abs(), threshold: limit[joint] });
                    self.phase = Phase::ReflexPending;
                    return false;
                }
                if self.next < self.plan.len || !controller.trajectory_finished() {
                    return false;
                }
                let since = *self.settle_start.get_or_insert(state.time);
                let close = self.error.fixed_rows::<3>(0).norm() <= 0.5 * c.reached_position
                    && self.error.fixed_rows::<3>(3).norm() <= 0.5 * c.reached_orientation
                    && state.dq.norm() < 0.01;
                self.within = if close { self.within + 1 } else { 0 };
                if self.within >= SETTLED_TICKS || state.time - since >= c.settle_timeout {
                    self.phase = if self.actuate { Phase::GripperPending } else { Phase::Done };
                }
            }
            Phase::Gripper { since } => {
                let grasp = gripper.update(state);
                self.grasp = Some(grasp);
                if grasp.is_settled() || state.time - since > self.gripper_timeout {
                    self.phase = Phase::Done;
                }
            }
            Phase::Stopping { since } => {
                self.error = pose_error(&self.plan.target, controller.tcp());
                let still = controller.trajectory_finished() && state.dq.norm() < REFLEX_STILL;
                if still || state.time - since >= REFLEX_STOP_TIMEOUT {
                    self.phase = Phase::Done;
                }
            }
            Phase::GripperPending | Phase::ReflexPending | Phase::Done => {}
        }
        self.phase == Phase::Done
    }
}
