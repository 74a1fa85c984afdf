//! The robot as the controller sees it: a torque-controlled arm with a real-time callback,
//! shaped like libfranka's: every period (1 ms) the robot reports its state and the controller
//! returns joint torques (gravity excluded: the robot compensates it) and the gripper command.
//! MuJoCo's `World` implements it (`sim::backend`); a real Panda is another implementation.
use crate::robot::JointVector;

/// What the arm reports every cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotState {
    /// The robot's clock (s): simulated time in MuJoCo, the time stamp of the robot's state
    /// packet on hardware (from the first state this client read).
    pub time: f64,
    /// Joint positions (rad) and velocities (rad/s).
    pub q: JointVector,
    pub dq: JointVector,
    /// Torques the joints applied last cycle (Nm).
    pub tau: JointVector,
    /// Distance between the fingers (m) and its rate of change (m/s).
    pub gripper_width: f64,
    pub gripper_speed: f64,
    /// The torques the robot received as last command (Nm, gravity excluded): what torque-rate
    /// limits are measured against.
    pub tau_commanded: JointVector,
    /// External torque on each joint (Nm): what the environment (contacts, a joint's end stop)
    /// exerts; the robot's estimate (`tau_ext_hat_filtered`) on a Franka, the constraint
    /// forces in MuJoCo. What the collision reflex watches.
    pub tau_ext: JointVector,
    /// Fraction of the last 100 command cycles that reached the robot in time (1 in simulation).
    pub command_success_rate: f64,
    /// What the robot is doing.
    pub mode: RobotMode,
    /// Error flags the robot reports now, bit i = libfranka's error i (`franka::ERROR_NAMES`,
    /// e.g. bit 0 joint_position_limits_violation); 0 in simulation.
    pub errors: u64,
}

/// The robot's mode (libfranka's `RobotMode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RobotMode {
    /// Under external control (a torque session runs; always so in simulation).
    Move,
    /// Ready, no motion running.
    Idle,
    /// A reflex (collision, limit) stopped the robot; automatic error recovery clears it.
    Reflex,
    /// The user stop is pressed.
    UserStopped,
    /// Recovering from an error.
    AutomaticErrorRecovery,
    /// Anything else (hand guiding, other).
    Other,
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
    /// The robot stopped the motion on a reflex (collision, joint or torque limit); its error
    /// flags are named. `recover` (automatic error recovery) clears it on a Franka.
    #[error("the robot stopped on a reflex ({errors}): {detail}")]
    Reflex { errors: String, detail: String },
    /// Commands stopped reaching the robot in time (a communication-constraints abort) or the
    /// connection was lost.
    #[error("communication with the robot failed: {0}")]
    Communication(String),
    /// The connection could not be made (address, FCI not enabled, another client).
    #[error("could not connect to the robot at {address}: {detail}")]
    Connect { address: String, detail: String },
    /// The controller produced a non-finite torque; the session was ended with the last finite
    /// command ramped toward zero.
    #[error("the controller produced a non-finite torque on joint {joint}; the motion was stopped")]
    NonFiniteTorque { joint: usize },
    /// The operation is not one this backend offers.
    #[error("{0}")]
    Unsupported(&'static str),
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
