//! The MuJoCo world as a torque-controlled robot backend: each cycle applies the torques and
//! the gripper command, steps the physics once (1 ms) and reads the arm back.
use crate::control::backend::{BackendError, Command, RobotBackend, RobotState};

use super::World;

impl RobotBackend for World {
    fn period(&self) -> f64 {
        self.timestep()
    }

    fn read_state(&self) -> RobotState {
        let s = self.arm_state();
        let [v1, v2] = self.finger_velocities();
        RobotState {
            time: s.time,
            q: s.q,
            dq: s.dq,
            tau: s.tau,
            gripper_width: s.gripper_width,
            gripper_speed: v1 + v2,
        }
    }

    fn cycle(&mut self, command: &Command) -> Result<RobotState, BackendError> {
        self.apply_torques(&command.tau).map_err(|e| BackendError::Rejected(e.to_string()))?;
        self.set_gripper(if command.gripper_open { 1.0 } else { 0.0 })
            .map_err(|e| BackendError::Rejected(e.to_string()))?;
        self.step();
        Ok(self.read_state())
    }
}
