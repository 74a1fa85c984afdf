//! Training FlowRAM on demonstration datasets (Algorithm 1 of the supplementary): uniform
//! sampling over tasks and variations, conditional flow matching with the supplementary's loss
//! weights, AdamW, EMA, augmentation, metrics, checkpoints, and an exact `--resume`.
//!
//! Run folder (`--out runs/NAME`): `checkpoints/` (see `checkpoint`), `metrics.csv`, `loss.png`.
//! Every step's randomness is a pure function of (seed, step), so a run killed and resumed from
//! its last checkpoint continues exactly as the uninterrupted run would have.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use candle_core::Tensor;
use candle_nn::VarMap;
use rand::Rng;

use super::checkpoint::{CheckpointStore, TrainerState, load_checkpoint, step_rng_for};
use super::config::PolicyConfig;
use super::error::{PolicyError, Result};
use super::flow::{LossWeights, flow_matching_loss, sample_source_noise};
use super::inputs::{Augmentation, PreparedObservation, prefix_inputs, prepare, suffix_inputs};
use super::metrics::{MetricsLog, MetricsRow, plot_loss_curve, read_metrics};
use super::model::{ACTION_DIMS, FlowRam, device};
use super::observation::Observation;
use super::optim::{AdamW, AdamWConfig, Ema, EmaConfig};
use super::text::TextEncoder;
use crate::data::Episode;

/// One training sample: keyframe `k` of episode `episode`.
#[derive(Debug, Clone, Copy)]
struct SampleRef {
    episode: usize,
    k: usize,
}

/// Demonstrations grouped by task and variation, with observations prepared lazily (and kept).
pub struct TrainingData {
    episodes: Vec<Episode>,
    /// task -> variation -> episode indices.
    groups: BTreeMap<String, BTreeMap<usize, Vec<usize>>>,
    prepared: Vec<Vec<Option<Arc<PreparedObservation>>>>,
}

impl TrainingData {
    /// Loads dataset folders (episodes that fail to load are reported on stderr and skipped).
    pub fn load(dirs: &[PathBuf]) -> Result<Self> {
        let mut episodes = Vec::new();
        for dir in dirs {
            let loaded = crate::data::load_dataset(dir)
                .map_err(|e| PolicyError::File { path: dir.clone(), message: e.to_string() })?;
            for (path, e) in &loaded.failures {
                eprintln!("warning: skipping {}: {e}", path.display());
            }
            episodes.extend(loaded.episodes);
        }
        Self::from_episodes(episodes)
    }

    pub fn from_episodes(episodes: Vec<Episode>) -> Result<Self> {
        let episodes: Vec<Episode> = episodes.into_iter().filter(|e| e.success && e.keyframes() > 0).collect();
        if episodes.is_empty() {
            return Err(PolicyError::Invalid(
                "no successful episode with keyframes to train on: collect some with `flowram collect`".into(),
            ));
        }
        let cameras = &episodes[0].cameras;
        let mut groups: BTreeMap<String, BTreeMap<usize, Vec<usize>>> = BTreeMap::new();
        for (i, e) in episodes.iter().enumerate() {
            if &e.cameras != cameras || e.height != episodes[0].height {
                return Err(PolicyError::Invalid(format!(
                    "datasets disagree on cameras or image size ({:?} {}px vs {:?} {}px): train on datasets collected alike",
                    e.cameras, e.height, cameras, episodes[0].height
                )));
            }
            groups.entry(e.task.clone()).or_default().entry(e.variation).or_default().push(i);
        }
        let prepared = episodes.iter().map(|e| vec![None; e.keyframes()]).collect();
        Ok(Self { episodes, groups, prepared })
    }

    pub fn episodes(&self) -> &[Episode] {
        &self.episodes
    }

    /// Keyframe samples in all.
    pub fn samples(&self) -> usize {
        self.episodes.iter().map(Episode::keyframes).sum()
    }

    /// A task uniformly, then a variation of it uniformly, an episode of that, a keyframe.
    fn draw(&self, rng: &mut impl Rng) -> SampleRef {
        let tasks: Vec<&BTreeMap<usize, Vec<usize>>> = self.groups.values().collect();
        let variations = tasks[rng.random_range(0..tasks.len())];
        let episodes: Vec<&Vec<usize>> = variations.values().collect();
        let of_variation = episodes[rng.random_range(0..episodes.len())];
        let episode = of_variation[rng.random_range(0..of_variation.len())];
        SampleRef { episode, k: rng.random_range(0..self.episodes[episode].keyframes()) }
    }

    fn prepared(
        &mut self,
        s: SampleRef,
        config: &PolicyConfig,
        text: &mut TextEncoder,
    ) -> Result<Arc<PreparedObservation>> {
        if let Some(p) = &self.prepared[s.episode][s.k] {
            return Ok(p.clone());
        }
        let observation = Observation::from_episode(&self.episodes[s.episode], s.k)?;
        let p = Arc::new(prepare(&observation, config, text)?);
        self.prepared[s.episode][s.k] = Some(p.clone());
        Ok(p)
    }
}

/// The losses of one step (unweighted components and the weighted total).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepLoss {
    pub total: f64,
    pub cfm: f64,
    pub bce: f64,
}

/// A model with its optimiser and EMA.
pub struct Trainer {
    pub config: PolicyConfig,
    pub varmap: VarMap,
    pub model: FlowRam,
    pub optimizer: AdamW,
    pub ema: Ema,
    pub step: u64,
    pub elapsed_seconds: f64,
}

impl Trainer {
    /// A freshly initialised model (initialisation seeded by `config.train.seed`).
    pub fn new(config: &PolicyConfig) -> Result<Self> {
        let varmap = VarMap::new();
        let vb = super::init::seeded_var_builder(&varmap, config.train.seed, &device());
        let model = FlowRam::new(config, vb)?;
        let t = &config.train;
        let optimizer = AdamW::new(
            &varmap,
            AdamWConfig {
                learning_rate: t.learning_rate,
                weight_decay: t.weight_decay,
                beta1: t.betas[0],
                beta2: t.betas[1],
                eps: 1e-8,
                max_grad_norm: (t.grad_clip > 0.0).then_some(t.grad_clip),
            },
        )?;
        let ema = Ema::new(&varmap, EmaConfig { decay: t.ema_decay, warmup: true })?;
        Ok(Self { config: config.clone(), varmap, model, optimizer, ema, step: 0, elapsed_seconds: 0.0 })
    }

    /// One optimiser step on a batch drawn with the randomness of step `self.step + 1`.
    pub fn train_step(&mut self, data: &mut TrainingData, text: &mut TextEncoder) -> Result<StepLoss> {
        // on a pool thread: see runtime::in_pool
        super::runtime::in_pool(|| self.train_step_in_pool(data, text))
    }

    fn train_step_in_pool(&mut self, data: &mut TrainingData, text: &mut TextEncoder) -> Result<StepLoss> {
        let step = self.step + 1;
        self.optimizer.set_learning_rate(self.config.learning_rate_at(step))?;
        let config = &self.config;
        let t_cfg = &config.train;
        let ws = &config.observation.workspace;
        let mut draw_rng = step_rng_for(t_cfg.seed, step, "batch");
        let mut aug_rng = step_rng_for(t_cfg.seed, step, "augment");
        let mut noise_rng = step_rng_for(t_cfg.seed, step, "noise");
        let b = t_cfg.batch;
        let mut samples = Vec::with_capacity(b);
        let mut targets = Vec::with_capacity(b);
        let mut opens = Vec::with_capacity(b);
        let (lo, hi) = (ws.min(), ws.max());
        for _ in 0..b {
            let s = data.draw(&mut draw_rng);
            let prepared = data.prepared(s, config, text)?;
            let j = t_cfg.translation_jitter as f32;
            let shift: [f32; 3] = std::array::from_fn(|a| 2.0 * aug_rng.random_range(-j..=j) / (hi[a] - lo[a]));
            let bj = t_cfg.brightness_jitter as f32;
            let brightness = 1.0 + aug_rng.random_range(-bj..=bj);
            let action = Observation::episode_action(&data.episodes[s.episode], s.k);
            let mut a1 = action.to_action(ws)?;
            for a in 0..3 {
                a1[a] += shift[a];
            }
            targets.push(a1);
            opens.push(if action.gripper_open { 1.0f32 } else { 0.0 });
            samples.push((prepared, Augmentation { shift, brightness }));
        }
        let a1 =
            Tensor::from_vec(targets.iter().flatten().copied().collect::<Vec<f32>>(), (b, ACTION_DIMS), &device())?;
        let a0 = sample_source_noise(&mut noise_rng, b, ACTION_DIMS, &device())?;
        let t: Vec<f32> = (0..b).map(|_| noise_rng.random_range(0.0f32..1.0)).collect();
        let t_tensor = Tensor::from_vec(t.clone(), (b, 1), &device())?;
        let a_t = (a0.broadcast_mul(&t_tensor.affine(-1.0, 1.0)?)? + a1.broadcast_mul(&t_tensor)?)?;
        let target = (&a1 - &a0)?;
        let a_t_rows: Vec<[f32; 9]> =
            a_t.to_vec2::<f32>()?.into_iter().map(|r| std::array::from_fn(|i| r[i])).collect();
        let refs: Vec<(&PreparedObservation, Augmentation)> = samples.iter().map(|(p, a)| (p.as_ref(), *a)).collect();
        let prefix = prefix_inputs(config, &refs)?;
        let own: Vec<usize> = (0..b).collect();
        let suffix = suffix_inputs(config, &refs, &own, &a_t_rows, &t, &config.radius_schedule)?;
        let out = self.model.forward(&prefix, &suffix)?;
        let weights = LossWeights { cfm: config.flow.cfm_weight, open: config.flow.open_weight };
        let open_target = Tensor::from_vec(opens, b, &device())?;
        let (total, cfm, bce) = flow_matching_loss(&out.velocity, &target, &out.open_logit, &open_target, &weights)?;
        self.optimizer.backward_step(&total)?;
        self.ema.update()?;
        self.step = step;
        Ok(StepLoss {
            total: total.to_scalar::<f32>()? as f64,
            cfm: cfm.to_scalar::<f32>()? as f64,
            bce: bce.to_scalar::<f32>()? as f64,
        })
    }

    fn trainer_state(&self, last_loss: Option<f64>) -> TrainerState {
        TrainerState {
            step: self.step,
            seed: self.config.train.seed,
            last_loss,
            elapsed_seconds: self.elapsed_seconds,
            extra: serde_json::Value::Null,
        }
    }

    /// Saves a checkpoint into `run/checkpoints`.
    pub fn save(&self, run: &Path, last_loss: Option<f64>) -> Result<PathBuf> {
        let store = CheckpointStore::open(run.join("checkpoints"))?;
        let config = serde_json::to_value(&self.config)
            .map_err(|e| PolicyError::Invalid(format!("cannot serialise the config: {e}")))?;
        store.save(&config, &self.varmap, &self.ema, &self.optimizer, &self.trainer_state(last_loss))
    }

    /// Resumes from the latest checkpoint of a run (its stored config wins).
    pub fn resume(run: &Path) -> Result<Self> {
        let store = CheckpointStore::open(run.join("checkpoints"))?;
        let dir = store.latest()?.ok_or_else(|| PolicyError::File {
            path: run.join("checkpoints"),
            message: "no checkpoint to resume from: start the run without --resume".into(),
        })?;
        let config = read_checkpoint_config(&dir)?;
        let mut trainer = Self::new(&config)?;
        let loaded = load_checkpoint(&dir, &trainer.varmap, &mut trainer.ema, &mut trainer.optimizer)?;
        trainer.step = loaded.trainer.step;
        trainer.elapsed_seconds = loaded.trainer.elapsed_seconds;
        Ok(trainer)
    }
}

/// The config stored in a checkpoint directory.
pub fn read_checkpoint_config(dir: &Path) -> Result<PolicyConfig> {
    let path = dir.join("config.json");
    let text = std::fs::read_to_string(&path)
        .map_err(|e| PolicyError::File { path: path.clone(), message: format!("cannot read: {e}") })?;
    let config: PolicyConfig = serde_json::from_str(&text)
        .map_err(|e| PolicyError::File { path: path.clone(), message: format!("not a policy config: {e}") })?;
    config.validate().map_err(|e| PolicyError::File { path, message: e.to_string() })?;
    Ok(config)
}

/// Progress of a training run, for a progress bar.
pub trait TrainProgress {
    fn step(&mut self, step: u64, total: u64, loss: &StepLoss);
}

/// Trains until `config.train.steps`, logging and checkpointing into `run`. With `resume`, the
/// run continues from its latest checkpoint (metrics after it are dropped and redone).
pub fn train(
    run: &Path,
    config: Option<&PolicyConfig>,
    data: &mut TrainingData,
    text: &mut TextEncoder,
    resume: bool,
    steps_override: Option<usize>,
    progress: &mut dyn TrainProgress,
) -> Result<Trainer> {
    std::fs::create_dir_all(run)
        .map_err(|e| PolicyError::File { path: run.into(), message: format!("cannot create the run folder: {e}") })?;
    let mut trainer = if resume {
        Trainer::resume(run)?
    } else {
        let config = config.ok_or_else(|| PolicyError::Invalid("a new run needs a config".into()))?;
        if CheckpointStore::open(run.join("checkpoints"))?.latest()?.is_some() {
            return Err(PolicyError::File {
                path: run.into(),
                message: "this run already has checkpoints: pass --resume to continue it, or choose another --out"
                    .into(),
            });
        }
        Trainer::new(config)?
    };
    if let Some(steps) = steps_override {
        trainer.config.train.steps = steps;
    }
    let metrics_path = run.join("metrics.csv");
    let mut log =
        if resume { MetricsLog::resume(&metrics_path, trainer.step)? } else { MetricsLog::create(&metrics_path)? };
    let total = trainer.config.train.steps as u64;
    let (log_every, checkpoint_every) =
        (trainer.config.train.log_every as u64, trainer.config.train.checkpoint_every as u64);
    while trainer.step < total {
        let started = std::time::Instant::now();
        let loss = trainer.train_step(data, text)?;
        trainer.elapsed_seconds += started.elapsed().as_secs_f64();
        progress.step(trainer.step, total, &loss);
        if trainer.step % log_every == 0 || trainer.step == total {
            log.append(&MetricsRow {
                step: trainer.step,
                loss: loss.total,
                cfm: loss.cfm,
                bce: loss.bce,
                lr: trainer.optimizer.learning_rate(),
                seconds: trainer.elapsed_seconds,
            })?;
        }
        if trainer.step % checkpoint_every == 0 || trainer.step == total {
            trainer.save(run, Some(loss.total))?;
            plot_loss_curve(&read_metrics(&metrics_path)?, &run.join("loss.png"), 900, 500)?;
        }
    }
    Ok(trainer)
}
