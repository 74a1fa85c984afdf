//! From observations to the network's batched input tensors: images in CHW order, the lifted
//! workspace cloud and its semantic tokens, the instruction's token features, proprioception;
//! and per flow step the geometric tokens chosen by the radius schedule around the noisy action.
//! Augmentation (training) shifts a sample's whole scene and scales its brightness.
use candle_core::{DType, Tensor};

use crate::policy::config::{MAX_KEYFRAME_INDEX, PolicyConfig};
use crate::policy::error::{PolicyError, Result};
use crate::policy::network::model::{PrefixInputs, SuffixInputs};
use crate::policy::network::text_encoder::{TEXT_HIDDEN_SIZE, TextEncoder};
use crate::policy::scene::observation::{ACTION_DIMS, Observation, SceneCloud, lift_scene, proprio_history_features};
use crate::policy::scene::radius_schedule::{RadiusSchedule, select_geometric_tokens_cached};
use crate::policy::scene::token_order::sort_far_to_near;

/// An observation turned into what the network needs (everything that does not depend on the
/// network's weights, computed once per observation).
#[derive(Debug, Clone)]
pub struct PreparedObservation {
    /// u8 [cams, 3, H, W].
    pub images: Vec<u8>,
    pub cameras: usize,
    pub cloud: SceneCloud,
    /// The current gripper pose's features, then those of the `observation.proprio_history - 1`
    /// poses before it.
    pub proprio: Vec<[f32; 10]>,
    /// [Lt, 384] instruction token features, zero-padded or truncated to Lt.
    pub language: Tensor,
    /// The instruction's sentence embedding (384, L2-normalised mean of the token features).
    pub instruction: Vec<f32>,
    /// Keyframes executed before the observation, clipped to [`MAX_KEYFRAME_INDEX`].
    pub keyframe: u32,
}

/// Per-sample augmentation: a shift of the scene (normalised workspace units, added to points,
/// proprioception and action positions) and a brightness factor.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Augmentation {
    pub shift: [f32; 3],
    pub brightness: f32,
}

impl Augmentation {
    pub const NONE: Augmentation = Augmentation { shift: [0.0; 3], brightness: 1.0 };
}

pub fn prepare(
    observation: &Observation,
    config: &PolicyConfig,
    text: &mut TextEncoder,
) -> Result<PreparedObservation> {
    let o = &config.observation;
    if observation.size != o.image_size {
        return Err(PolicyError::Invalid(format!(
            "the observation has {0}x{0} images; this policy was configured for {1}x{1} (observation.image_size)",
            observation.size, o.image_size
        )));
    }
    let selected;
    let observation = if o.cameras.is_empty() {
        observation
    } else {
        selected = select_cameras(observation, &o.cameras)?;
        &selected
    };
    let (h, w) = (observation.size, observation.size);
    let mut images = Vec::with_capacity(observation.cameras.len() * 3 * h * w);
    for view in &observation.cameras {
        for ch in 0..3 {
            images.extend(view.rgb.iter().skip(ch).step_by(3).copied());
        }
    }
    let cloud = lift_scene(observation, o.feature_stride, &o.workspace, o.semantic_tokens, o.geometric_tokens)?;
    let proprio = proprio_history_features(observation, o.proprio_history, &o.workspace)?;
    let instruction = InstructionInputs::encode(&observation.instruction, config, text)?;
    Ok(PreparedObservation {
        images,
        cameras: observation.cameras.len(),
        cloud,
        proprio,
        language: instruction.language,
        instruction: instruction.embedding,
        keyframe: observation.keyframe.min(MAX_KEYFRAME_INDEX) as u32,
    })
}

/// The instruction that stands for none (`flow.instruction_dropout`,
/// `flow.pointer_sharpening.guidance`): the empty string, which MiniLM reads as its two special
/// tokens, so the features are those of a real (if empty) sentence and no attention over the
/// instruction's tokens is left with only padding.
pub const NULL_INSTRUCTION: &str = "";

/// What the network reads of an instruction: its token features [Lt, 384], zero-padded or
/// truncated to `observation.language_tokens`, and its sentence embedding.
#[derive(Debug, Clone)]
pub struct InstructionInputs {
    pub language: Tensor,
    pub embedding: Vec<f32>,
}

impl InstructionInputs {
    pub fn encode(instruction: &str, config: &PolicyConfig, text: &mut TextEncoder) -> Result<Self> {
        let lt = config.observation.language_tokens;
        let features = text.encode(instruction)?;
        let tokens = features.tokens.to_dtype(DType::F32)?;
        let t = tokens.dim(0)?.min(lt);
        let mut language = tokens.narrow(0, 0, t)?;
        if t < lt {
            language =
                Tensor::cat(&[language, Tensor::zeros((lt - t, TEXT_HIDDEN_SIZE), DType::F32, tokens.device())?], 0)?;
        }
        Ok(Self { language, embedding: features.embedding.clone() })
    }

    /// [`NULL_INSTRUCTION`]'s.
    pub fn null(config: &PolicyConfig, text: &mut TextEncoder) -> Result<Self> {
        Self::encode(NULL_INSTRUCTION, config, text)
    }
}

impl PreparedObservation {
    /// The same observation with another instruction's features (the null instruction's, for
    /// `flow.instruction_dropout` and `flow.pointer_sharpening.guidance`).
    pub fn with_instruction(&self, instruction: &InstructionInputs) -> Self {
        Self { language: instruction.language.clone(), instruction: instruction.embedding.clone(), ..self.clone() }
    }
}

/// The observation restricted to the named cameras (`observation.cameras`), in that order.
fn select_cameras(observation: &Observation, names: &[String]) -> Result<Observation> {
    let mut cameras = Vec::with_capacity(names.len());
    for name in names {
        let view = observation.cameras.iter().find(|v| &v.name == name).ok_or_else(|| {
            let have: Vec<&str> = observation.cameras.iter().map(|v| v.name.as_str()).collect();
            PolicyError::Invalid(format!(
                "this policy sees the cameras {names:?} (observation.cameras) but the observation has {have:?}: \
                 render or collect with those cameras (--cameras)"
            ))
        })?;
        cameras.push(view.clone());
    }
    Ok(Observation {
        size: observation.size,
        cameras,
        proprio: observation.proprio,
        instruction: observation.instruction.clone(),
        keyframe: observation.keyframe,
        history: observation.history.clone(),
    })
}

fn shifted(p: [f32; 3], s: [f32; 3]) -> [f32; 3] {
    [p[0] + s[0], p[1] + s[1], p[2] + s[2]]
}

/// The prefix inputs of a batch. All samples must have the same cameras and image size.
pub fn prefix_inputs(config: &PolicyConfig, samples: &[(&PreparedObservation, Augmentation)]) -> Result<PrefixInputs> {
    let b = samples.len();
    let Some((first, _)) = samples.first() else { return Err(PolicyError::Invalid("an empty batch".into())) };
    let o = &config.observation;
    let size = o.image_size;
    let cams = first.cameras;
    let grid = size / o.feature_stride;
    let cells_per_sample = cams * grid * grid;
    let n1 = o.semantic_tokens;
    let mut images = Vec::with_capacity(b * cams * 3 * size * size);
    let mut cells = Vec::with_capacity(b * n1);
    let mut xyz = Vec::with_capacity(b * n1 * 3);
    let poses = first.proprio.len();
    let mut proprio = Vec::with_capacity(b * 10 * poses);
    let mut language = Vec::with_capacity(b);
    let mut instruction = Vec::with_capacity(b * TEXT_HIDDEN_SIZE);
    let mut keyframe = Vec::with_capacity(b);
    for (i, (s, aug)) in samples.iter().enumerate() {
        if s.cameras != cams || s.images.len() != first.images.len() {
            return Err(PolicyError::Invalid("every sample of a batch needs the same cameras and image size".into()));
        }
        if aug.brightness == 1.0 {
            images.extend_from_slice(&s.images);
        } else {
            images.extend(s.images.iter().map(|&v| (f32::from(v) * aug.brightness).round().clamp(0.0, 255.0) as u8));
        }
        for &k in &s.cloud.semantic {
            cells.push((i * cells_per_sample + s.cloud.cells[k]) as u32);
            xyz.extend(shifted(s.cloud.points_norm[k], aug.shift));
        }
        if s.proprio.len() != poses {
            return Err(PolicyError::Invalid("every sample of a batch needs the same gripper poses".into()));
        }
        for pose in &s.proprio {
            let mut p = *pose;
            for (p, shift) in p.iter_mut().zip(aug.shift) {
                *p += shift;
            }
            proprio.extend(p);
        }
        language.push(s.language.clone());
        instruction.extend_from_slice(&s.instruction);
        keyframe.push(s.keyframe);
    }
    let device = first.language.device();
    Ok(PrefixInputs {
        images: Tensor::from_vec(images, (b * cams, 3, size, size), device)?,
        language: Tensor::stack(&language, 0)?,
        semantic_cells: Tensor::from_vec(cells, b * n1, device)?,
        semantic_xyz: Tensor::from_vec(xyz, (b, n1, 3), device)?,
        proprio: Tensor::from_vec(proprio, (b, 10 * poses), device)?,
        instruction: Tensor::from_vec(instruction, (b, TEXT_HIDDEN_SIZE), device)?,
        keyframe: Tensor::from_vec(keyframe, b, device)?,
    })
}

/// The inputs of one flow step: geometric tokens around each sample's noisy action position
/// (`actions` [B, 9] rows, normalised), at flow times `t` (one per sample). `feature_sample[i]`
/// says whose image features sample i uses (its own in training; 0 when several action
/// samples share one encoded observation). `schedule` is the config's radius schedule, or
/// `RadiusSchedule::Global` for the w/o-DRS ablation.
pub fn suffix_inputs(
    config: &PolicyConfig,
    samples: &[(&PreparedObservation, Augmentation)],
    feature_sample: &[usize],
    actions: &[[f32; ACTION_DIMS]],
    t: &[f32],
    schedule: &RadiusSchedule,
) -> Result<SuffixInputs> {
    let b = actions.len();
    if samples.len() != b || feature_sample.len() != b || t.len() != b {
        return Err(PolicyError::Invalid("suffix inputs: one sample, feature sample and time per action".into()));
    }
    let o = &config.observation;
    let grid = o.image_size / o.feature_stride;
    let n2 = o.geometric_tokens;
    let mut cells = Vec::with_capacity(b * n2);
    let mut xyz = Vec::with_capacity(b * n2 * 3);
    for i in 0..b {
        let (s, aug) = samples[i];
        let cells_per_sample = s.cameras * grid * grid;
        // The selection runs in the sample's own (unshifted) frame.
        let center = [actions[i][0] - aug.shift[0], actions[i][1] - aug.shift[1], actions[i][2] - aug.shift[2]];
        let selection = select_geometric_tokens_cached(
            &s.cloud.points_norm,
            Some(&s.cloud.geometric_global),
            center,
            t[i].clamp(0.0, 1.0),
            n2,
            o.min_inside,
            schedule,
        )?;
        // scan order: farthest to nearest, the action token after the nearest (see `scene::token_order`)
        let mut indices = selection.indices;
        sort_far_to_near(&s.cloud.points_norm, center.map(|v| v.clamp(-1.0, 1.0)), &mut indices);
        for &k in &indices {
            cells.push((feature_sample[i] * cells_per_sample + s.cloud.cells[k]) as u32);
            xyz.extend(shifted(s.cloud.points_norm[k], aug.shift));
        }
    }
    let device = candle_core::Device::Cpu;
    Ok(SuffixInputs {
        geometric_cells: Tensor::from_vec(cells, b * n2, &device)?,
        geometric_xyz: Tensor::from_vec(xyz, (b, n2, 3), &device)?,
        action: Tensor::from_vec(actions.iter().flatten().copied().collect::<Vec<f32>>(), (b, 9), &device)?,
        t: Tensor::from_vec(t.to_vec(), b, &device)?,
    })
}
