//! Errors of the policy (FlowRAM) module.
use std::path::PathBuf;

/// Everything that can go wrong in the policy: tensor errors, bad shapes or
/// configuration, unreadable files. Messages say what was expected and what
/// to do.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    /// A caller passed something out of contract (shape, range, size).
    #[error("{0}")]
    Invalid(String),
    /// A file could not be read or written, or its content is wrong.
    #[error("{}: {message}", path.display())]
    File { path: PathBuf, message: String },
    /// A native dependency (the text encoder's weights) is not installed.
    #[error(transparent)]
    MissingDependency(#[from] crate::deps::MissingDependency),
    /// A new training run was started in a folder that already holds checkpoints.
    #[error("{}: this run already has checkpoints", run.display())]
    RunHasCheckpoints { run: PathBuf },
    /// A run was to be resumed, but its checkpoint folder holds no committed checkpoint.
    #[error("{}: no checkpoint to resume from", checkpoints.display())]
    NoCheckpoint { checkpoints: PathBuf },
}

pub type Result<T> = std::result::Result<T, PolicyError>;

impl PolicyError {
    /// A [`PolicyError::File`] about `path`.
    pub fn file(path: &std::path::Path, message: impl Into<String>) -> Self {
        PolicyError::File { path: path.to_path_buf(), message: message.into() }
    }

    /// An I/O error while doing `action` ("read", "write", ...) on `path`.
    pub fn io(path: &std::path::Path, action: &str, e: std::io::Error) -> Self {
        Self::file(path, format!("cannot {action}: {e}"))
    }
}
