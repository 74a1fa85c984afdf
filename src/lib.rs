//! flowram: a FlowRAM keyframe policy and a real-time torque-control stack for a
//! MuJoCo-simulated Franka Panda. See README.md.
pub mod control;
pub mod data;
pub mod deps;
pub mod files;
pub mod franka;
pub mod policy;
pub mod robot;
pub mod rollout;
pub mod runtime;
pub mod sim;
pub mod stats;
pub mod tasks;
pub mod unit_config;
