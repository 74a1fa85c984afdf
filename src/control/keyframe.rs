//! The keyframe file format: a keyframe is a TCP pose in the robot base frame and the gripper
//! state once the pose is reached; a keyframes file is the JSON `{"keyframes": [...]}` (serde,
//! unknown fields refused), readable from Python as plain JSON.
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

/// A keyframe: the TCP pose in the robot base frame (`panda_link0`, metres, quaternion
/// [w, x, y, z]) and whether the gripper is open once the pose is reached.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Keyframe {
    pub position: [f64; 3],
    pub quat_wxyz: [f64; 4],
    pub gripper_open: bool,
}

impl Keyframe {
    /// A keyframe at a pose.
    pub fn at(pose: &Isometry3<f64>, gripper_open: bool) -> Self {
        let t = pose.translation.vector;
        let q = pose.rotation.quaternion();
        Self { position: [t.x, t.y, t.z], quat_wxyz: [q.w, q.i, q.j, q.k], gripper_open }
    }
}

/// The keyframes file: `{"keyframes": [...]}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeyframeFile {
    pub keyframes: Vec<Keyframe>,
}

/// Why a keyframes file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum KeyframeFileError {
    #[error("cannot read the keyframes file {}", path.display())]
    Read { path: std::path::PathBuf, source: std::io::Error },
    #[error(
        "{} is not a keyframes file ({source}); expected {{\"keyframes\":[{{\"position\":[x,y,z],\"quat_wxyz\":[w,x,y,z],\"gripper_open\":true}}, ...]}}",
        path.display()
    )]
    Format { path: std::path::PathBuf, source: serde_json::Error },
    #[error("{} has no keyframes", path.display())]
    Empty { path: std::path::PathBuf },
}

impl KeyframeFile {
    /// Reads a keyframes file; it must hold at least one keyframe.
    pub fn read(path: &std::path::Path) -> Result<Self, KeyframeFileError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| KeyframeFileError::Read { path: path.to_path_buf(), source })?;
        let file: KeyframeFile = serde_json::from_str(&text)
            .map_err(|source| KeyframeFileError::Format { path: path.to_path_buf(), source })?;
        if file.keyframes.is_empty() {
            return Err(KeyframeFileError::Empty { path: path.to_path_buf() });
        }
        Ok(file)
    }
}
