//! The simulated world. `sim` is the only module that talks to MuJoCo: it composes the scene,
//! steps the physics at 1 kHz, reads and writes the arm's state, and renders the cameras into
//! RGB, depth and world-frame point clouds; it also records videos and exports the arm's
//! description for the controller's Pinocchio model.
pub mod arm_export;
pub mod backend;
pub mod camera;
pub mod cloud;
mod error;
pub mod image;
pub mod logging;
pub mod recorder;
pub mod scene;
pub mod world;

pub use crate::robot::JointVector;
pub use arm_export::ArmDynamicsReference;
pub use camera::{CameraRig, Intrinsics, RgbdFrame, Visuals};
pub use cloud::{PointCloud, Workspace};
pub use error::SimError;
pub use recorder::Video;
pub use world::{ArmState, SceneObject, World};
