//! The robot as the controller sees it: a torque-controlled arm with a real-time callback,
//! shaped like libfranka's: every period (1 ms) the robot reports its state and the controller
//! returns joint torques (gravity excluded: the robot compensates it) and the gripper command.
//! MuJoCo's `World` implements it (`sim::backend`); a real Panda is another implementation.
use crate::robot::JointVector;

/// What the arm reports every cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotState {
    /// Time since the backend started (s).
    pub time: f64,
    /// Joint positions (rad) and velocities (rad/s).
    pub q: JointVector,
    pub dq: JointVector,
    /// Torques the joints applied last cycle (Nm).
    pub tau: JointVector,
    /// Distance between the fingers (m) and its rate of change (m/s).
    pub gripper_width: f64,
    pub gripper_speed: f64,
}

/// What the controller sends every cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Command {
    /// Joint torques (Nm), gravity compensation excluded.
    pub tau: JointVector,
    /// Open (true) or close (false) the gripper.
    pub gripper_open: bool,
}

/// The callback's answer: keep going with this command, or apply it and end the loop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Cycle {
    Continue(Command),
    Finish(Command),
}

#[derive(Debug, thiserror::Error)]
pub enum BackendError {
    #[error("the robot refused the command: {0}")]
    Rejected(String),
}

/// A torque-controlled arm.
pub trait RobotBackend {
    /// The control period (s).
    fn period(&self) -> f64;

    /// The state now.
    fn read_state(&self) -> RobotState;

    /// Applies `command` for one period and returns the state at the end of it.
    fn cycle(&mut self, command: &Command) -> Result<RobotState, BackendError>;

    /// Runs `callback` once per period until it returns [`Cycle::Finish`]: the real-time
    /// contract (state in, torques out). The callback must not block or allocate.
    fn control<F>(&mut self, mut callback: F) -> Result<RobotState, BackendError>
    where
        F: FnMut(&RobotState) -> Cycle,
        Self: Sized,
    {
        let mut state = self.read_state();
        loop {
            match callback(&state) {
                Cycle::Continue(command) => state = self.cycle(&command)?,
                Cycle::Finish(command) => return self.cycle(&command),
            }
        }
    }
}
