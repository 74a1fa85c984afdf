//! Errors of the simulation layer.
use std::path::PathBuf;

use crate::deps::MissingDependency;

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    MissingDependency(#[from] MissingDependency),

    #[error("scene file {path} not found: pass a scene name from models/ (e.g. `default`) or a path to an MJCF file")]
    SceneNotFound { path: PathBuf },

    #[error("MuJoCo could not load {path}: {message}")]
    Load { path: PathBuf, message: String },

    #[error("the scene {path} is missing `{name}` ({kind}); flowram's scenes need it (see models/scene.xml)")]
    MissingElement { path: PathBuf, kind: &'static str, name: String },

    #[error("unknown camera `{name}`; valid cameras: {valid}")]
    UnknownCamera { name: String, valid: String },

    #[error("unknown {kind} `{name}`; valid names: {valid}")]
    UnknownName { kind: &'static str, name: String, valid: String },

    #[error("body `{name}` has no free joint, so its pose cannot be set; give it <freejoint/> in the MJCF")]
    NotFreeBody { name: String },

    #[error("invalid {what}: {detail}")]
    InvalidInput { what: &'static str, detail: String },

    #[error("offscreen rendering failed: {0}")]
    Render(String),
}
