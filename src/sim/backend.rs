//! The MuJoCo world as a torque-controlled robot backend: each cycle applies the torques and
//! the gripper command, steps the physics once (1 ms) and reads the arm back.
use crate::control::backend::{BackendError, Command, RobotBackend, RobotMode, RobotState};

use super::{SimError, World};

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
            // MuJoCo applies every command in time and exactly (the motors' ranges are the
            // rated torques, which the controller stays inside).
            tau_commanded: s.tau,
            tau_ext: s.tau_ext,
            command_success_rate: 1.0,
            mode: RobotMode::Move,
            errors: 0,
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

/// A world without a video recorder, movable to another thread (the real-time runtime's control
/// thread). A recording world cannot move: its renderer's EGL context belongs to the thread
/// that made it.
#[derive(Debug)]
pub struct DetachedWorld(World);

// SAFETY: everything a World owns besides the recorder is Send (MuJoCo's model and data are
// plain memory owned by the world; mujoco-rs marks MjData Send); `World::detach` only builds a
// DetachedWorld when the recorder is absent, and none can be attached while detached.
unsafe impl Send for DetachedWorld {}

impl World {
    /// This world as a backend for another thread; refused while a video is being recorded.
    pub fn detach(self) -> Result<DetachedWorld, SimError> {
        if self.recorder.is_some() {
            return Err(SimError::InvalidInput {
                what: "world",
                detail: "a world that records video cannot move to the control thread; finish the recording first"
                    .into(),
            });
        }
        Ok(DetachedWorld(self))
    }
}

impl DetachedWorld {
    pub fn world(&self) -> &World {
        &self.0
    }

    pub fn into_world(self) -> World {
        self.0
    }
}

impl RobotBackend for DetachedWorld {
    fn period(&self) -> f64 {
        self.0.period()
    }

    fn read_state(&self) -> RobotState {
        self.0.read_state()
    }

    fn cycle(&mut self, command: &Command) -> Result<RobotState, BackendError> {
        self.0.cycle(command)
    }
}
