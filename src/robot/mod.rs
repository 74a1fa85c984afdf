//! The arm's model: its kinematics and dynamics through Pinocchio (`pinocchio.rs` and the C++
//! shim in `shim/`), built from an [`ArmDescription`] that the simulator exports so both
//! describe the same robot, and its limits (`controllers/panda_limits.toml`).
mod limits;

pub use limits::JointLimits;

use nalgebra::SVector;

/// Seven joint values of the arm (rad, rad/s or Nm), base to flange.
pub type JointVector = SVector<f64, 7>;
