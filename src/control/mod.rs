//! Everything that runs every keyframe or every 1 ms tick: IK, the jerk-limited trajectory,
//! the operational-space controller (a QP solved with OSQP), the gripper, the keyframe file
//! format, straight-line waypoints, the limit monitor, and the runner that sequences keyframes
//! on a robot backend. `control` knows neither MuJoCo nor Pinocchio: it sees the arm
//! through `robot::Kinematics` and the [`backend::RobotBackend`] trait.
pub mod backend;
pub mod controller;
pub mod execution;
pub mod gripper;
pub mod ik;
pub mod keyframe;
pub mod monitor;
pub mod osc;
pub mod osc_config;
pub mod pose_error;
pub mod runner;
pub mod trajectory;
pub mod tuning;
pub mod waypoints;
