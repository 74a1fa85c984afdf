//! Training FlowRAM on demonstration datasets (Algorithm 1 of the supplementary): uniform
//! sampling over tasks and variations, conditional flow matching with the supplementary's loss
//! weights, AdamW, EMA, augmentation, metrics, checkpoints, and an exact `--resume`.
//!
//! Run folder (`runs/NAME`): `checkpoints/` (see `policy::checkpoint`), `metrics.csv`, `loss.png`.
//! Every step's randomness is a pure function of (seed, step), so a run killed and resumed from
//! its last checkpoint continues exactly as the uninterrupted run would have.
use std::path::{Path, PathBuf};
use std::sync::Arc;

use candle_core::Tensor;
use candle_nn::VarMap;
use rand::Rng;

use super::adamw::{AdamW, AdamWConfig};
use super::checkpointing::{load_checkpoint, save_checkpoint};
use super::data::TrainingData;
use super::ema::{Ema, EmaConfig};
use super::loss_plot::plot_loss_curve;
use super::lr_schedule::LearningRateSchedule;
use super::rng::step_rng_for;
use crate::policy::checkpoint::format::{TrainerState, read_checkpoint_config};
use crate::policy::checkpoint::store::CheckpointStore;
use crate::policy::config::{GoalKeyframe, GoalTarget, PointerTarget, PolicyConfig};
use crate::policy::error::{PolicyError, Result};
use crate::policy::flow::{
    LossWeights, flow_matching_loss, flow_training_sample, grounding_labels, grounding_loss, pointer_loss,
    relational_pointer_target,
};
use crate::policy::inputs::{Augmentation, InstructionInputs, PreparedObservation, prefix_inputs, suffix_inputs};
use crate::policy::network::init::seeded_var_builder;
use crate::policy::network::model::{FlowRam, device};
use crate::policy::network::text_encoder::TextEncoder;
use crate::policy::runtime::in_pool;
use crate::policy::scene::observation::{ACTION_DIMS, Observation, stage_end};
use crate::policy::training::metrics::{MetricsLog, MetricsRow, read_metrics};

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
        let vb = seeded_var_builder(&varmap, config.train.seed, &device());
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
        in_pool(|| self.train_step_in_pool(data, text))
    }

    fn train_step_in_pool(&mut self, data: &mut TrainingData, text: &mut TextEncoder) -> Result<StepLoss> {
        let step = self.step + 1;
        self.optimizer.set_learning_rate(LearningRateSchedule::of(&self.config.train).at(step))?;
        let config = &self.config;
        let t_cfg = &config.train;
        let ws = &config.observation.workspace;
        let mut draw_rng = step_rng_for(t_cfg.seed, step, "batch");
        let mut aug_rng = step_rng_for(t_cfg.seed, step, "augment");
        let mut noise_rng = step_rng_for(t_cfg.seed, step, "noise");
        let mut dropout_rng = step_rng_for(t_cfg.seed, step, "instruction-dropout");
        let dropout = config.flow.instruction_dropout;
        let null = if dropout > 0.0 { Some(InstructionInputs::null(config, text)?) } else { None };
        let b = t_cfg.batch;
        // K flow samples per observation: rows i * K .. (i + 1) * K belong to observation i.
        let k = t_cfg.flow_samples;
        let mut samples = Vec::with_capacity(b);
        let mut targets = Vec::with_capacity(b * k);
        // The goal keyframe's position (`flow.goal_keyframe`), shifted with its observation (`flow.goal_weight`).
        let mut goals = Vec::with_capacity(b * 3);
        let mut opens = Vec::with_capacity(b * k);
        // The positions of the episode's keyframes from the sample's on, shifted with its
        // observation (`flow.grounding_weight`).
        let grounding = config.flow.grounding_weight > 0.0;
        let mut later: Vec<Vec<[f32; 3]>> = Vec::with_capacity(if grounding { b } else { 0 });
        let (lo, hi) = (ws.min(), ws.max());
        for _ in 0..b {
            let s = data.draw(&mut draw_rng, &t_cfg.task_weights);
            let mut prepared = data.prepared(s, config, text)?;
            if let Some(null) = &null
                && dropout_rng.random_bool(dropout)
            {
                prepared = Arc::new(prepared.with_instruction(null));
            }
            let j = t_cfg.translation_jitter as f32;
            let shift: [f32; 3] = std::array::from_fn(|a| 2.0 * aug_rng.random_range(-j..=j) / (hi[a] - lo[a]));
            let bj = t_cfg.brightness_jitter as f32;
            let brightness = 1.0 + aug_rng.random_range(-bj..=bj);
            let episode = &data.episodes()[s.episode];
            let action = Observation::episode_action(episode, s.k);
            let mut a1 = action.to_action(ws)?;
            for a in 0..3 {
                a1[a] += shift[a];
            }
            if config.flow.goal_weight > 0.0 {
                let goal_k = match config.flow.goal_keyframe {
                    GoalKeyframe::Last => episode.keyframes() - 1,
                    GoalKeyframe::StageEnd => stage_end(&episode.action, s.k),
                };
                let goal = Observation::episode_action(episode, goal_k).to_action(ws)?;
                goals.extend((0..3).map(|a| goal[a] + shift[a]));
            }
            if grounding {
                let positions = (s.k..episode.keyframes())
                    .map(|j| {
                        let a = Observation::episode_action(episode, j).to_action(ws)?;
                        Ok(std::array::from_fn(|i| a[i] + shift[i]))
                    })
                    .collect::<Result<Vec<[f32; 3]>>>()?;
                later.push(positions);
            }
            for _ in 0..k {
                targets.push(a1);
                opens.push(if action.gripper_open { 1.0f32 } else { 0.0 });
            }
            samples.push((prepared, Augmentation { shift, brightness }));
        }
        let a1 =
            Tensor::from_vec(targets.iter().flatten().copied().collect::<Vec<f32>>(), (b * k, ACTION_DIMS), &device())?;
        // Algorithm 1: a0 then t from the noise stream, a_t on the straight path, target a1 - a0.
        let flow = flow_training_sample(&a1, &mut noise_rng, config.flow.time_sampling)?;
        let target = config.flow.prediction.target(&flow, &a1);
        let t: Vec<f32> = flow.t.to_vec1()?;
        let a_t_rows: Vec<[f32; ACTION_DIMS]> =
            flow.a_t.to_vec2::<f32>()?.into_iter().map(|r| std::array::from_fn(|i| r[i])).collect();
        let refs: Vec<(&PreparedObservation, Augmentation)> = samples.iter().map(|(p, a)| (p.as_ref(), *a)).collect();
        let prefix = prefix_inputs(config, &refs)?;
        let own: Vec<usize> = (0..b * k).map(|i| i / k).collect();
        let per_sample: Vec<(&PreparedObservation, Augmentation)> = own.iter().map(|&i| refs[i]).collect();
        let suffix = suffix_inputs(config, &per_sample, &own, &a_t_rows, &t, &config.radius_schedule)?;
        let out = self.model.forward(&prefix, &suffix)?;
        let weights = LossWeights { cfm: config.flow.cfm_weight, open: config.flow.open_weight };
        let open_target = Tensor::from_vec(opens, b * k, &device())?;
        let (mut total, cfm, bce) =
            flow_matching_loss(&out.velocity, &target, &out.open_logit, &open_target, &weights)?;
        let half_extent: [f32; 3] = std::array::from_fn(|a| (hi[a] - lo[a]) / 2.0);
        if let Some((log_weights, candidates)) = &out.pointer
            && config.flow.pointer_weight > 0.0
        {
            let mut position = a1.narrow(1, 0, 3)?;
            if config.flow.pointer_target == PointerTarget::Relational {
                let (beta, goal) = out.relation.as_ref().ok_or_else(|| {
                    PolicyError::Invalid(
                        "flow.pointer_target = \"relational\" but the model returned no relation \
                         (model.relational_pointer must be on)"
                            .into(),
                    )
                })?;
                position = relational_pointer_target(&position, beta, goal)?;
            }
            let pointer = pointer_loss(log_weights, candidates, &position, half_extent, config.flow.pointer_sigma)?;
            total = total.add(&pointer.affine(config.flow.pointer_weight, 0.0)?)?;
        }
        if let Some(log_weights) = &out.goal
            && config.flow.goal_weight > 0.0
        {
            let goal = Tensor::from_vec(goals, (b, 3), &device())?;
            let extent = match config.flow.goal_target {
                GoalTarget::Keyframe => half_extent,
                // Horizontal distance: a zero scale on z.
                GoalTarget::Under => [half_extent[0], half_extent[1], 0.0],
            };
            let loss = pointer_loss(log_weights, &prefix.semantic_xyz, &goal, extent, config.flow.pointer_sigma)?;
            total = total.add(&loss.affine(config.flow.goal_weight, 0.0)?)?;
        }
        if let Some(scores) = &out.grounding
            && grounding
        {
            let xyz = prefix.semantic_xyz.to_vec3::<f32>()?;
            let labels: Vec<f32> = xyz
                .iter()
                .zip(&later)
                .flat_map(|(row, later)| {
                    let row: Vec<[f32; 3]> = row.iter().map(|p| [p[0], p[1], p[2]]).collect();
                    grounding_labels(&row, later, half_extent, config.flow.grounding_radius)
                })
                .collect();
            let labels = Tensor::from_vec(labels, scores.dims2()?, &device())?;
            let loss = grounding_loss(scores, &labels)?;
            total = total.add(&loss.affine(config.flow.grounding_weight, 0.0)?)?;
        }
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
        save_checkpoint(&store, &config, &self.varmap, &self.ema, &self.optimizer, &self.trainer_state(last_loss))
    }

    /// Resumes from the latest checkpoint of a run (its stored config wins).
    pub fn resume(run: &Path) -> Result<Self> {
        let store = CheckpointStore::open(run.join("checkpoints"))?;
        let dir = store.latest()?.ok_or_else(|| PolicyError::NoCheckpoint { checkpoints: run.join("checkpoints") })?;
        let config = read_checkpoint_config(&dir)?;
        let mut trainer = Self::new(&config)?;
        let loaded = load_checkpoint(&dir, &trainer.varmap, &mut trainer.ema, &mut trainer.optimizer)?;
        trainer.step = loaded.trainer.step;
        trainer.elapsed_seconds = loaded.trainer.elapsed_seconds;
        Ok(trainer)
    }
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
            return Err(PolicyError::RunHasCheckpoints { run: run.to_path_buf() });
        }
        Trainer::new(config)?
    };
    if let Some(steps) = steps_override {
        trainer.config.train.steps = steps;
    }
    data.check_task_weights(&trainer.config.train.task_weights)?;
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
