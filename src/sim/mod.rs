//! The simulated world. `sim` is the only module that talks to MuJoCo: it composes the scene,
//! steps the physics at 1 kHz, reads and writes the arm's state, and renders the cameras into
//! RGB, depth and world-frame point clouds.
pub mod backend;
pub mod camera;
pub mod cloud;
mod error;
pub mod image;
mod logging;
pub mod scene;
pub mod world;

pub use crate::robot::JointVector;
pub use camera::{CameraRig, Intrinsics, RgbdFrame, Visuals};
pub use cloud::{PointCloud, Workspace};
pub use error::SimError;
pub use world::{ArmDynamicsReference, ArmState, Video, World};
