//! What a checkpoint folder holds: the file names, `trainer.json` (the trainer's progress and
//! the size and digest of every other file), and reading them back verified.
use std::collections::{BTreeMap, HashMap};
use std::fs;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::policy::config::PolicyConfig;
use crate::policy::error::{PolicyError, Result};

pub const CONFIG_FILE: &str = "config.json";
pub const MODEL_FILE: &str = "model.safetensors";
pub const EMA_FILE: &str = "ema.safetensors";
pub const OPTIMIZER_FILE: &str = "optimizer.safetensors";
pub const TRAINER_FILE: &str = "trainer.json";
pub const LATEST_FILE: &str = "latest";
/// Prefix of the optimiser's tensors in `optimizer.safetensors`.
pub const OPTIMIZER_PREFIX: &str = "adamw.";
/// Name of the update counter inside an EMA safetensors file. The other
/// tensors carry the model's own names, so the file loads as model weights.
pub const EMA_UPDATES_TENSOR: &str = "__ema_updates";
/// The files a checkpoint holds besides `trainer.json`, each with its digest in it.
pub const DIGESTED_FILES: [&str; 4] = [CONFIG_FILE, MODEL_FILE, EMA_FILE, OPTIMIZER_FILE];
pub(super) const FORMAT_VERSION: u32 = 1;

pub use crate::files::fnv1a64;

/// Size and digest of one checkpoint file, recorded in `trainer.json`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileDigest {
    pub bytes: u64,
    /// FNV-1a 64 of the content, hex.
    pub fnv1a64: String,
}

pub(super) fn digest_of(path: &Path) -> Result<(FileDigest, Vec<u8>)> {
    let bytes = fs::read(path).map_err(|e| PolicyError::io(path, "read", e))?;
    let digest = FileDigest { bytes: bytes.len() as u64, fnv1a64: format!("{:016x}", fnv1a64(&bytes)) };
    Ok((digest, bytes))
}

/// What a policy loaded from checkpoint folder `dir` computes with: FNV-1a 64 (hex) of its
/// `config.json` and its EMA weights. Two folders with equal digests act the same; the
/// manifests of sharded evaluations compare it.
pub fn weights_digest(dir: &Path) -> Result<String> {
    let mut h = fnv1a64(&[]);
    for file in [CONFIG_FILE, EMA_FILE] {
        let (_, bytes) = digest_of(&dir.join(file))?;
        h = (h ^ fnv1a64(&bytes)).wrapping_mul(0x0000_0100_0000_01b3);
    }
    Ok(format!("{h:016x}"))
}

/// The trainer's progress, saved as `trainer.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainerState {
    /// Optimiser steps completed; training resumes at step `step + 1`.
    pub step: u64,
    /// Seed of the run; with `step` it determines all randomness (`training::rng::step_rng`).
    pub seed: u64,
    /// Total loss of the last step, if any.
    pub last_loss: Option<f64>,
    /// Wall-clock seconds of training so far (summed over resumes).
    #[serde(default)]
    pub elapsed_seconds: f64,
    /// Anything else the caller needs to resume (data-order state, ...).
    #[serde(default)]
    pub extra: serde_json::Value,
}

/// `trainer.json` as written: the trainer state, and the digest of every other file.
#[derive(Serialize, Deserialize)]
pub(super) struct TrainerFile {
    pub(super) format_version: u32,
    #[serde(flatten)]
    pub(super) state: TrainerState,
    pub(super) files: BTreeMap<String, FileDigest>,
}

/// Reads and verifies a checkpoint's `trainer.json` and the digests of its files; returns the
/// files' contents by name.
pub(super) fn read_trainer_file(dir: &Path) -> Result<(TrainerFile, HashMap<&'static str, Vec<u8>>)> {
    read_trainer_file_verifying(dir, &DIGESTED_FILES)
}

/// Verifies the files `names` of checkpoint `dir` against the sizes and digests its
/// `trainer.json` recorded (what a policy loads: [`CONFIG_FILE`] and [`EMA_FILE`]), so that a
/// changed byte is an error naming the file instead of other weights.
pub fn verify_checkpoint_files(dir: &Path, names: &[&'static str]) -> Result<()> {
    read_trainer_file_verifying(dir, names).map(|_| ())
}

fn read_trainer_file_verifying(
    dir: &Path,
    names: &[&'static str],
) -> Result<(TrainerFile, HashMap<&'static str, Vec<u8>>)> {
    let trainer_path = dir.join(TRAINER_FILE);
    let text = fs::read_to_string(&trainer_path)
        .map_err(|e| PolicyError::io(&trainer_path, "read (is this a committed checkpoint directory?)", e))?;
    let trainer: TrainerFile = serde_json::from_str(&text)
        .map_err(|e| PolicyError::file(&trainer_path, format!("not a valid trainer state: {e}")))?;
    if trainer.format_version != FORMAT_VERSION {
        return Err(PolicyError::file(
            &trainer_path,
            format!("format version {} is not supported (expected {FORMAT_VERSION})", trainer.format_version),
        ));
    }
    let mut contents = HashMap::new();
    for &name in names {
        let path = dir.join(name);
        let expected = trainer
            .files
            .get(name)
            .ok_or_else(|| PolicyError::file(&trainer_path, format!("records no digest for {name}")))?;
        let (found, bytes) = digest_of(&path)?;
        if found.bytes != expected.bytes {
            return Err(PolicyError::file(
                &path,
                format!("truncated or corrupt: {} bytes, trainer.json recorded {}", found.bytes, expected.bytes),
            ));
        }
        if found.fnv1a64 != expected.fnv1a64 {
            return Err(PolicyError::file(
                &path,
                format!(
                    "corrupt: content digest {} does not match {} recorded in trainer.json",
                    found.fnv1a64, expected.fnv1a64
                ),
            ));
        }
        contents.insert(name, bytes);
    }
    Ok((trainer, contents))
}

/// A checkpoint's `config.json` as plain JSON (the tests' configs are not policy configs).
#[cfg(test)]
pub(crate) fn read_config_json(dir: &Path) -> Result<serde_json::Value> {
    let path = dir.join(CONFIG_FILE);
    let bytes = fs::read(&path).map_err(|e| PolicyError::io(&path, "read", e))?;
    serde_json::from_slice(&bytes).map_err(|e| PolicyError::file(&path, format!("not valid JSON: {e}")))
}

/// The policy config stored in a checkpoint directory, validated (to build the model before
/// loading its weights).
pub fn read_checkpoint_config(dir: &Path) -> Result<PolicyConfig> {
    let path = dir.join(CONFIG_FILE);
    let text = fs::read_to_string(&path).map_err(|e| PolicyError::io(&path, "read", e))?;
    let config: PolicyConfig =
        serde_json::from_str(&text).map_err(|e| PolicyError::file(&path, format!("not a policy config: {e}")))?;
    config.validate().map_err(|e| PolicyError::file(&path, e.to_string()))?;
    Ok(config)
}
