//! Checkpoints of a training run on disk: format, store, weights.
//!
//! Layout under a run's checkpoint root:
//! ```text
//! <root>/latest                 "step-000001000\n": the last committed checkpoint
//! <root>/step-000001000/        one checkpoint
//!     config.json               the caller's configuration (any serde value)
//!     model.safetensors         model weights, VarMap names
//!     ema.safetensors           EMA weights (same names) + "__ema_updates"
//!     optimizer.safetensors     AdamW moments "adamw.m.*", "adamw.v.*", "adamw.step"
//!     trainer.json              step, seed, last loss, size + FNV-1a digest of each file
//! ```
//! A checkpoint is written into a staging directory (`.staging-…`), every file
//! atomically (temp file, fsync, rename), `trainer.json` last; the staging
//! directory is then renamed to `step-N` and only after that is `latest`
//! replaced (atomically). A run killed at any point leaves the previous
//! checkpoint and `latest` intact; stale staging directories are ignored and
//! removed by the next save.
//!
//! - [`format`]: the file names, `trainer.json` and the digests that verify a checkpoint;
//! - [`store`]: saving and committing checkpoints of named tensors, finding the latest, reading
//!   one back verified (it knows tensors by name, not the optimiser or the EMA that made them);
//! - [`weights`]: safetensors files and the model's variables (loading inference weights).
pub mod format;
pub mod store;
pub mod weights;
