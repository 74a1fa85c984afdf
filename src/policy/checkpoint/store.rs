//! A run's checkpoint root: numbered checkpoints of named tensors, committed atomically (see the
//! module docs of [`crate::policy::checkpoint`] for the order), the newest few kept, the latest
//! found, and one read back with every file verified. The store knows tensors by name only:
//! the trainer turns its model, EMA and optimiser into tensors and back.
use std::collections::{BTreeMap, HashMap};
use std::fs::{self, File};
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};

use super::format::{
    CONFIG_FILE, DIGESTED_FILES, EMA_FILE, FORMAT_VERSION, LATEST_FILE, MODEL_FILE, OPTIMIZER_FILE, TRAINER_FILE,
    TrainerFile, TrainerState, digest_of, read_trainer_file,
};
use super::weights::{parse_safetensors, write_safetensors};
use crate::files::write_atomic;
use crate::policy::error::{PolicyError, Result};

const STEP_DIR_PREFIX: &str = "step-";
const STAGING_PREFIX: &str = ".staging-";

/// The tensors of one checkpoint, by file.
pub struct CheckpointTensors {
    /// The model's variables (`model.safetensors`).
    pub model: HashMap<String, Tensor>,
    /// The EMA weights and their update counter (`ema.safetensors`).
    pub ema: HashMap<String, Tensor>,
    /// The optimiser's state (`optimizer.safetensors`).
    pub optimizer: HashMap<String, Tensor>,
}

/// A checkpoint read back: every file verified against `trainer.json`, the tensors parsed (not
/// yet checked against any model).
pub struct StoredCheckpoint {
    pub dir: PathBuf,
    pub config: serde_json::Value,
    pub trainer: TrainerState,
    pub tensors: CheckpointTensors,
}

/// A run's checkpoint root: saves numbered checkpoints, keeps the newest
/// `keep_last`, and finds the latest committed one.
#[derive(Clone, Debug)]
pub struct CheckpointStore {
    root: PathBuf,
    keep_last: usize,
}

pub(crate) fn step_dir_name(step: u64) -> String {
    format!("{STEP_DIR_PREFIX}{step:09}")
}

fn parse_step_dir(name: &str) -> Option<u64> {
    name.strip_prefix(STEP_DIR_PREFIX)?.parse().ok()
}

/// fsyncs a directory so a rename inside it is durable.
fn sync_dir(dir: &Path) -> Result<()> {
    File::open(dir).and_then(|f| f.sync_all()).map_err(|e| PolicyError::io(dir, "fsync directory", e))
}

fn unique_suffix() -> u64 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    COUNTER.fetch_add(1, Ordering::Relaxed)
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic(path, bytes).map_err(|e| PolicyError::io(path, "write", e))
}

impl CheckpointStore {
    /// Opens (creating it if needed) a checkpoint root. Keeps the 3 newest checkpoints.
    pub fn open(root: impl Into<PathBuf>) -> Result<Self> {
        let root = root.into();
        fs::create_dir_all(&root).map_err(|e| PolicyError::io(&root, "create the checkpoint directory", e))?;
        Ok(Self { root, keep_last: 3 })
    }

    /// How many committed checkpoints to keep (at least 1).
    pub fn with_keep_last(mut self, keep_last: usize) -> Self {
        self.keep_last = keep_last.max(1);
        self
    }

    /// Committed checkpoints (those with a `trainer.json`), oldest first.
    pub fn committed(&self) -> Result<Vec<(u64, PathBuf)>> {
        let entries = fs::read_dir(&self.root).map_err(|e| PolicyError::io(&self.root, "list", e))?;
        let mut out = Vec::new();
        for entry in entries {
            let entry = entry.map_err(|e| PolicyError::io(&self.root, "list", e))?;
            let name = entry.file_name();
            if let Some(step) = parse_step_dir(&name.to_string_lossy())
                && entry.path().join(TRAINER_FILE).is_file()
            {
                out.push((step, entry.path()));
            }
        }
        out.sort();
        Ok(out)
    }

    /// The checkpoint to resume from: the one `latest` names, or — when the
    /// pointer is missing or names nothing valid — the newest committed one.
    pub fn latest(&self) -> Result<Option<PathBuf>> {
        let pointer = self.root.join(LATEST_FILE);
        if let Ok(name) = fs::read_to_string(&pointer) {
            let dir = self.root.join(name.trim());
            if parse_step_dir(name.trim()).is_some() && dir.join(TRAINER_FILE).is_file() {
                return Ok(Some(dir));
            }
        }
        Ok(self.committed()?.pop().map(|(_, dir)| dir))
    }

    /// Saves a checkpoint for `trainer.step` and commits it (see the module
    /// docs for the order). Returns the checkpoint's directory.
    pub fn save(
        &self,
        config: &serde_json::Value,
        tensors: &CheckpointTensors,
        trainer: &TrainerState,
    ) -> Result<PathBuf> {
        self.remove_stale_staging();
        let final_name = step_dir_name(trainer.step);
        let staging =
            self.root.join(format!("{STAGING_PREFIX}{final_name}-{}-{}", std::process::id(), unique_suffix()));
        fs::create_dir_all(&staging).map_err(|e| PolicyError::io(&staging, "create", e))?;

        let config_bytes = serde_json::to_vec_pretty(config)
            .map_err(|e| PolicyError::file(&staging.join(CONFIG_FILE), format!("cannot serialise: {e}")))?;
        write_file(&staging.join(CONFIG_FILE), &config_bytes)?;
        write_safetensors(&tensors.model, &staging.join(MODEL_FILE))?;
        write_safetensors(&tensors.ema, &staging.join(EMA_FILE))?;
        write_safetensors(&tensors.optimizer, &staging.join(OPTIMIZER_FILE))?;

        let mut files = BTreeMap::new();
        for name in DIGESTED_FILES {
            files.insert(name.to_string(), digest_of(&staging.join(name))?.0);
        }
        let trainer_file = TrainerFile { format_version: FORMAT_VERSION, state: trainer.clone(), files };
        let trainer_bytes = serde_json::to_vec_pretty(&trainer_file)
            .map_err(|e| PolicyError::file(&staging.join(TRAINER_FILE), format!("cannot serialise: {e}")))?;
        write_file(&staging.join(TRAINER_FILE), &trainer_bytes)?;
        sync_dir(&staging)?;

        // Commit: move the finished directory into place, then the pointer.
        let final_dir = self.root.join(&final_name);
        let displaced = if final_dir.exists() {
            let old = self.root.join(format!("{STAGING_PREFIX}old-{final_name}-{}", unique_suffix()));
            fs::rename(&final_dir, &old).map_err(|e| PolicyError::io(&final_dir, "move aside", e))?;
            Some(old)
        } else {
            None
        };
        fs::rename(&staging, &final_dir).map_err(|e| PolicyError::io(&final_dir, "commit (rename staging onto)", e))?;
        sync_dir(&self.root)?;
        write_file(&self.root.join(LATEST_FILE), format!("{final_name}\n").as_bytes())?;
        if let Some(old) = displaced {
            let _ = fs::remove_dir_all(old);
        }
        self.prune(&final_dir)?;
        Ok(final_dir)
    }

    fn remove_stale_staging(&self) {
        if let Ok(entries) = fs::read_dir(&self.root) {
            for entry in entries.flatten() {
                if entry.file_name().to_string_lossy().starts_with(STAGING_PREFIX) {
                    let _ = fs::remove_dir_all(entry.path());
                }
            }
        }
    }

    /// Removes committed checkpoints beyond `keep_last`, never `keep`.
    fn prune(&self, keep: &Path) -> Result<()> {
        let committed = self.committed()?;
        let excess = committed.len().saturating_sub(self.keep_last);
        for (_, dir) in committed.into_iter().take(excess) {
            if dir != keep {
                fs::remove_dir_all(&dir).map_err(|e| PolicyError::io(&dir, "remove old checkpoint", e))?;
            }
        }
        Ok(())
    }
}

/// Reads a committed checkpoint directory with every file verified (sizes and digests against
/// `trainer.json`, valid JSON and safetensors), tensors onto `device`. The error names the
/// offending file.
pub fn read_checkpoint(dir: &Path, device: &Device) -> Result<StoredCheckpoint> {
    let (trainer, contents) = read_trainer_file(dir)?;
    let config_path = dir.join(CONFIG_FILE);
    let config: serde_json::Value = serde_json::from_slice(&contents[CONFIG_FILE])
        .map_err(|e| PolicyError::file(&config_path, format!("not valid JSON: {e}")))?;
    let tensors = |name: &str| parse_safetensors(&dir.join(name), &contents[name], device);
    let tensors =
        CheckpointTensors { model: tensors(MODEL_FILE)?, ema: tensors(EMA_FILE)?, optimizer: tensors(OPTIMIZER_FILE)? };
    Ok(StoredCheckpoint { dir: dir.to_path_buf(), config, trainer: trainer.state, tensors })
}
