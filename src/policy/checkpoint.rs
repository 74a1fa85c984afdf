//! Training checkpoints on disk and the training RNG.
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
//! Randomness of training step `s` is a pure function of `(seed, s)`
//! ([`step_rng`]), so a run resumed from a checkpoint draws exactly what the
//! uninterrupted run would have.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::fs::{self, File};
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use candle_nn::VarMap;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::policy::error::{PolicyError, Result};
use crate::policy::optim::{AdamW, Ema, load_safetensors};

pub const CONFIG_FILE: &str = "config.json";
pub const MODEL_FILE: &str = "model.safetensors";
pub const EMA_FILE: &str = "ema.safetensors";
pub const OPTIMIZER_FILE: &str = "optimizer.safetensors";
pub const TRAINER_FILE: &str = "trainer.json";
pub const LATEST_FILE: &str = "latest";
/// Prefix of the optimiser's tensors in `optimizer.safetensors`.
pub const OPTIMIZER_PREFIX: &str = "adamw.";
const STEP_DIR_PREFIX: &str = "step-";
const STAGING_PREFIX: &str = ".staging-";
const FORMAT_VERSION: u32 = 1;

fn file_error(path: &Path, message: impl Into<String>) -> PolicyError {
    PolicyError::File { path: path.to_path_buf(), message: message.into() }
}

fn io_error(path: &Path, action: &str, e: std::io::Error) -> PolicyError {
    file_error(path, format!("cannot {action}: {e}"))
}

/// fsyncs a directory so a rename inside it is durable.
fn sync_dir(dir: &Path) -> Result<()> {
    File::open(dir).and_then(|f| f.sync_all()).map_err(|e| io_error(dir, "fsync directory", e))
}

fn unique_suffix() -> u64 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    COUNTER.fetch_add(1, Ordering::Relaxed)
}

/// Writes a file atomically with `write(temp_path)` ([`crate::files::write_atomic_with`]:
/// temporary file in the same folder, fsync, rename, folder fsync). Readers see the old or the
/// new file, never a partial one. An error of `write` itself is returned as it was.
pub fn write_atomic_with<F>(path: &Path, write: F) -> Result<()>
where
    F: FnOnce(&Path) -> Result<()>,
{
    let mut inner = None;
    let outcome = crate::files::write_atomic_with(path, |tmp| {
        write(tmp).map_err(|e| {
            let message = e.to_string();
            inner = Some(e);
            std::io::Error::other(message)
        })
    });
    outcome.map_err(|e| inner.take().unwrap_or_else(|| io_error(path, "write", e)))
}

/// Writes `bytes` to `path` atomically (see [`write_atomic_with`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    crate::files::write_atomic(path, bytes).map_err(|e| io_error(path, "write", e))
}

/// Writes tensors as a safetensors file atomically.
pub fn write_safetensors_atomic(tensors: &HashMap<String, Tensor>, path: &Path) -> Result<()> {
    write_atomic_with(path, |tmp| {
        candle_core::safetensors::save(tensors, tmp)
            .map_err(|e| file_error(tmp, format!("cannot write safetensors: {e}")))
    })
}

/// 64-bit FNV-1a of a byte string (a corruption check, not a cryptographic hash).
fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Size and digest of one checkpoint file, recorded in `trainer.json`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileDigest {
    pub bytes: u64,
    /// FNV-1a 64 of the content, hex.
    pub fnv1a64: String,
}

fn digest_of(path: &Path) -> Result<(FileDigest, Vec<u8>)> {
    let bytes = fs::read(path).map_err(|e| io_error(path, "read", e))?;
    let digest = FileDigest { bytes: bytes.len() as u64, fnv1a64: format!("{:016x}", fnv1a64(&bytes)) };
    Ok((digest, bytes))
}

/// The trainer's progress, saved as `trainer.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainerState {
    /// Optimiser steps completed; training resumes at step `step + 1`.
    pub step: u64,
    /// Seed of the run; with `step` it determines all randomness ([`step_rng`]).
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

#[derive(Serialize, Deserialize)]
struct TrainerFile {
    format_version: u32,
    #[serde(flatten)]
    state: TrainerState,
    files: BTreeMap<String, FileDigest>,
}

/// What [`load_checkpoint`] returns besides filling the model and optimiser.
#[derive(Clone, Debug)]
pub struct LoadedCheckpoint {
    pub dir: PathBuf,
    pub config: serde_json::Value,
    pub trainer: TrainerState,
}

/// A run's checkpoint root: saves numbered checkpoints, keeps the newest
/// `keep_last`, and finds the latest committed one.
#[derive(Clone, Debug)]
pub struct CheckpointStore {
    root: PathBuf,
    keep_last: usize,
}

fn step_dir_name(step: u64) -> String {
    format!("{STEP_DIR_PREFIX}{step:09}")
}

fn parse_step_dir(name: &str) -> Option<u64> {
    name.strip_prefix(STEP_DIR_PREFIX)?.parse().ok()
}

impl CheckpointStore {
    /// Opens (creating it if needed) a checkpoint root. Keeps the 3 newest checkpoints.
    pub fn open(root: impl Into<PathBuf>) -> Result<Self> {
        let root = root.into();
        fs::create_dir_all(&root).map_err(|e| io_error(&root, "create the checkpoint directory", e))?;
        Ok(Self { root, keep_last: 3 })
    }

    /// How many committed checkpoints to keep (at least 1).
    pub fn with_keep_last(mut self, keep_last: usize) -> Self {
        self.keep_last = keep_last.max(1);
        self
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Committed checkpoints (those with a `trainer.json`), oldest first.
    pub fn committed(&self) -> Result<Vec<(u64, PathBuf)>> {
        let entries = fs::read_dir(&self.root).map_err(|e| io_error(&self.root, "list", e))?;
        let mut out = Vec::new();
        for entry in entries {
            let entry = entry.map_err(|e| io_error(&self.root, "list", e))?;
            let name = entry.file_name();
            if let Some(step) = parse_step_dir(&name.to_string_lossy()) {
                if entry.path().join(TRAINER_FILE).is_file() {
                    out.push((step, entry.path()));
                }
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
        model: &VarMap,
        ema: &Ema,
        optimizer: &AdamW,
        trainer: &TrainerState,
    ) -> Result<PathBuf> {
        self.remove_stale_staging();
        let final_name = step_dir_name(trainer.step);
        let staging =
            self.root.join(format!("{STAGING_PREFIX}{final_name}-{}-{}", std::process::id(), unique_suffix()));
        fs::create_dir_all(&staging).map_err(|e| io_error(&staging, "create", e))?;

        let config_bytes = serde_json::to_vec_pretty(config)
            .map_err(|e| file_error(&staging.join(CONFIG_FILE), format!("cannot serialise: {e}")))?;
        write_atomic(&staging.join(CONFIG_FILE), &config_bytes)?;
        write_safetensors_atomic(&varmap_tensors(model)?, &staging.join(MODEL_FILE))?;
        write_safetensors_atomic(&ema.state_tensors()?, &staging.join(EMA_FILE))?;
        write_safetensors_atomic(&optimizer.state_tensors(OPTIMIZER_PREFIX)?, &staging.join(OPTIMIZER_FILE))?;

        let mut files = BTreeMap::new();
        for name in [CONFIG_FILE, MODEL_FILE, EMA_FILE, OPTIMIZER_FILE] {
            files.insert(name.to_string(), digest_of(&staging.join(name))?.0);
        }
        let trainer_file = TrainerFile { format_version: FORMAT_VERSION, state: trainer.clone(), files };
        let trainer_bytes = serde_json::to_vec_pretty(&trainer_file)
            .map_err(|e| file_error(&staging.join(TRAINER_FILE), format!("cannot serialise: {e}")))?;
        write_atomic(&staging.join(TRAINER_FILE), &trainer_bytes)?;
        sync_dir(&staging)?;

        // Commit: move the finished directory into place, then the pointer.
        let final_dir = self.root.join(&final_name);
        let displaced = if final_dir.exists() {
            let old = self.root.join(format!("{STAGING_PREFIX}old-{final_name}-{}", unique_suffix()));
            fs::rename(&final_dir, &old).map_err(|e| io_error(&final_dir, "move aside", e))?;
            Some(old)
        } else {
            None
        };
        fs::rename(&staging, &final_dir).map_err(|e| io_error(&final_dir, "commit (rename staging onto)", e))?;
        sync_dir(&self.root)?;
        write_atomic(&self.root.join(LATEST_FILE), format!("{final_name}\n").as_bytes())?;
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
                fs::remove_dir_all(&dir).map_err(|e| io_error(&dir, "remove old checkpoint", e))?;
            }
        }
        Ok(())
    }
}

/// The model's variables as named tensors (what goes to `model.safetensors`).
pub fn varmap_tensors(model: &VarMap) -> Result<HashMap<String, Tensor>> {
    let data =
        model.data().lock().map_err(|_| PolicyError::Invalid("checkpoint: the VarMap lock is poisoned".into()))?;
    Ok(data.iter().map(|(k, v)| (k.clone(), v.as_tensor().clone())).collect())
}

/// Checks `tensors` against the model's variables by name, shape and dtype,
/// and returns them in a form ready to assign. Errors name `source`.
fn check_model_tensors(
    model: &VarMap,
    tensors: &HashMap<String, Tensor>,
    ignore: &[&str],
    source: &Path,
) -> Result<Vec<(candle_core::Var, Tensor)>> {
    let data =
        model.data().lock().map_err(|_| PolicyError::Invalid("checkpoint: the VarMap lock is poisoned".into()))?;
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let mut out = Vec::with_capacity(names.len());
    for name in names {
        let var = &data[name];
        let t = tensors.get(name).ok_or_else(|| {
            file_error(
                source,
                format!(
                    "missing tensor '{name}' (the model expects shape {:?}); the checkpoint was written by a different model configuration",
                    var.dims()
                ),
            )
        })?;
        if t.shape() != var.shape() {
            return Err(file_error(
                source,
                format!("tensor '{name}' has shape {:?}, the model expects {:?}", t.dims(), var.dims()),
            ));
        }
        if t.dtype() != var.dtype() {
            return Err(file_error(
                source,
                format!("tensor '{name}' is {:?}, the model expects {:?}", t.dtype(), var.dtype()),
            ));
        }
        out.push((var.clone(), t.clone()));
    }
    let known: HashSet<&str> = data.keys().map(String::as_str).chain(ignore.iter().copied()).collect();
    let mut extra: Vec<&String> = tensors.keys().filter(|k| !known.contains(k.as_str())).collect();
    extra.sort();
    if let Some(first) = extra.first() {
        return Err(file_error(
            source,
            format!(
                "{} tensor(s) the model does not have, e.g. '{first}'; the checkpoint was written by a different model configuration",
                extra.len()
            ),
        ));
    }
    Ok(out)
}

fn model_device(model: &VarMap) -> Device {
    model.all_vars().first().map_or(Device::Cpu, |v| v.device().clone())
}

/// Loads model weights from a safetensors file (e.g. a checkpoint's
/// `model.safetensors` or `ema.safetensors` for inference) into `model`,
/// checking names and shapes. Nothing is changed on error.
pub fn load_model_weights(path: &Path, model: &VarMap) -> Result<()> {
    let tensors = load_safetensors(path, &model_device(model))?;
    let assignments = check_model_tensors(model, &tensors, &[crate::policy::optim::EMA_UPDATES_TENSOR], path)?;
    for (var, t) in assignments {
        var.set(&t)?;
    }
    Ok(())
}

/// Reads and verifies a checkpoint's `trainer.json` and the digests of its files.
fn read_trainer_file(dir: &Path) -> Result<(TrainerFile, HashMap<&'static str, Vec<u8>>)> {
    let trainer_path = dir.join(TRAINER_FILE);
    let text = fs::read_to_string(&trainer_path)
        .map_err(|e| io_error(&trainer_path, "read (is this a committed checkpoint directory?)", e))?;
    let trainer: TrainerFile = serde_json::from_str(&text)
        .map_err(|e| file_error(&trainer_path, format!("not a valid trainer state: {e}")))?;
    if trainer.format_version != FORMAT_VERSION {
        return Err(file_error(
            &trainer_path,
            format!("format version {} is not supported (expected {FORMAT_VERSION})", trainer.format_version),
        ));
    }
    let mut contents = HashMap::new();
    for name in [CONFIG_FILE, MODEL_FILE, EMA_FILE, OPTIMIZER_FILE] {
        let path = dir.join(name);
        let expected = trainer
            .files
            .get(name)
            .ok_or_else(|| file_error(&trainer_path, format!("records no digest for {name}")))?;
        let (found, bytes) = digest_of(&path)?;
        if found.bytes != expected.bytes {
            return Err(file_error(
                &path,
                format!("truncated or corrupt: {} bytes, trainer.json recorded {}", found.bytes, expected.bytes),
            ));
        }
        if found.fnv1a64 != expected.fnv1a64 {
            return Err(file_error(
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

fn parse_safetensors(path: &Path, bytes: &[u8], device: &Device) -> Result<HashMap<String, Tensor>> {
    candle_core::safetensors::load_buffer(bytes, device)
        .map_err(|e| file_error(path, format!("not a valid safetensors file (truncated or corrupt?): {e}")))
}

/// Restores a checkpoint directory into `model`, `ema` and `optimizer` and
/// returns its config and trainer state. Every file is verified (digests,
/// names, shapes) before anything is changed, so on error the model and
/// optimiser are untouched; the error names the offending file.
pub fn load_checkpoint(dir: &Path, model: &VarMap, ema: &mut Ema, optimizer: &mut AdamW) -> Result<LoadedCheckpoint> {
    let (trainer, contents) = read_trainer_file(dir)?;
    let device = model_device(model);
    let config_path = dir.join(CONFIG_FILE);
    let config: serde_json::Value = serde_json::from_slice(&contents[CONFIG_FILE])
        .map_err(|e| file_error(&config_path, format!("not valid JSON: {e}")))?;

    let model_path = dir.join(MODEL_FILE);
    let model_tensors = parse_safetensors(&model_path, &contents[MODEL_FILE], &device)?;
    let assignments = check_model_tensors(model, &model_tensors, &[], &model_path)?;

    let ema_path = dir.join(EMA_FILE);
    let ema_tensors = parse_safetensors(&ema_path, &contents[EMA_FILE], &device)?;
    let ema_state = ema.stage_state(&ema_tensors, &ema_path)?;
    let opt_path = dir.join(OPTIMIZER_FILE);
    let opt_tensors = parse_safetensors(&opt_path, &contents[OPTIMIZER_FILE], &device)?;
    let opt_state = optimizer.stage_state(&opt_tensors, OPTIMIZER_PREFIX, &opt_path)?;

    // Everything checked: install.
    for (var, t) in assignments {
        var.set(&t)?;
    }
    ema.apply_state(ema_state);
    optimizer.apply_state(opt_state);
    Ok(LoadedCheckpoint { dir: dir.to_path_buf(), config, trainer: trainer.state })
}

/// Reads only a checkpoint's `config.json` (e.g. to build the model before
/// [`load_checkpoint`]).
pub fn read_checkpoint_config(dir: &Path) -> Result<serde_json::Value> {
    let path = dir.join(CONFIG_FILE);
    let bytes = fs::read(&path).map_err(|e| io_error(&path, "read", e))?;
    serde_json::from_slice(&bytes).map_err(|e| file_error(&path, format!("not valid JSON: {e}")))
}

/// The RNG for training step `step` of the run seeded with `seed`: ChaCha8
/// keyed by the seed, on stream `step`. Pure in `(seed, step)`: a resumed run
/// draws exactly the numbers of the uninterrupted one. Draw from it in a fixed
/// order within the step (e.g. batch indices, then `a0`, then `t`).
pub fn step_rng(seed: u64, step: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(step);
    rng
}

/// Like [`step_rng`] but with an independent key per `purpose` (e.g.
/// `"noise"`, `"augment"`), so adding draws for one purpose does not shift
/// another's.
pub fn step_rng_for(seed: u64, step: u64, purpose: &str) -> ChaCha8Rng {
    let key = seed ^ fnv1a64(purpose.as_bytes()).rotate_left(17);
    step_rng(key, step)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::optim::{AdamWConfig, EmaConfig};
    use candle_core::DType;
    use candle_nn::{Init, VarBuilder};
    use rand::Rng;

    struct TempDir(PathBuf);
    impl TempDir {
        fn new(tag: &str) -> Self {
            let p = std::env::temp_dir().join(format!("policy_train_ckpt_{tag}_{}", std::process::id()));
            let _ = fs::remove_dir_all(&p);
            fs::create_dir_all(&p).unwrap();
            TempDir(p)
        }
    }
    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = fs::remove_dir_all(&self.0);
        }
    }

    /// A small model: "enc.w" [4, 3], "enc.b" [4] (and optionally "head.w" [2, 4]).
    fn model(extra_head: bool, enc_rows: usize) -> VarMap {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        vb.pp("enc").get_with_hints((enc_rows, 3), "w", Init::Randn { mean: 0.0, stdev: 1.0 }).unwrap();
        vb.pp("enc").get_with_hints(enc_rows, "b", Init::Const(0.1)).unwrap();
        if extra_head {
            vb.pp("head").get_with_hints((2, enc_rows), "w", Init::Const(0.2)).unwrap();
        }
        varmap
    }

    fn train_steps(varmap: &VarMap, opt: &mut AdamW, ema: &mut Ema, n: usize) {
        let w = varmap.data().lock().unwrap()["enc.w"].clone();
        for _ in 0..n {
            let loss = w.as_tensor().sqr().unwrap().sum_all().unwrap();
            opt.backward_step(&loss).unwrap();
            ema.update().unwrap();
        }
    }

    fn snapshot(varmap: &VarMap) -> BTreeMap<String, Vec<f32>> {
        varmap_tensors(varmap)
            .unwrap()
            .into_iter()
            .map(|(k, t)| (k, t.flatten_all().unwrap().to_vec1().unwrap()))
            .collect()
    }

    fn save_one(store: &CheckpointStore, varmap: &VarMap, step: u64) -> (PathBuf, AdamW, Ema) {
        let mut opt = AdamW::new(varmap, AdamWConfig { learning_rate: 0.01, ..Default::default() }).unwrap();
        let mut ema = Ema::new(varmap, EmaConfig::default()).unwrap();
        train_steps(varmap, &mut opt, &mut ema, 3);
        let trainer = TrainerState {
            step,
            seed: 42,
            last_loss: Some(1.5),
            elapsed_seconds: 12.0,
            extra: serde_json::json!({"epoch": 1}),
        };
        let config = serde_json::json!({"model": {"dim": 120}});
        let dir = store.save(&config, varmap, &ema, &opt, &trainer).unwrap();
        (dir, opt, ema)
    }

    fn error_path(err: &PolicyError) -> PathBuf {
        match err {
            PolicyError::File { path, .. } => path.clone(),
            other => panic!("expected a File error, got {other:?}"),
        }
    }

    #[test]
    fn round_trip_restores_everything() {
        let tmp = TempDir::new("roundtrip");
        let store = CheckpointStore::open(&tmp.0).unwrap();
        let saved = model(true, 4);
        let (dir, opt, ema) = save_one(&store, &saved, 3);
        assert_eq!(store.latest().unwrap(), Some(dir.clone()));
        for f in [CONFIG_FILE, MODEL_FILE, EMA_FILE, OPTIMIZER_FILE, TRAINER_FILE] {
            assert!(dir.join(f).is_file(), "{f}");
        }

        let fresh = model(true, 4);
        let mut opt2 = AdamW::new(&fresh, AdamWConfig::default()).unwrap();
        let mut ema2 = Ema::new(&fresh, EmaConfig::default()).unwrap();
        let loaded = load_checkpoint(&dir, &fresh, &mut ema2, &mut opt2).unwrap();
        assert_eq!(loaded.trainer.step, 3);
        assert_eq!(loaded.trainer.seed, 42);
        assert_eq!(loaded.trainer.extra["epoch"], 1);
        assert_eq!(loaded.config["model"]["dim"], 120);
        assert_eq!(snapshot(&fresh), snapshot(&saved));
        assert_eq!(opt2.step_count(), opt.step_count());
        assert_eq!(ema2.updates(), ema.updates());
        let (a, b) = (ema.tensors().unwrap(), ema2.tensors().unwrap());
        assert_eq!(a["enc.w"].to_vec2::<f32>().unwrap(), b["enc.w"].to_vec2::<f32>().unwrap());
        let (a, b) = (opt.state_tensors("x").unwrap(), opt2.state_tensors("x").unwrap());
        assert_eq!(a["xv.enc.w"].to_vec2::<f32>().unwrap(), b["xv.enc.w"].to_vec2::<f32>().unwrap());

        // EMA weights load as a model for inference.
        let inference = model(true, 4);
        load_model_weights(&dir.join(EMA_FILE), &inference).unwrap();
        assert_eq!(
            snapshot(&inference)["enc.w"],
            ema.tensors().unwrap()["enc.w"].flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );
        assert_eq!(read_checkpoint_config(&dir).unwrap()["model"]["dim"], 120);
    }

    #[test]
    fn truncated_model_file_is_named() {
        let tmp = TempDir::new("truncated");
        let store = CheckpointStore::open(&tmp.0).unwrap();
        let saved = model(false, 4);
        let (dir, _, _) = save_one(&store, &saved, 1);
        let model_path = dir.join(MODEL_FILE);
        let bytes = fs::read(&model_path).unwrap();
        fs::write(&model_path, &bytes[..bytes.len() / 2]).unwrap();

        let fresh = model(false, 4);
        let before = snapshot(&fresh);
        let mut opt = AdamW::new(&fresh, AdamWConfig::default()).unwrap();
        let mut ema = Ema::new(&fresh, EmaConfig::default()).unwrap();
        let err = load_checkpoint(&dir, &fresh, &mut ema, &mut opt).unwrap_err();
        assert_eq!(error_path(&err), model_path);
        assert!(err.to_string().contains("truncated"), "{err}");
        assert_eq!(snapshot(&fresh), before, "a failed load must not change the model");
        assert_eq!(opt.step_count(), 0);

        // Without trainer.json's digests the safetensors parser catches it too.
        let err = load_model_weights(&model_path, &fresh).unwrap_err();
        assert_eq!(error_path(&err), model_path);
        assert!(err.to_string().contains("safetensors"), "{err}");
    }

    #[test]
    fn missing_tensor_and_wrong_shape_are_named() {
        let tmp = TempDir::new("mismatch");
        let store = CheckpointStore::open(&tmp.0).unwrap();
        let saved = model(false, 4);
        let (dir, _, _) = save_one(&store, &saved, 1);
        let model_path = dir.join(MODEL_FILE);

        // The loading model has a head the checkpoint lacks.
        let bigger = model(true, 4);
        let mut opt = AdamW::new(&bigger, AdamWConfig::default()).unwrap();
        let mut ema = Ema::new(&bigger, EmaConfig::default()).unwrap();
        let err = load_checkpoint(&dir, &bigger, &mut ema, &mut opt).unwrap_err();
        assert_eq!(error_path(&err), model_path);
        assert!(err.to_string().contains("missing tensor 'head.w'"), "{err}");

        // Same names, different shape.
        let wider = model(false, 5);
        let mut opt = AdamW::new(&wider, AdamWConfig::default()).unwrap();
        let mut ema = Ema::new(&wider, EmaConfig::default()).unwrap();
        let err = load_checkpoint(&dir, &wider, &mut ema, &mut opt).unwrap_err();
        assert_eq!(error_path(&err), model_path);
        let msg = err.to_string();
        assert!(msg.contains("'enc.b'") && msg.contains("[4]") && msg.contains("[5]"), "{msg}");
    }

    #[test]
    fn corrupted_bytes_are_detected_by_digest() {
        let tmp = TempDir::new("corrupt");
        let store = CheckpointStore::open(&tmp.0).unwrap();
        let saved = model(false, 4);
        let (dir, _, _) = save_one(&store, &saved, 1);
        let opt_path = dir.join(OPTIMIZER_FILE);
        let mut bytes = fs::read(&opt_path).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 0x55;
        fs::write(&opt_path, &bytes).unwrap();
        let fresh = model(false, 4);
        let mut opt = AdamW::new(&fresh, AdamWConfig::default()).unwrap();
        let mut ema = Ema::new(&fresh, EmaConfig::default()).unwrap();
        let err = load_checkpoint(&dir, &fresh, &mut ema, &mut opt).unwrap_err();
        assert_eq!(error_path(&err), opt_path);
        assert!(err.to_string().contains("digest"), "{err}");
    }

    #[test]
    fn interrupted_save_leaves_previous_checkpoint_and_pruning_keeps_newest() {
        let tmp = TempDir::new("interrupt");
        let store = CheckpointStore::open(&tmp.0).unwrap().with_keep_last(2);
        let saved = model(false, 4);
        let (first, _, _) = save_one(&store, &saved, 10);
        // A save killed half-way: a staging directory with some files and a
        // step directory without trainer.json.
        let staging = tmp.0.join(".staging-step-000000020-999-0");
        fs::create_dir_all(&staging).unwrap();
        fs::write(staging.join(MODEL_FILE), b"partial").unwrap();
        let uncommitted = tmp.0.join(step_dir_name(30));
        fs::create_dir_all(&uncommitted).unwrap();
        fs::write(uncommitted.join(MODEL_FILE), b"partial").unwrap();
        assert_eq!(store.latest().unwrap(), Some(first.clone()));
        // Even with the pointer gone, the newest committed one is found.
        fs::remove_file(tmp.0.join(LATEST_FILE)).unwrap();
        assert_eq!(store.latest().unwrap(), Some(first.clone()));

        save_one(&store, &saved, 20);
        assert!(!staging.exists(), "stale staging directories are removed");
        let (third, _, _) = save_one(&store, &saved, 40);
        let steps: Vec<u64> = store.committed().unwrap().into_iter().map(|(s, _)| s).collect();
        assert_eq!(steps, vec![20, 40]);
        assert_eq!(store.latest().unwrap(), Some(third));
        // Saving the same step again replaces it.
        let (again, _, _) = save_one(&store, &saved, 40);
        assert_eq!(store.latest().unwrap(), Some(again));
    }

    #[test]
    fn step_rng_is_pure_in_seed_and_step() {
        let draw = |mut r: ChaCha8Rng| -> Vec<u32> { (0..8).map(|_| r.random()).collect() };
        assert_eq!(draw(step_rng(1, 5)), draw(step_rng(1, 5)));
        assert_ne!(draw(step_rng(1, 5)), draw(step_rng(1, 6)));
        assert_ne!(draw(step_rng(1, 5)), draw(step_rng(2, 5)));
        assert_ne!(draw(step_rng_for(1, 5, "noise")), draw(step_rng_for(1, 5, "augment")));
        assert_eq!(draw(step_rng_for(1, 5, "noise")), draw(step_rng_for(1, 5, "noise")));
    }

    /// A miniature FlowRAM training step: image encoder -> pooled features,
    /// concatenated with (a_t, t) -> velocity and open logit; loss of Table B.
    struct MiniPolicy {
        encoder: crate::policy::image_encoder::ImageEncoder,
        head: candle_nn::Linear,
    }

    impl MiniPolicy {
        fn new(varmap: &VarMap) -> Self {
            let vb = VarBuilder::from_varmap(varmap, DType::F32, &Device::Cpu);
            let cfg = crate::policy::image_encoder::ImageEncoderConfig {
                image_size: 32,
                out_channels: 8,
                widths: vec![8, 12],
                blocks: vec![1, 1],
                ..Default::default()
            };
            let encoder = crate::policy::image_encoder::ImageEncoder::new(cfg, vb.pp("encoder")).unwrap();
            let head = candle_nn::linear(
                8 + crate::policy::flow::ACTION_DIMS + 1,
                crate::policy::flow::ACTION_DIMS + 1,
                vb.pp("head"),
            )
            .unwrap();
            Self { encoder, head }
        }

        /// One optimiser step `step` (1-based); returns the total loss.
        #[allow(clippy::too_many_arguments)]
        fn train_step(
            &self,
            images: &Tensor,
            a1: &Tensor,
            open: &Tensor,
            seed: u64,
            step: u64,
            opt: &mut AdamW,
            ema: &mut Ema,
        ) -> f32 {
            use crate::policy::flow::{
                ACTION_DIMS, FlowTimeSampling, LossWeights, flow_matching_loss, flow_training_sample,
            };
            let mut rng = step_rng(seed, step);
            let sample = flow_training_sample(a1, &mut rng, FlowTimeSampling::Uniform).unwrap();
            let feats = self.encoder.forward_channels_last(images).unwrap().mean((1, 2)).unwrap();
            let input = Tensor::cat(&[&feats, &sample.a_t, &sample.t.unsqueeze(1).unwrap()], 1).unwrap();
            let out = candle_nn::Module::forward(&self.head, &input).unwrap();
            let v_pred = out.narrow(1, 0, ACTION_DIMS).unwrap();
            let open_logit = out.narrow(1, ACTION_DIMS, 1).unwrap().squeeze(1).unwrap();
            let (total, _, _) =
                flow_matching_loss(&v_pred, &sample.target_velocity, &open_logit, open, &LossWeights::default())
                    .unwrap();
            opt.backward_step(&total).unwrap();
            ema.update().unwrap();
            total.to_scalar::<f32>().unwrap()
        }
    }

    #[test]
    fn resumed_training_is_bit_identical_to_uninterrupted() {
        let tmp = TempDir::new("resume");
        let dev = Device::Cpu;
        let images = Tensor::from_vec(
            (0..4 * 3 * 32 * 32).map(|i| ((i * 37) % 251) as u8).collect::<Vec<u8>>(),
            (4, 3, 32, 32),
            &dev,
        )
        .unwrap();
        let a1 = Tensor::randn(0f32, 0.5, (4, crate::policy::flow::ACTION_DIMS), &dev).unwrap();
        let open = Tensor::new(&[1f32, 0.0, 1.0, 0.0], &dev).unwrap();
        let seed = 1234;
        let opt_cfg = AdamWConfig { learning_rate: 1e-3, max_grad_norm: Some(1.0), ..Default::default() };

        // Two runs from the same initial weights.
        let vm_a = VarMap::new();
        let policy_a = MiniPolicy::new(&vm_a);
        let vm_b = VarMap::new();
        let policy_b = MiniPolicy::new(&vm_b);
        copy_weights(&vm_a, &vm_b);

        // Uninterrupted: 6 steps.
        let mut opt_a = AdamW::new(&vm_a, opt_cfg.clone()).unwrap();
        let mut ema_a = Ema::new(&vm_a, EmaConfig::default()).unwrap();
        let losses_a: Vec<f32> =
            (1..=6).map(|s| policy_a.train_step(&images, &a1, &open, seed, s, &mut opt_a, &mut ema_a)).collect();

        // Interrupted: 3 steps, checkpoint, "crash".
        let mut opt_b = AdamW::new(&vm_b, opt_cfg.clone()).unwrap();
        let mut ema_b = Ema::new(&vm_b, EmaConfig::default()).unwrap();
        let mut last = 0.0;
        for s in 1..=3 {
            last = policy_b.train_step(&images, &a1, &open, seed, s, &mut opt_b, &mut ema_b);
        }
        let store = CheckpointStore::open(&tmp.0).unwrap();
        let trainer = TrainerState {
            step: 3,
            seed,
            last_loss: Some(last as f64),
            elapsed_seconds: 0.0,
            extra: serde_json::Value::Null,
        };
        store.save(&serde_json::json!({}), &vm_b, &ema_b, &opt_b, &trainer).unwrap();
        drop((policy_b, opt_b, ema_b, vm_b));

        // Fresh process: new (differently initialised) model, resume.
        let vm_c = VarMap::new();
        let policy_c = MiniPolicy::new(&vm_c);
        let mut opt_c = AdamW::new(&vm_c, opt_cfg).unwrap();
        let mut ema_c = Ema::new(&vm_c, EmaConfig::default()).unwrap();
        let loaded = load_checkpoint(&store.latest().unwrap().unwrap(), &vm_c, &mut ema_c, &mut opt_c).unwrap();
        let losses_c: Vec<f32> = (loaded.trainer.step + 1..=6)
            .map(|s| policy_c.train_step(&images, &a1, &open, loaded.trainer.seed, s, &mut opt_c, &mut ema_c))
            .collect();

        assert_eq!(losses_c, losses_a[3..].to_vec());
        assert_eq!(snapshot(&vm_c), snapshot(&vm_a));
        let (ea, ec) = (ema_a.tensors().unwrap(), ema_c.tensors().unwrap());
        for (name, t) in &ea {
            let a: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            let c: Vec<f32> = ec[name].flatten_all().unwrap().to_vec1().unwrap();
            assert_eq!(a, c, "EMA {name}");
        }
    }

    /// Copies `from`'s weights into `to` (same structure).
    fn copy_weights(from: &VarMap, to: &VarMap) {
        let src = from.data().lock().unwrap();
        for (name, var) in to.data().lock().unwrap().iter() {
            var.set(src[name].as_tensor()).unwrap();
        }
    }

    #[test]
    fn atomic_write_replaces_whole_file() {
        let tmp = TempDir::new("atomic");
        let p = tmp.0.join("a.txt");
        write_atomic(&p, b"first").unwrap();
        write_atomic(&p, b"second").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"second");
        let leftovers = fs::read_dir(&tmp.0).unwrap().count();
        assert_eq!(leftovers, 1, "no temporary files left behind");
    }
}
