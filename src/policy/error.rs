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
}

pub type Result<T> = std::result::Result<T, PolicyError>;
