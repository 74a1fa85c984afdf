//! The arm's model: kinematics and dynamics through Pinocchio (`pinocchio.rs` over the C++ shim
//! in `shim/`), built from an [`ArmDescription`] that the simulator exports so both describe the
//! same robot; and the arm's limits (`controllers/panda_limits.toml`).
mod description;
mod limits;
mod pinocchio;

pub use description::{ArmDescription, BodyInertia, LinkDescription};
pub use limits::JointLimits;
pub use pinocchio::{Dynamics, Jacobian, JointMatrix, Kinematics, KinematicsError, ModelError, TaskKinematics};

use nalgebra::SVector;

/// Seven joint values of the arm (rad, rad/s or Nm), base to flange.
pub type JointVector = SVector<f64, 7>;
