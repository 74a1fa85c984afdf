//! A real Franka arm (Panda or FR3) as a [`crate::control::backend::RobotBackend`], through the
//! pure-Rust `franka-rs` client (cargo feature `franka`): the robot's 1 kHz packets pace the
//! control callback, one continuous torque session carries a whole run, every command passes
//! the [`guard::TorqueGuard`] (finite, inside the rated torques, within the torque-rate limit of
//! what the robot last received), reflexes and communication aborts become typed
//! [`crate::control::backend::BackendError`]s, the hand is driven from a worker thread and the
//! collision thresholds come from a TOML profile ([`collision::CollisionProfile`]).
//!
//! The guard, the profile and the robot models build without the feature, so they are tested
//! everywhere; the connection itself needs `--features franka`.
#[cfg(feature = "franka")]
mod backend;
pub mod collision;
#[cfg(feature = "franka")]
mod gripper;
pub mod guard;

#[cfg(feature = "franka")]
pub use backend::{FrankaBackend, FrankaOptions, SessionFigures};

use crate::robot::JointLimits;
use crate::unit_config::ConfigError;

/// Which Franka arm: decides the protocol version and the joint limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FrankaRobot {
    /// Franka Emika Panda (FER), FCI v5, `controllers/panda_limits.toml`.
    Panda,
    /// Franka Research 3, FCI v10, `controllers/fr3_limits.toml`.
    Fr3,
}

impl FrankaRobot {
    /// The arm's joint limits, from `controllers/`.
    pub fn limits(self) -> Result<JointLimits, ConfigError> {
        match self {
            FrankaRobot::Panda => JointLimits::panda(),
            FrankaRobot::Fr3 => JointLimits::load(&crate::deps::controllers_dir().join("fr3_limits.toml")),
        }
    }
}
