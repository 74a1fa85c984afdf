//! flowram: a FlowRAM keyframe policy and a real-time torque-control stack for a
//! MuJoCo-simulated Franka Panda. See DESIGN.md in the shared folder and README.md.
pub mod deps;
pub mod files;
pub mod sim;
