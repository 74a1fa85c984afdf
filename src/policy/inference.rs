//! Inference: a trained FlowRAM (its EMA weights) turns an observation into keyframes by Euler
//! integration of the learned velocity field (Algorithm 2, accumulating). The observation is
//! encoded once (image features, the scan state after the language and semantic tokens); each
//! Euler step re-samples the geometric tokens around the current action estimate (DRS) and runs
//! only the suffix of the sequence. Several samples per observation run as one batch.
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::DType;
use candle_nn::{VarBuilder, VarMap};
use rand::SeedableRng;

use crate::policy::checkpoint::format::{CONFIG_FILE, EMA_FILE, read_checkpoint_config, verify_checkpoint_files};
use crate::policy::checkpoint::store::CheckpointStore;
use crate::policy::checkpoint::weights::load_model_weights;
use crate::policy::config::{Consensus, PointerSharpening, PolicyConfig};
use crate::policy::error::{PolicyError, Result};
use crate::policy::flow::{euler_sample, sample_source_noise};
use crate::policy::inputs::{
    Augmentation, InstructionInputs, PreparedObservation, prefix_inputs, prepare, suffix_inputs,
};
use crate::policy::network::model::{EncodedObservation, FlowRam, PosteriorAt, device};
use crate::policy::network::text_encoder::TextEncoder;
use crate::policy::runtime::in_pool;
use crate::policy::scene::observation::{ACTION_DIMS, KeyframePose, Observation};
use crate::policy::scene::radius_schedule::RadiusSchedule;

/// How to sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SamplingOptions {
    /// Euler steps.
    pub steps: usize,
    /// Action samples per observation.
    pub samples: usize,
    /// false: the w/o-DRS ablation (global geometric tokens at every step).
    pub drs: bool,
    /// Seed of the source noise a0.
    pub seed: u64,
    /// Which sample is executed ([`consensus`]).
    pub consensus: Consensus,
    /// The position pointer's temperature over the first Euler steps.
    pub sharpening: PointerSharpening,
}

impl SamplingOptions {
    /// `steps` Euler steps and `samples` samples from noise seed `seed`, with DRS, their medoid
    /// executed, the pointer as trained.
    pub fn new(steps: usize, samples: usize, seed: u64) -> Self {
        Self { steps, samples, drs: true, seed, consensus: Consensus::Medoid, sharpening: PointerSharpening::OFF }
    }

    /// The radius schedule these options sample with, given the checkpoint's `configured` one:
    /// that schedule, or global tokens at every step when `drs` is off.
    pub fn schedule(&self, configured: RadiusSchedule) -> RadiusSchedule {
        if self.drs { configured } else { RadiusSchedule::Global }
    }

    /// Whether sampling uses the Dynamic Radius Schedule: `drs` on and a checkpoint trained with
    /// a dynamic schedule (one trained with `kind = "global"` samples with global tokens).
    pub fn samples_with_drs(&self, configured: RadiusSchedule) -> bool {
        matches!(self.schedule(configured), RadiusSchedule::Dynamic { .. })
    }
}

/// Where the time of one `sample` call went (wall clock, milliseconds).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct SampleProfile {
    /// Geometric token selection (DRS) and the suffix inputs, all Euler steps.
    pub selection_ms: f64,
    /// The network's suffix (tokens, Mamba from the cached prefix, heads), all Euler steps.
    pub network_ms: f64,
}

/// What a sample's pointers said at its last Euler step (world frame, metres): the position
/// pointer's pointed position p, and with `model.relational_pointer` the instruction pointer's
/// position g and beta of the position p + beta (p - g) + offset. A diagnostic (`predict
/// --json`): which part of the readout a wrong keyframe came from.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PointerReadout {
    pub pointed: [f32; 3],
    #[serde(skip_serializing_if = "Option::is_none")]
    pub goal: Option<[f32; 3]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub beta: Option<f32>,
}

/// Keyframe samples of one observation, with their pointers' readouts (empty without
/// `model.position_pointer`).
#[derive(Debug, Clone, PartialEq)]
pub struct Samples {
    pub poses: Vec<KeyframePose>,
    pub pointers: Vec<PointerReadout>,
}

/// A model ready to predict.
pub struct Policy {
    pub model: FlowRam,
    pub text: TextEncoder,
    /// Where the weights came from (None: random initialisation).
    pub checkpoint: Option<PathBuf>,
    /// The null instruction's features (`flow.pointer_sharpening.guidance`).
    null: InstructionInputs,
}

impl Policy {
    /// Loads a checkpoint: a run folder (its latest checkpoint) or a checkpoint folder. Uses the
    /// EMA weights.
    pub fn load(path: &Path, mut text: TextEncoder) -> Result<Self> {
        if !path.is_dir() {
            return Err(PolicyError::File {
                path: path.into(),
                message: "no such folder: expected a run folder (runs/NAME, from `flowram train`) or one of its checkpoints/step-* folders".into(),
            });
        }
        let dir = if path.join("trainer.json").exists() {
            path.to_path_buf()
        } else {
            let root = if path.join("checkpoints").is_dir() { path.join("checkpoints") } else { path.to_path_buf() };
            CheckpointStore::open(&root)?.latest()?.ok_or_else(|| PolicyError::File {
                path: path.into(),
                message:
                    "no checkpoint here: expected a run folder (runs/NAME) or one of its checkpoints/step-* folders"
                        .into(),
            })?
        };
        verify_checkpoint_files(&dir, &[CONFIG_FILE, EMA_FILE])?;
        let config = read_checkpoint_config(&dir)?;
        let varmap = VarMap::new();
        let model = FlowRam::new(&config, VarBuilder::from_varmap(&varmap, DType::F32, &device()))?;
        load_model_weights(&dir.join(EMA_FILE), &varmap)?;
        let null = InstructionInputs::null(&config, &mut text)?;
        Ok(Self { model, text, checkpoint: Some(dir), null })
    }

    /// A randomly initialised model (benchmarks).
    pub fn random(config: &PolicyConfig, mut text: TextEncoder) -> Result<Self> {
        let varmap = VarMap::new();
        let model = FlowRam::new(
            config,
            crate::policy::network::init::seeded_var_builder(&varmap, config.train.seed, &device()),
        )?;
        let null = InstructionInputs::null(config, &mut text)?;
        Ok(Self { model, text, checkpoint: None, null })
    }

    pub fn config(&self) -> &PolicyConfig {
        self.model.config()
    }

    /// Everything that depends only on the observation (not on the weights).
    pub fn prepare(&mut self, observation: &Observation) -> Result<PreparedObservation> {
        prepare(observation, self.model.config(), &mut self.text)
    }

    /// Encodes a prepared observation (image features and the prefix's scan state).
    pub fn encode(&self, prepared: &PreparedObservation) -> Result<EncodedObservation> {
        in_pool(|| {
            let prefix = prefix_inputs(self.model.config(), &[(prepared, Augmentation::NONE)])?;
            self.model.encode(&prefix)
        })
    }

    /// Samples keyframes for an encoded observation.
    pub fn sample(
        &self,
        prepared: &PreparedObservation,
        encoded: &EncodedObservation,
        options: &SamplingOptions,
    ) -> Result<Vec<KeyframePose>> {
        self.sample_profiled(prepared, encoded, options, &mut SampleProfile::default())
    }

    /// [`Self::sample`], adding where the time went to `profile`.
    pub fn sample_profiled(
        &self,
        prepared: &PreparedObservation,
        encoded: &EncodedObservation,
        options: &SamplingOptions,
        profile: &mut SampleProfile,
    ) -> Result<Vec<KeyframePose>> {
        in_pool(|| self.sample_in_pool(prepared, encoded, options, profile, false)).map(|s| s.poses)
    }

    fn sample_in_pool(
        &self,
        prepared: &PreparedObservation,
        encoded: &EncodedObservation,
        options: &SamplingOptions,
        profile: &mut SampleProfile,
        read_out: bool,
    ) -> Result<Samples> {
        let config = self.model.config();
        if options.steps == 0 || options.samples == 0 {
            return Err(PolicyError::Invalid(format!(
                "sampling needs at least 1 Euler step and 1 sample; got {} steps, {} samples",
                options.steps, options.samples
            )));
        }
        options.sharpening.validate()?;
        if options.sharpening.guided() && !config.model.position_pointer {
            return Err(PolicyError::Invalid(format!(
                "the instruction's guidance (flow.pointer_sharpening.guidance, --pointer-guidance {}) guides the \
                 position pointer, and this model has none (model.position_pointer = false): leave it at 1",
                options.sharpening.guidance
            )));
        }
        let s = options.samples;
        // classifier-free guidance: the same observation with the null instruction (the same
        // image features)
        let guidance = options.sharpening.guidance;
        let null = if options.sharpening.guided() {
            let prefix = prefix_inputs(config, &[(&prepared.with_instruction(&self.null), Augmentation::NONE)])?;
            Some(self.model.encode_with_features(encoded.features.clone(), &prefix)?.repeat(s)?)
        } else {
            None
        };
        let encoded = encoded.repeat(s)?;
        let schedule = options.schedule(config.radius_schedule);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(options.seed);
        let a0 = sample_source_noise(&mut rng, s, ACTION_DIMS, &device())?;
        let refs: Vec<(&PreparedObservation, Augmentation)> = vec![(prepared, Augmentation::NONE); s];
        let shared = vec![0usize; s];
        let mut open = None;
        let mut last_pointers = None;
        // the posterior's candidate width in each axis's normalised units (2 / the box's extent)
        let (low, high) = (config.observation.workspace.min(), config.observation.workspace.max());
        let width: [f32; 3] =
            std::array::from_fn(|i| (2.0 * options.sharpening.posterior_width) as f32 / (high[i] - low[i]));
        let a = euler_sample(a0, options.steps, |a, t| {
            let rows: Vec<[f32; ACTION_DIMS]> =
                a.to_vec2::<f32>()?.into_iter().map(|r| std::array::from_fn(|i| r[i])).collect();
            let t0 = Instant::now();
            let suffix = suffix_inputs(config, &refs, &shared, &rows, &vec![t; s], &schedule)?;
            let t1 = Instant::now();
            let posterior = options.sharpening.posterior.then_some(PosteriorAt { t, width });
            let out = self.model.step_guided(
                &encoded,
                &suffix,
                options.sharpening.temperature_at(t),
                posterior,
                null.as_ref().map(|n| (n, guidance)),
            )?;
            profile.selection_ms += (t1 - t0).as_secs_f64() * 1e3;
            profile.network_ms += t1.elapsed().as_secs_f64() * 1e3;
            open = Some(out.open_logit);
            last_pointers = Some((out.pointer, out.relation));
            config.flow.prediction.velocity(out.velocity, a, t)
        })?;
        // The gripper logit of the last step (closest to the data).
        let open = open.ok_or_else(|| PolicyError::Invalid("sampling ran no Euler step".into()))?;
        let rows = a.to_vec2::<f32>()?;
        let open = open.to_vec1::<f32>()?;
        let poses = rows
            .iter()
            .zip(open)
            .map(|(r, o)| KeyframePose::from_action(&std::array::from_fn(|i| r[i]), o, &config.observation.workspace))
            .collect();
        let pointers = match last_pointers {
            Some((Some((log_weights, candidates)), relation)) if read_out => {
                pointer_readouts(&log_weights, &candidates, relation.as_ref(), &config.observation.workspace)?
            }
            _ => Vec::new(),
        };
        Ok(Samples { poses, pointers })
    }

    /// Observation in, one keyframe out: the [`consensus`] of `options.samples` samples (with 1
    /// sample, that sample).
    pub fn predict_keyframe(&mut self, observation: &Observation, options: &SamplingOptions) -> Result<KeyframePose> {
        let poses = self.predict(observation, options)?;
        consensus(&poses, options.consensus).ok_or_else(|| PolicyError::Invalid("sampling returned no keyframe".into()))
    }

    /// Observation in, keyframes out.
    pub fn predict(&mut self, observation: &Observation, options: &SamplingOptions) -> Result<Vec<KeyframePose>> {
        self.predict_reading_out(observation, options, false).map(|s| s.poses)
    }

    /// [`Self::predict`], with what each sample's pointers said at its last Euler step.
    pub fn predict_explained(&mut self, observation: &Observation, options: &SamplingOptions) -> Result<Samples> {
        self.predict_reading_out(observation, options, true)
    }

    fn predict_reading_out(
        &mut self,
        observation: &Observation,
        options: &SamplingOptions,
        read_out: bool,
    ) -> Result<Samples> {
        in_pool(|| {
            let prepared = self.prepare(observation)?;
            let encoded = self.encode(&prepared)?;
            self.sample_in_pool(&prepared, &encoded, options, &mut SampleProfile::default(), read_out)
        })
    }
}

/// The pointers' readouts of a batch, in the world frame: p = the attention [B, N] (log) over
/// the candidates' normalised positions [B, N, 3]; with `relation`, beta [B, 1] and g [B, 3]
/// (normalised).
fn pointer_readouts(
    log_weights: &candle_core::Tensor,
    candidates: &candle_core::Tensor,
    relation: Option<&(candle_core::Tensor, candle_core::Tensor)>,
    workspace: &crate::policy::scene::workspace::WorkspaceBounds,
) -> Result<Vec<PointerReadout>> {
    let pointed = log_weights.exp()?.unsqueeze(1)?.matmul(candidates)?.squeeze(1)?.to_vec2::<f32>()?;
    let (betas, goals) = match relation {
        Some((beta, goal)) => (Some(beta.flatten_all()?.to_vec1::<f32>()?), Some(goal.to_vec2::<f32>()?)),
        None => (None, None),
    };
    let world = |r: &[f32]| workspace.denormalize(std::array::from_fn(|i| r[i]));
    Ok(pointed
        .iter()
        .enumerate()
        .map(|(i, p)| PointerReadout {
            pointed: world(p),
            goal: goals.as_ref().map(|g| world(&g[i])),
            beta: betas.as_ref().map(|b| b[i]),
        })
        .collect())
}

/// Metres: samples closer than this count as one mode in [`Consensus::Mode`] (half a 4 cm block;
/// the same as `flow.pointer_sigma`'s default, not tied to it).
pub const MODE_RADIUS: f64 = 0.02;

/// The consensus of several samples of one observation's keyframe, whole: its rotation and
/// gripper come with it, never an average of two modes. Flow matching samples every mode of the
/// demonstrations (the left or the right side of the block, one button or the next, any of four
/// blocks of the named colour); a single sample lands on a minority mode as often as that mode's
/// share, a consensus of several on the majority's.
/// - [`Consensus::Medoid`]: the sample with the least summed distance to the others. With two
///   modes it is the majority's; with many, spread over the table, it leans to the sample
///   nearest the middle of them all, which need not be the most sampled.
/// - [`Consensus::Mode`]: the sample with the most others within [`MODE_RADIUS`]; among equals,
///   the least summed distance to all samples (so the medoid whenever no two samples are that
///   close).
///
/// Samples with a non-finite position take no part (if all have one, the first is returned, for
/// the caller's checks to reject). `None` for no samples.
pub fn consensus(poses: &[KeyframePose], rule: Consensus) -> Option<KeyframePose> {
    let distance = |a: &KeyframePose, b: &KeyframePose| {
        (0..3).map(|i| (f64::from(a.position[i]) - f64::from(b.position[i])).powi(2)).sum::<f64>().sqrt()
    };
    let finite: Vec<&KeyframePose> = poses.iter().filter(|p| p.position.iter().all(|v| v.is_finite())).collect();
    if finite.is_empty() {
        return poses.first().copied();
    }
    // (neighbours within the radius, summed distance): the most neighbours, then the least sum
    let score = |p: &KeyframePose| {
        let distances = finite.iter().map(|q| distance(p, q));
        let neighbours = match rule {
            Consensus::Medoid => 0,
            Consensus::Mode => distances.clone().filter(|&d| d < MODE_RADIUS).count(),
        };
        (neighbours, distances.sum::<f64>())
    };
    finite
        .iter()
        .map(|&p| (p, score(p)))
        // the first of equals: with one sample, or identical samples, the first
        .fold(None, |best: Option<(&KeyframePose, (usize, f64))>, (p, (n, d))| match best {
            Some((_, (bn, bd))) if bn > n || (bn == n && bd <= d) => best,
            _ => Some((p, (n, d))),
        })
        .map(|(p, _)| *p)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drs_is_the_configured_dynamic_schedule_unless_switched_off() {
        let dynamic = RadiusSchedule::default();
        let on = SamplingOptions::new(8, 1, 0);
        let off = SamplingOptions { drs: false, ..on };
        assert_eq!(on.schedule(dynamic), dynamic);
        assert_eq!(off.schedule(dynamic), RadiusSchedule::Global);
        assert!(on.samples_with_drs(dynamic));
        assert!(!off.samples_with_drs(dynamic));
        // A checkpoint trained with global tokens samples with them whatever the option says.
        assert_eq!(on.schedule(RadiusSchedule::Global), RadiusSchedule::Global);
        assert!(!on.samples_with_drs(RadiusSchedule::Global));
    }

    fn at(x: f32, open: bool) -> KeyframePose {
        KeyframePose { position: [x, 0.0, 0.2], quat_wxyz: [1.0, 0.0, 0.0, 0.0], gripper_open: open }
    }

    #[test]
    fn the_consensus_is_the_majority_modes_sample_not_an_average() {
        // Two samples near x = 0.3 (one closed), one at x = -0.3: the medoid is the middle one of
        // the majority, whole, not the mean x = 0.1 between the modes.
        let poses = [at(-0.3, true), at(0.31, false), at(0.30, true), at(0.32, true)];
        let c = consensus(&poses, Consensus::Medoid).unwrap();
        assert_eq!(c.position, [0.31, 0.0, 0.2]);
        assert!(!c.gripper_open, "the medoid's own gripper comes with it");
        assert_eq!(consensus(&poses[..1], Consensus::Medoid).unwrap(), poses[0]);
        assert_eq!(consensus(&[at(0.1, true), at(0.1, false)], Consensus::Medoid).unwrap(), at(0.1, true));
        for rule in [Consensus::Medoid, Consensus::Mode] {
            assert!(consensus(&[], rule).is_none());
        }
        // A non-finite sample takes no part; all non-finite: the first, for the caller to reject.
        let nan = at(f32::NAN, true);
        assert_eq!(
            consensus(&[at(0.2, true), nan, at(0.21, false), at(0.5, true)], Consensus::Medoid).unwrap(),
            at(0.21, false)
        );
        assert!(consensus(&[nan, nan], Consensus::Mode).unwrap().position[0].is_nan());
    }

    #[test]
    fn the_mode_goes_with_the_most_samples_where_the_medoid_leans_to_the_middle() {
        // Four objects on a line, 15 cm apart: three samples on the first, one on the second,
        // two on the third, one on the fourth. The medoid is the lone sample on the second (in
        // the middle of them all); the mode is one of the three, the one with the least summed
        // distance to all samples (the one nearest the rest), whole.
        let poses = [
            at(0.0, true),
            at(0.004, true),
            at(0.008, false),
            at(0.15, true),
            at(0.3, true),
            at(0.31, true),
            at(0.45, true),
        ];
        assert_eq!(consensus(&poses, Consensus::Medoid).unwrap(), at(0.15, true));
        assert_eq!(consensus(&poses, Consensus::Mode).unwrap(), at(0.008, false));
        // No two samples within the radius: the mode is the medoid.
        let spread = [at(0.0, true), at(0.1, true), at(0.15, false), at(0.3, true)];
        assert_eq!(consensus(&spread, Consensus::Mode), consensus(&spread, Consensus::Medoid));
        assert_eq!(consensus(&poses[..1], Consensus::Mode).unwrap(), poses[0]);
    }
}
