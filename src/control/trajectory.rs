//! Jerk-limited joint-space trajectories (ruckig) from the current reference state to a joint
//! goal, sampled every control tick.
//!
//! Why `rsruckig` (the pure-Rust port) and not the official `ruckig` crate (C++ through cxx):
//! the port samples without allocating (0.14 us per tick here; the official crate copies every
//! vector into C++ and back, about 15 heap allocations per update), builds in seconds instead of
//! 73 s, and gives bit-identical trajectories: `tests/trajectory.rs` keeps that check against
//! the official library. A new goal re-plans from the current *reference* position, velocity
//! and acceleration, so the reference stays continuous in velocity and acceleration.
use rsruckig::prelude::*;

use crate::robot::{JointLimits, JointVector};

/// The reference at one tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointSetpoint {
    pub q: JointVector,
    pub dq: JointVector,
    pub ddq: JointVector,
}

/// Velocity, acceleration and jerk bounds the planner uses (SI units, per joint).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionLimits {
    pub velocity: JointVector,
    pub acceleration: JointVector,
    pub jerk: JointVector,
}

impl MotionLimits {
    /// Fractions of the arm's limits (each in (0, 1]).
    pub fn scaled(limits: &JointLimits, velocity: f64, acceleration: f64, jerk: f64) -> Self {
        Self {
            velocity: limits.velocity * velocity,
            acceleration: limits.acceleration * acceleration,
            jerk: limits.jerk * jerk,
        }
    }
}

#[derive(Debug, Clone, thiserror::Error)]
#[error("trajectory planning failed: {0}")]
pub struct TrajectoryError(pub String);

/// A ruckig generator with its input and output kept between ticks (no allocation per tick).
pub struct JointTrajectory {
    otg: Ruckig<7, ThrowErrorHandler>,
    input: InputParameter<7>,
    output: OutputParameter<7>,
    finished: bool,
    duration: f64,
}

impl std::fmt::Debug for JointTrajectory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("JointTrajectory").field("finished", &self.finished).field("duration", &self.duration).finish()
    }
}

fn set(dst: &mut DataArrayOrVec<f64, 7>, v: &JointVector) {
    for i in 0..7 {
        dst[i] = v[i];
    }
}

fn get(src: &DataArrayOrVec<f64, 7>) -> JointVector {
    JointVector::from_fn(|i, _| src[i])
}

impl JointTrajectory {
    /// A generator stepping by `dt` seconds, holding still at `q`.
    pub fn new(limits: &MotionLimits, dt: f64, q: &JointVector) -> Self {
        let mut input = InputParameter::<7>::new(None);
        set(&mut input.max_velocity, &limits.velocity);
        set(&mut input.max_acceleration, &limits.acceleration);
        set(&mut input.max_jerk, &limits.jerk);
        let mut t = Self {
            otg: Ruckig::new(None, dt),
            input,
            output: OutputParameter::new(None),
            finished: true,
            duration: 0.0,
        };
        t.hold(q);
        t
    }

    /// Stop wherever the reference is asked to be: at rest at `q`.
    pub fn hold(&mut self, q: &JointVector) {
        let zero = JointVector::zeros();
        set(&mut self.input.current_position, q);
        set(&mut self.input.current_velocity, &zero);
        set(&mut self.input.current_acceleration, &zero);
        set(&mut self.input.target_position, q);
        set(&mut self.input.target_velocity, &zero);
        set(&mut self.input.target_acceleration, &zero);
        self.finished = true;
        self.duration = 0.0;
    }

    /// A new goal (at rest there). Re-plans from the current reference state on the next tick.
    pub fn set_goal(&mut self, goal: &JointVector) {
        set(&mut self.input.target_position, goal);
        self.finished = false;
    }

    pub fn goal(&self) -> JointVector {
        get(&self.input.target_position)
    }

    /// Whether the reference has arrived at the goal.
    pub fn is_finished(&self) -> bool {
        self.finished
    }

    /// Duration of the current plan (s), from its start.
    pub fn duration(&self) -> f64 {
        self.duration
    }

    /// The reference one tick later.
    pub fn step(&mut self) -> Result<JointSetpoint, TrajectoryError> {
        if self.finished {
            return Ok(self.current());
        }
        match self.otg.update(&self.input, &mut self.output) {
            Ok(RuckigResult::Working) => {}
            Ok(RuckigResult::Finished) => self.finished = true,
            Ok(other) => return Err(TrajectoryError(format!("{other:?}"))),
            Err(e) => return Err(TrajectoryError(e.to_string())),
        }
        if self.output.new_calculation {
            self.duration = self.output.trajectory.get_duration();
        }
        self.output.pass_to_input(&mut self.input);
        Ok(self.current())
    }

    /// The reference now.
    pub fn current(&self) -> JointSetpoint {
        JointSetpoint {
            q: get(&self.input.current_position),
            dq: get(&self.input.current_velocity),
            ddq: get(&self.input.current_acceleration),
        }
    }
}
