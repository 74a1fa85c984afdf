//! What the threads of a real-time run hand each other. Every message is a fixed-size `Copy`
//! value, so the queues between threads (`rtrb` ring buffers, allocated when the run starts)
//! never allocate and dropping a message never frees memory on the control thread.
use crate::control::backend::RobotState;
use crate::control::execution::{ExecutionOutcome, MotionPlan};
use crate::control::keyframe::Keyframe;
use crate::robot::JointVector;

/// Control -> policy: the next keyframe is wanted; `state` is the arm at tick `tick` and
/// `gripper_open` the gripper's commanded state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Request {
    pub id: u64,
    pub tick: u64,
    pub state: RobotState,
    pub gripper_open: bool,
}

/// What the keyframe source answers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Answer {
    /// Go to this keyframe (base frame).
    Keyframe(Keyframe),
    /// The source failed to produce one (the arm holds).
    Failed,
    /// The episode is over (the task is solved, or the source has nothing more).
    Finish,
}

/// Policy -> planner: the answer to request `request`, to be planned from the joint positions
/// `from` (the arm at the request, at rest).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Proposal {
    pub request: u64,
    pub answer: Answer,
    pub from: JointVector,
}

/// What the planner made of an answer.
// Fixed size on purpose: a boxed plan would be freed on the control thread.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PlanOutcome {
    Plan(MotionPlan),
    Rejected(Rejection),
    Finish,
}

/// Why the planner refused a keyframe (the arm holds where it is).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Rejection {
    /// The policy returned an error instead of a keyframe.
    PolicyFailed,
    /// NaN or infinite position or quaternion.
    NonFinite,
    /// The quaternion's norm is not 1 (within 1e-3).
    NotUnitQuaternion,
    /// The position lies outside the run's workspace box.
    OutsideWorkspace,
    /// No IK solution within the joint limits.
    Unreachable,
    /// The plan failed the control thread's own check (joint limits, finite values).
    BadPlan,
}

impl Rejection {
    pub const ALL: [Rejection; 6] = [
        Rejection::PolicyFailed,
        Rejection::NonFinite,
        Rejection::NotUnitQuaternion,
        Rejection::OutsideWorkspace,
        Rejection::Unreachable,
        Rejection::BadPlan,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Rejection::PolicyFailed => "policy_failed",
            Rejection::NonFinite => "non_finite",
            Rejection::NotUnitQuaternion => "not_unit_quaternion",
            Rejection::OutsideWorkspace => "outside_workspace",
            Rejection::Unreachable => "unreachable",
            Rejection::BadPlan => "bad_plan",
        }
    }
}

/// Planner -> control: the plan for request `request`, or why there is none.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanMessage {
    pub request: u64,
    pub outcome: PlanOutcome,
}

/// Control -> logger: one tick's timing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TickRecord {
    pub tick: u64,
    /// From waking to the command being ready: hand-offs, keyframe execution, controller,
    /// limit check (ns). On hardware this is all the tick computes.
    pub compute_ns: u32,
    /// Applying the command: one MuJoCo step in simulation, sending the packet on hardware (ns).
    pub backend_ns: u32,
    /// How late the thread woke after the tick's release (ns).
    pub wake_late_ns: u32,
    /// The tick blocked waiting for a plan (only the simulated-latency mode ever does).
    pub waited: bool,
}

/// Control -> logger: what happened, at which tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Event {
    Requested {
        request: u64,
        tick: u64,
    },
    PlanStarted {
        request: u64,
        tick: u64,
    },
    Rejected {
        request: u64,
        tick: u64,
        why: Rejection,
    },
    KeyframeDone {
        request: u64,
        tick: u64,
        outcome: ExecutionOutcome,
    },
    /// No answer to `request` for `ticks` ticks: the arm holds and the run ends.
    WatchdogHold {
        request: u64,
        tick: u64,
        ticks: u64,
    },
}

/// Control -> anyone: the latest state (a triple buffer: the reader always gets the newest).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Status {
    pub tick: u64,
    pub state: RobotState,
    /// The request whose plan is executing, if any.
    pub executing: Option<u64>,
    /// Keyframes finished so far.
    pub keyframes_done: u64,
    pub finished: bool,
}
