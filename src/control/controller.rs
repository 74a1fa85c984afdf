//! The per-tick controller: the trajectory's joint reference, turned into a Cartesian
//! reference through the arm model, tracked by the OSC QP. `tick` is the real-time part: it
//! does not allocate or block, and always returns a command (a damping torque if anything in
//! it fails), with its compute time split into kinematics, trajectory and OSC.
use std::time::{Duration, Instant};

use super::backend::{Command, RobotState};
use super::osc::{JointFriction, Osc, OscSetupError, TaskReference};
use super::osc_config::OscConfig;
use super::trajectory::{JointSetpoint, JointTrajectory, MotionLimits};
use crate::robot::{JointLimits, JointVector, Kinematics};

/// Compute time of the last tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TickTiming {
    pub kinematics: Duration,
    pub trajectory: Duration,
    pub osc: Duration,
    pub total: Duration,
}

/// Counts of things that went wrong in ticks (the tick still produced a safe command).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TickFaults {
    pub kinematics: u64,
    pub trajectory: u64,
}

pub struct ArmController {
    kinematics: Kinematics,
    trajectory: JointTrajectory,
    osc: Osc,
    gripper_open: bool,
    reference: JointSetpoint,
    task: Option<TaskReference>,
    tcp: nalgebra::Isometry3<f64>,
    timing: TickTiming,
    faults: TickFaults,
}

impl std::fmt::Debug for ArmController {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ArmController").field("reference", &self.reference).field("osc", &self.osc).finish()
    }
}

impl ArmController {
    /// A controller holding the arm where `state` says it is.
    pub fn new(
        mut kinematics: Kinematics,
        limits: JointLimits,
        config: OscConfig,
        dt: f64,
        state: &RobotState,
    ) -> Result<Self, OscSetupError> {
        let motion = MotionLimits::scaled(&limits, config.velocity_scale, config.acceleration_scale, config.jerk_scale);
        let trajectory = JointTrajectory::new(&motion, dt, &state.q);
        let friction = JointFriction::of(kinematics.description());
        let mut osc = Osc::new(config, limits, friction, dt)?;
        osc.reset(&state.tau_commanded);
        let tcp = kinematics.tcp(&state.q).unwrap_or_else(|_| nalgebra::Isometry3::identity());
        Ok(Self {
            kinematics,
            trajectory,
            osc,
            gripper_open: state.gripper_width > 0.04,
            reference: JointSetpoint { q: state.q, dq: JointVector::zeros(), ddq: JointVector::zeros() },
            task: None,
            tcp,
            timing: TickTiming::default(),
            faults: TickFaults::default(),
        })
    }

    /// Plan from the current reference to a joint goal (re-plans mid-motion, continuously).
    pub fn set_goal(&mut self, goal: &JointVector) {
        self.trajectory.set_goal(goal);
    }

    /// Replace the reference by a raw step: the reference jumps to `q` at rest (for step
    /// responses; normal motion goes through `set_goal`).
    pub fn jump_reference(&mut self, q: &JointVector) {
        self.trajectory.hold(q);
    }

    pub fn set_gripper(&mut self, open: bool) {
        self.gripper_open = open;
    }

    pub fn goal(&self) -> JointVector {
        self.trajectory.goal()
    }

    /// The trajectory has arrived at its goal (the arm may still be settling).
    pub fn trajectory_finished(&self) -> bool {
        self.trajectory.is_finished()
    }

    /// The joint reference of the last tick.
    pub fn reference(&self) -> &JointSetpoint {
        &self.reference
    }

    /// The Cartesian reference of the last tick.
    pub fn task_reference(&self) -> Option<&TaskReference> {
        self.task.as_ref()
    }

    /// The measured TCP pose at the last tick (base frame).
    pub fn tcp(&self) -> &nalgebra::Isometry3<f64> {
        &self.tcp
    }

    pub fn kinematics_mut(&mut self) -> &mut Kinematics {
        &mut self.kinematics
    }

    pub fn osc(&self) -> &Osc {
        &self.osc
    }

    pub fn timing(&self) -> TickTiming {
        self.timing
    }

    pub fn faults(&self) -> TickFaults {
        self.faults
    }

    /// One control tick.
    pub fn tick(&mut self, state: &RobotState) -> Command {
        let t0 = Instant::now();
        match self.trajectory.step() {
            Ok(setpoint) => self.reference = setpoint,
            Err(_) => {
                // Keep the last reference, at rest, rather than jump.
                self.faults.trajectory += 1;
                self.trajectory.hold(&self.reference.q);
                self.reference = self.trajectory.current();
            }
        }
        let t1 = Instant::now();
        let at_reference = self.kinematics.task(&self.reference.q, &self.reference.dq);
        let measured = self.kinematics.dynamics(&state.q, &state.dq);
        let t2 = Instant::now();
        let output = match (at_reference, measured) {
            (Ok(r), Ok(m)) => {
                self.tcp = m.tcp;
                let task = TaskReference::from_joint_setpoint(&self.reference, &r);
                self.task = Some(task);
                self.osc.compute(&state.q, &state.dq, &m, &task, &state.tau_ext)
            }
            _ => {
                self.faults.kinematics += 1;
                self.osc.safe_torque(&state.dq)
            }
        };
        let t3 = Instant::now();
        self.timing = TickTiming { trajectory: t1 - t0, kinematics: t2 - t1, osc: t3 - t2, total: t3 - t0 };
        Command { tau: output.tau, gripper_open: self.gripper_open }
    }
}
