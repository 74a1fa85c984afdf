//! The FlowRAM network: tokens of the observation, region-aware Mamba, flow-matching heads.
//!
//! Token sequence, in scan order (causal, so the tokens that read out the action come last and
//! see everything before them; the code release put the action first, a defect):
//!
//! ```text
//! [ language (Lt) | semantic (N1) ] [ geometric (N2) | action (1) ]
//!   prefix: depends on the observation   suffix: depends on the flow step (a_t, t)
//! ```
//!
//! - language: the instruction's MiniLM token features (384) projected to C;
//! - semantic: image-encoder features at the N1 farthest-point-sampled workspace points, plus a
//!   3D positional encoding of their (normalised) positions; in Z-order (Morton) along the scan;
//! - geometric: features at N2 points sampled around the noisy action position with the
//!   radius schedule r(t) (DRS), plus the encodings of their position and of their offset from
//!   the action position; from the farthest to the nearest to the action position (see
//!   `scene::token_order`);
//! - action: the noisy action a_t (normalised position + 6D rotation) projected to C, plus the
//!   encoding of its position.
//!
//! Every Mamba block is modulated (AdaLN) by a condition: the prefix by the proprioception's
//! embedding (plus, with `model.instruction_adaln`, an embedding of the instruction's sentence
//! vector), the suffix by that plus an embedding of the flow time t. The prefix thus
//! depends only on the observation: inference runs it once and caches the scan state, then runs
//! only the suffix at each Euler step. Heads on the last (action) token: velocity of the
//! position (3) and of the rotation (6), and the gripper-open logit.
//!
//! With `model.position_pointer` (endpoint prediction), the position is a pointer into the
//! scene: a softmax attention of the action token's output (plus the instruction) over the
//! semantic and geometric tokens' keys, whose weighted mean position the head's output offsets.
//! `flow.pointer_weight` trains that attention directly (`flow::pointer_loss`).
//!
//! With `model.instruction_pointer`, the prefix ends with one more token: an attention of the
//! instruction over the semantic tokens (their features plus the encoding of their weighted mean
//! position), and the action token gets the encoding of its offset from that position.
//! `flow.goal_weight` trains that attention to point at the episode's last keyframe.
//!
//! With `model.relational_pointer` (both pointers), the position is p + beta * (p - g) + offset,
//! p the position pointer's pointed position, g the instruction pointer's, beta a linear readout
//! of the action token (zero at initialisation).
//!
//! The instruction these read is one vector pooled from its tokens (`model.instruction_pooling`):
//! the sentence embedding, a learned softmax pooling, or that pooling with scores that also depend
//! on the condition (proprioception, keyframe index), so that a sequence's phase can choose its
//! word. With `model.language_attention_heads`, the action token's output also attends to every
//! instruction token before the heads read it (as 3D Diffuser Actor's queries attend to the
//! language), so each flow step can read the word its phase needs.
use candle_core::{Device, Tensor};
use candle_nn::{Linear, Module, VarBuilder};

use crate::policy::config::{InstructionPooling, LanguageReads, MAX_KEYFRAME_INDEX, PolicyConfig};
use crate::policy::error::{PolicyError, Result};
use crate::policy::network::encoding::{positional_encoding, time_embedding};
use crate::policy::network::image_encoder::{ImageEncoder, ImageEncoderConfig};
use crate::policy::network::mamba::{Conditioning, MambaConfig, MambaStack, StackState};
use crate::policy::network::text_encoder::TEXT_HIDDEN_SIZE;
use crate::policy::scene::observation::ACTION_DIMS;

/// Proprioception features of one gripper pose: normalised position, 6D rotation, gripper open
/// (`observation.proprio_history` poses of them feed the proprioception MLP).
pub const PROPRIO_DIMS: usize = 10;

const LANGUAGE: usize = 0;
const SEMANTIC: usize = 1;
const GEOMETRIC: usize = 2;
const ACTION: usize = 3;

/// A two-layer MLP with SiLU.
#[derive(Debug, Clone)]
struct Mlp {
    a: Linear,
    b: Linear,
}

impl Mlp {
    fn new(input: usize, hidden: usize, output: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self { a: candle_nn::linear(input, hidden, vb.pp("0"))?, b: candle_nn::linear(hidden, output, vb.pp("1"))? })
    }

    /// An MLP whose output layer is zero at initialisation (a branch that starts switched off).
    fn new_zero_output(input: usize, hidden: usize, output: usize, vb: VarBuilder) -> Result<Self> {
        let out = vb.pp("1");
        let w = out.get_with_hints((output, hidden), "weight", candle_nn::Init::Const(0.0))?;
        let b = out.get_with_hints(output, "bias", candle_nn::Init::Const(0.0))?;
        Ok(Self { a: candle_nn::linear(input, hidden, vb.pp("0"))?, b: Linear::new(w, Some(b)) })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(self.b.forward(&candle_nn::ops::silu(&self.a.forward(x)?)?)?)
    }
}

/// Hidden width of `model.relation_rotation`'s MLP of g - p.
const RELATION_ROTATION_HIDDEN: usize = 64;

/// Batched inputs of the observation side (prefix), on the CPU.
#[derive(Debug, Clone)]
pub struct PrefixInputs {
    /// u8 [B * cams, 3, H, W].
    pub images: Tensor,
    /// [B, Lt, 384] instruction token features (zero-padded).
    pub language: Tensor,
    /// u32 [B * N1]: feature pixel of each semantic token, `b * cells_per_sample + cell`.
    pub semantic_cells: Tensor,
    /// [B, N1, 3] normalised positions.
    pub semantic_xyz: Tensor,
    /// [B, 10 x observation.proprio_history] proprioception features, the current pose first.
    pub proprio: Tensor,
    /// [B, 384] the instruction's sentence embedding (for `model.instruction_adaln`).
    pub instruction: Tensor,
    /// u32 [B] keyframes executed before each observation (for `observation.keyframe_index`),
    /// at most [`MAX_KEYFRAME_INDEX`].
    pub keyframe: Tensor,
}

/// Batched inputs of one flow step (suffix).
#[derive(Debug, Clone)]
pub struct SuffixInputs {
    /// u32 [B * N2]: feature pixel of each geometric token (as `semantic_cells`).
    pub geometric_cells: Tensor,
    /// [B, N2, 3] normalised positions.
    pub geometric_xyz: Tensor,
    /// [B, 9] the noisy action a_t.
    pub action: Tensor,
    /// [B] flow time.
    pub t: Tensor,
}

/// What inference keeps of the observation between Euler steps.
#[derive(Debug, Clone)]
pub struct EncodedObservation {
    /// Image features of every feature pixel: [B * cells_per_sample, C].
    pub features: Tensor,
    /// The scan state after the prefix.
    pub state: StackState,
    /// The prefix condition [B, C].
    pub condition: Tensor,
    /// What the position pointer keeps of the prefix (`model.position_pointer`).
    pub pointer: Option<PointerMemory>,
    /// The instruction pointer's pointed position [B, 3], normalised (`model.instruction_pointer`).
    pub goal: Option<Tensor>,
    /// The instruction's keys and values for `model.language_attention_heads`.
    pub language: Option<LanguageMemory>,
}

/// The prefix's part of the position pointer (`model.position_pointer`): the semantic tokens'
/// keys and positions and the instruction's part of the query.
#[derive(Debug, Clone)]
pub struct PointerMemory {
    /// [B, N1, C]
    keys: Tensor,
    /// [B, N1, 3] normalised positions.
    xyz: Tensor,
    /// [B, C]
    query: Tensor,
}

impl PointerMemory {
    fn index_select(&self, rows: &Tensor) -> Result<Self> {
        Ok(Self {
            keys: self.keys.index_select(rows, 0)?,
            xyz: self.xyz.index_select(rows, 0)?,
            query: self.query.index_select(rows, 0)?,
        })
    }

    fn repeat(&self, n: usize) -> Result<Self> {
        Ok(Self {
            keys: self.keys.repeat((n, 1, 1))?,
            xyz: self.xyz.repeat((n, 1, 1))?,
            query: self.query.repeat((n, 1))?,
        })
    }
}

impl EncodedObservation {
    /// The encoding of one observation repeated for `n` action samples (the image features are
    /// shared: geometric tokens of every sample index the first sample's features).
    pub fn repeat(&self, n: usize) -> Result<Self> {
        if self.condition.dim(0)? != 1 {
            return Err(PolicyError::Invalid("only the encoding of a single observation can be repeated".into()));
        }
        if n == 1 {
            return Ok(self.clone());
        }
        Ok(Self {
            features: self.features.clone(),
            state: self.state.repeat(n)?,
            condition: self.condition.repeat((n, 1))?,
            pointer: self.pointer.as_ref().map(|p| p.repeat(n)).transpose()?,
            goal: self.goal.as_ref().map(|g| g.repeat((n, 1))).transpose()?,
            language: self.language.as_ref().map(|m| m.repeat(n)).transpose()?,
        })
    }
}

/// The instruction's part of `model.language_attention_heads`, once per observation: keys and
/// values [B, H, Lt, C / H] and the padding mask [B, 1, 1, Lt] (-1e9 on padding, else 0).
#[derive(Debug, Clone)]
pub struct LanguageMemory {
    keys: Tensor,
    values: Tensor,
    mask: Tensor,
}

impl LanguageMemory {
    fn index_select(&self, rows: &Tensor) -> Result<Self> {
        Ok(Self {
            keys: self.keys.index_select(rows, 0)?,
            values: self.values.index_select(rows, 0)?,
            mask: self.mask.index_select(rows, 0)?,
        })
    }

    fn repeat(&self, n: usize) -> Result<Self> {
        Ok(Self {
            keys: self.keys.repeat((n, 1, 1, 1))?,
            values: self.values.repeat((n, 1, 1, 1))?,
            mask: self.mask.repeat((n, 1, 1, 1))?,
        })
    }
}

/// `model.language_attention_heads`: multi-head attention from the action token's output to the
/// instruction's tokens (keys: the token's features plus the embedding of its place), added to
/// that output through a zero-initialised projection.
#[derive(Debug, Clone)]
struct LanguageAttention {
    heads: usize,
    query: Linear,
    key: Linear,
    value: Linear,
    /// [Lt, C]
    index: Tensor,
    out: Linear,
}

impl LanguageAttention {
    fn new(c: usize, heads: usize, tokens: usize, vb: VarBuilder) -> Result<Self> {
        let out = vb.pp("out");
        let w = out.get_with_hints((c, c), "weight", candle_nn::Init::Const(0.0))?;
        let b = out.get_with_hints(c, "bias", candle_nn::Init::Const(0.0))?;
        Ok(Self {
            heads,
            query: candle_nn::linear_no_bias(c, c, vb.pp("query"))?,
            key: candle_nn::linear_no_bias(TEXT_HIDDEN_SIZE, c, vb.pp("key"))?,
            value: candle_nn::linear(TEXT_HIDDEN_SIZE, c, vb.pp("value"))?,
            index: vb.get_with_hints((tokens, c), "index", candle_nn::Init::Randn { mean: 0.0, stdev: 0.02 })?,
            out: Linear::new(w, Some(b)),
        })
    }

    /// The instruction's tokens [B, Lt, 384] (zero rows are padding) -> keys, values, mask.
    fn memory(&self, language: &Tensor) -> Result<LanguageMemory> {
        let (b, lt, _) = language.dims3()?;
        if lt != self.index.dim(0)? {
            return Err(PolicyError::Invalid(format!(
                "the instruction has {lt} tokens but the language attention was built for {} \
                 (observation.language_tokens): prepare the observation with this model's config",
                self.index.dim(0)?
            )));
        }
        let c = self.index.dim(1)?;
        let d = c / self.heads;
        let split =
            |x: Tensor| -> Result<Tensor> { Ok(x.reshape((b, lt, self.heads, d))?.transpose(1, 2)?.contiguous()?) };
        let keys = split(self.key.forward(language)?.broadcast_add(&self.index)?)?;
        let values = split(self.value.forward(language)?)?;
        let mask = padding(language)?.affine(-1e9, 0.0)?.reshape((b, 1, 1, lt))?;
        Ok(LanguageMemory { keys, values, mask })
    }

    /// The action token's output [B, C] plus what it reads from the instruction.
    fn forward(&self, memory: &LanguageMemory, last: &Tensor) -> Result<Tensor> {
        let (b, c) = last.dims2()?;
        let d = c / self.heads;
        let q = self.query.forward(last)?.reshape((b, self.heads, 1, d))?;
        let scores = q
            .matmul(&memory.keys.transpose(2, 3)?.contiguous()?)?
            .affine(1.0 / (d as f64).sqrt(), 0.0)?
            .broadcast_add(&memory.mask)?;
        let weights = candle_nn::ops::softmax_last_dim(&scores)?;
        let read = weights.matmul(&memory.values)?.reshape((b, c))?;
        Ok(last.add(&self.out.forward(&read)?)?)
    }
}

/// What the heads read from the action token ([`FlowRam::read_instruction`]).
struct Readout {
    /// [B, C], read by the position offset, rotation, gripper and relation heads.
    token: Tensor,
    /// [B, C], read by the position pointer's query.
    query: Tensor,
}

/// Network output for one flow step.
#[derive(Debug, Clone)]
pub struct Velocity {
    /// [B, 9]
    pub velocity: Tensor,
    /// [B]
    pub open_logit: Tensor,
    /// With `model.position_pointer`: the pointer's log attention over its candidate tokens
    /// [B, N1 + N2] and their normalised positions [B, N1 + N2, 3] (for its loss).
    pub pointer: Option<(Tensor, Tensor)>,
    /// With `model.instruction_pointer`, from the training forward only: its log attention over
    /// the semantic tokens, one row per observation [B_obs, N1] (the candidates are the prefix
    /// inputs' `semantic_xyz`; for `flow.goal_weight`).
    pub goal: Option<Tensor>,
    /// With `model.relational_pointer`: beta [B, 1] and the instruction pointer's position g
    /// [B, 3] of the position p + beta (p - g) + offset (for `flow.pointer_target`).
    pub relation: Option<(Tensor, Tensor)>,
    /// With `flow.grounding_weight`, from the training forward only: the scores of the position
    /// pointer's instruction query against the semantic tokens' keys, one row per observation
    /// [B_obs, N1] (the candidates are the prefix inputs' `semantic_xyz`).
    pub grounding: Option<Tensor>,
}

/// The prefix of a batch: tokens [B, Lt + N1 (+ 1 pointer), C], the condition [B, C], the
/// position pointer's memory and the instruction pointer's log attention [B, N1] and pointed
/// position [B, 3].
struct Prefix {
    tokens: Tensor,
    condition: Tensor,
    memory: Option<PointerMemory>,
    goal: Option<(Tensor, Tensor)>,
    language: Option<LanguageMemory>,
}

/// The instruction-pointer token (`model.instruction_pointer`): one attention of the instruction
/// over the semantic tokens; the token is the attended features plus the encoding of the
/// attended position.
#[derive(Debug, Clone)]
struct InstructionPointer {
    query: Linear,
    key: Linear,
    out: Linear,
}

impl InstructionPointer {
    fn new(c: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            query: candle_nn::linear(TEXT_HIDDEN_SIZE, c, vb.pp("query"))?,
            key: candle_nn::linear_no_bias(c, c, vb.pp("key"))?,
            out: candle_nn::linear(c, c, vb.pp("out"))?,
        })
    }

    /// instruction [B, 384], tokens [B, N, C] at normalised positions xyz [B, N, 3] -> the token
    /// [B, 1, C], the log attention [B, N] and the pointed position [B, 3].
    fn forward(&self, instruction: &Tensor, tokens: &Tensor, xyz: &Tensor) -> Result<(Tensor, Tensor, Tensor)> {
        let q = self.query.forward(instruction)?.unsqueeze(1)?;
        let scores = attention_scores(&q, &self.key.forward(tokens)?)?;
        let log_weights = candle_nn::ops::log_softmax(&scores, 2)?;
        let weights = log_weights.exp()?;
        let pointed = weights.matmul(xyz)?;
        let token = self.out.forward(&weights.matmul(tokens)?)?.add(&positional_encoding(&pointed, tokens.dim(2)?)?)?;
        Ok((token, log_weights.squeeze(1)?, pointed.squeeze(1)?))
    }
}

/// The condition's part of the instruction pooling's scores (`model.instruction_pooling =
/// "conditioned"`): a query from the AdaLN condition against keys of each token's features plus
/// a learned embedding of its index in the instruction, so the pooling can follow a sequence's
/// phase. The query starts at zero: a new model pools as `"attention"` does.
#[derive(Debug, Clone)]
struct PoolingQuery {
    query: Linear,
    key: Linear,
    /// [Lt, C]
    index: Tensor,
}

impl PoolingQuery {
    fn new(c: usize, tokens: usize, vb: VarBuilder) -> Result<Self> {
        let w = vb.pp("query").get_with_hints((c, c), "weight", candle_nn::Init::Const(0.0))?;
        Ok(Self {
            query: Linear::new(w, None),
            key: candle_nn::linear_no_bias(TEXT_HIDDEN_SIZE, c, vb.pp("key"))?,
            index: vb.get_with_hints((tokens, c), "index", candle_nn::Init::Randn { mean: 0.0, stdev: 0.02 })?,
        })
    }

    /// The instruction's tokens [B, Lt, 384] and the condition [B, C] -> logits [B, Lt, 1].
    fn logits(&self, language: &Tensor, condition: &Tensor) -> Result<Tensor> {
        let (_, lt, _) = language.dims3()?;
        if lt != self.index.dim(0)? {
            return Err(PolicyError::Invalid(format!(
                "the instruction has {lt} tokens but the conditioned pooling was built for {} \
                 (observation.language_tokens): prepare the observation with this model's config",
                self.index.dim(0)?
            )));
        }
        let keys = self.key.forward(language)?.broadcast_add(&self.index)?; // [B, Lt, C]
        let q = self.query.forward(condition)?.unsqueeze(2)?; // [B, C, 1]
        let scale = 1.0 / (keys.dim(2)? as f64).sqrt();
        Ok(keys.matmul(&q)?.affine(scale, 0.0)?)
    }
}

/// What the position pointer's posterior needs (`flow.pointer_sharpening.posterior`): the noisy
/// position a_t [B, 3], the position head's offset [B, 3], and the step's flow time and
/// candidate width.
#[derive(Debug, Clone, Copy)]
struct Posterior<'a> {
    position: &'a Tensor,
    offset: &'a Tensor,
    at: PosteriorAt,
}

/// The flow time and the candidates' width per axis (normalised units) of a posterior step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PosteriorAt {
    pub t: f32,
    pub width: [f32; 3],
}

/// The position pointer (`model.position_pointer`): the predicted position as an attention over
/// the scene tokens' positions.
#[derive(Debug, Clone)]
struct PositionPointer {
    query: Linear,
    instruction: Linear,
    key: Linear,
}

impl PositionPointer {
    fn new(c: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            query: candle_nn::linear_no_bias(c, c, vb.pp("query"))?,
            instruction: candle_nn::linear(TEXT_HIDDEN_SIZE, c, vb.pp("instruction"))?,
            key: candle_nn::linear_no_bias(c, c, vb.pp("key"))?,
        })
    }

    /// semantic tokens [B, N1, C] at positions [B, N1, 3], the pooled instruction [B, 384].
    fn memory(&self, semantic: &Tensor, xyz: &Tensor, instruction: &Tensor) -> Result<PointerMemory> {
        Ok(PointerMemory {
            keys: self.key.forward(semantic)?,
            xyz: xyz.clone(),
            query: self.instruction.forward(instruction)?,
        })
    }

    /// The pointed position [B, 3]: the softmax over the semantic and geometric tokens (keys
    /// against the action token's output `last` [B, C] plus the instruction) of their positions;
    /// with the log attention [B, N] and the candidates' positions [B, N, 3]. `temperature`
    /// divides the scores (1: as trained; below 1 sharpens, `flow.pointer_sharpening`).
    /// `guide` = (the null instruction's scores [B, 1, N] at the same step, w): the scores are
    /// guided to s_null + w (s - s_null) before the posterior's likelihood
    /// (`flow.pointer_sharpening.guidance`).
    #[allow(clippy::too_many_arguments)]
    fn point(
        &self,
        memory: &PointerMemory,
        geometric: &Tensor,
        geometric_xyz: &Tensor,
        last: &Tensor,
        temperature: f64,
        posterior: Option<Posterior>,
        guide: Option<(&Tensor, f64)>,
    ) -> Result<(Tensor, Tensor, Tensor)> {
        let (mut scores, xyz) = self.scores(memory, geometric, geometric_xyz, last, temperature)?;
        if let Some((null, w)) = guide {
            scores = guided_scores(&scores, null, w)?;
        }
        if let Some(Posterior { position, offset, at: PosteriorAt { t, width } }) = posterior {
            // log N(a_t; t (x_i + c), diag((1 - t)^2 + t^2 w^2)) up to a constant, per candidate i
            let remaining = f64::from(1.0 - t).max(1e-3);
            let centres = xyz.broadcast_add(&offset.unsqueeze(1)?)?.affine(f64::from(t), 0.0)?;
            let squared = centres.broadcast_sub(&position.unsqueeze(1)?)?.sqr()?;
            // points (w = 0) keep session 30's arithmetic, so the shipped samples stay bit for bit
            let log_likelihood = if width == [0.0; 3] {
                squared.sum(2)?.affine(-0.5 / (remaining * remaining), 0.0)?
            } else {
                let precision: Vec<f32> = width
                    .iter()
                    .map(|&w| {
                        let spread = f64::from(t) * f64::from(w);
                        (-0.5 / (remaining * remaining + spread * spread)) as f32
                    })
                    .collect();
                let precision = Tensor::from_vec(precision, 3, squared.device())?;
                squared.broadcast_mul(&precision)?.sum(2)?
            };
            scores = scores.add(&log_likelihood.unsqueeze(1)?)?;
        }
        let log_weights = candle_nn::ops::log_softmax(&scores, 2)?;
        let pointed = log_weights.exp()?.matmul(&xyz)?.squeeze(1)?;
        Ok((pointed, log_weights.squeeze(1)?, xyz))
    }

    /// The scores [B, 1, N] of the semantic then geometric tokens (divided by `temperature`)
    /// and the candidates' positions [B, N, 3].
    fn scores(
        &self,
        memory: &PointerMemory,
        geometric: &Tensor,
        geometric_xyz: &Tensor,
        last: &Tensor,
        temperature: f64,
    ) -> Result<(Tensor, Tensor)> {
        let keys = Tensor::cat(&[&memory.keys, &self.key.forward(geometric)?], 1)?;
        let xyz = Tensor::cat(&[&memory.xyz, geometric_xyz], 1)?;
        let q = self.query.forward(last)?.add(&memory.query)?.unsqueeze(1)?;
        let mut scores = attention_scores(&q, &keys)?;
        if temperature != 1.0 {
            scores = scores.affine(1.0 / temperature, 0.0)?;
        }
        Ok((scores, xyz))
    }
}

/// The FlowRAM network. Weights live in the `VarBuilder`'s storage (a `VarMap` for training).
#[derive(Debug, Clone)]
pub struct FlowRam {
    config: PolicyConfig,
    image_encoder: ImageEncoder,
    language_proj: Linear,
    action_in: Linear,
    /// [4, C]: language, semantic, geometric, action.
    token_types: Tensor,
    proprio_mlp: Mlp,
    /// The instruction's part of the AdaLN condition (`model.instruction_adaln`).
    instruction_mlp: Option<Mlp>,
    /// [MAX_KEYFRAME_INDEX + 1, C]: the keyframe index's part of the AdaLN condition
    /// (`observation.keyframe_index`), zero-initialised.
    keyframe_embedding: Option<Tensor>,
    /// Scores of the instruction's tokens for `model.instruction_pooling = "attention"` or
    /// `"conditioned"`.
    instruction_scores: Option<Linear>,
    /// The condition's part of those scores (`model.instruction_pooling = "conditioned"`).
    pooling_query: Option<PoolingQuery>,
    /// `model.instruction_pointer`.
    pointer: Option<InstructionPointer>,
    /// `model.position_pointer`.
    position_pointer: Option<PositionPointer>,
    /// `model.relational_pointer`: beta of the position p + beta * (p - g) + offset.
    relation: Option<Linear>,
    /// `model.relation_rotation`: the rotation's part read from g - p.
    relation_rotation: Option<Mlp>,
    /// `model.point_colour`: raw mean colour of a feature pixel -> C.
    colour_mlp: Option<Mlp>,
    /// `model.language_attention_heads`.
    language_attention: Option<LanguageAttention>,
    time_mlp: Mlp,
    mamba: MambaStack,
    position_head: Mlp,
    rotation_head: Mlp,
    open_head: Mlp,
}

impl FlowRam {
    pub fn new(config: &PolicyConfig, vb: VarBuilder) -> Result<Self> {
        config.validate()?;
        let c = config.model.channels;
        let o = &config.observation;
        // Whether anything reads the pooled instruction.
        let pools = config.model.instruction_adaln || config.model.instruction_pointer || config.model.position_pointer;
        let encoder_config = ImageEncoderConfig {
            image_size: o.image_size,
            patch_size: o.feature_stride,
            out_channels: c,
            ..ImageEncoderConfig::default()
        };
        let mamba_config = MambaConfig {
            d_model: c,
            d_state: config.model.d_state,
            d_conv: config.model.d_conv,
            expand: config.model.expand,
            n_layers: config.model.layers,
            ..MambaConfig::default()
        };
        Ok(Self {
            config: config.clone(),
            image_encoder: ImageEncoder::new(encoder_config, vb.pp("image_encoder"))?,
            language_proj: candle_nn::linear(TEXT_HIDDEN_SIZE, c, vb.pp("language_proj"))?,
            action_in: candle_nn::linear(ACTION_DIMS, c, vb.pp("action_in"))?,
            token_types: vb.get_with_hints((4, c), "token_types", candle_nn::Init::Randn { mean: 0.0, stdev: 0.02 })?,
            proprio_mlp: Mlp::new(PROPRIO_DIMS * config.observation.proprio_history, c, c, vb.pp("proprio_mlp"))?,
            keyframe_embedding: if config.observation.keyframe_index {
                Some(vb.get_with_hints(
                    (MAX_KEYFRAME_INDEX + 1, c),
                    "keyframe_embedding",
                    candle_nn::Init::Const(0.0),
                )?)
            } else {
                None
            },
            instruction_mlp: if config.model.instruction_adaln {
                Some(Mlp::new(TEXT_HIDDEN_SIZE, c, c, vb.pp("instruction_mlp"))?)
            } else {
                None
            },
            instruction_scores: if pools && config.model.instruction_pooling != InstructionPooling::Sentence {
                Some(candle_nn::linear(TEXT_HIDDEN_SIZE, 1, vb.pp("instruction_scores"))?)
            } else {
                None
            },
            pooling_query: if pools && config.model.instruction_pooling == InstructionPooling::Conditioned {
                Some(PoolingQuery::new(c, o.language_tokens, vb.pp("pooling_query"))?)
            } else {
                None
            },
            pointer: if config.model.instruction_pointer {
                Some(InstructionPointer::new(c, vb.pp("instruction_pointer"))?)
            } else {
                None
            },
            position_pointer: if config.model.position_pointer {
                Some(PositionPointer::new(c, vb.pp("position_pointer"))?)
            } else {
                None
            },
            relation: if config.model.relational_pointer {
                // Zero at initialisation: training starts from the single pointer.
                let vb = vb.pp("relation");
                let w = vb.get_with_hints((1, c), "weight", candle_nn::Init::Const(0.0))?;
                let b = vb.get_with_hints(1, "bias", candle_nn::Init::Const(0.0))?;
                Some(Linear::new(w, Some(b)))
            } else {
                None
            },
            relation_rotation: if config.model.relation_rotation {
                let input = if config.model.relation_rotation_reads_token { 3 + c } else { 3 };
                Some(Mlp::new_zero_output(input, RELATION_ROTATION_HIDDEN, 6, vb.pp("relation_rotation"))?)
            } else {
                None
            },
            colour_mlp: if config.model.point_colour { Some(Mlp::new(3, c, c, vb.pp("colour_mlp"))?) } else { None },
            language_attention: match config.model.language_attention_heads {
                0 => None,
                heads => Some(LanguageAttention::new(c, heads, o.language_tokens, vb.pp("language_attention"))?),
            },
            time_mlp: Mlp::new(c, c, c, vb.pp("time_mlp"))?,
            mamba: MambaStack::new(&mamba_config, vb.pp("mamba"))?,
            position_head: Mlp::new(c, c, 3, vb.pp("position_head"))?,
            rotation_head: Mlp::new(c, c, 6, vb.pp("rotation_head"))?,
            open_head: Mlp::new(c, c, 1, vb.pp("open_head"))?,
        })
    }

    pub fn config(&self) -> &PolicyConfig {
        &self.config
    }

    /// Feature pixels per sample: cameras x (size / stride)^2.
    pub fn cells_per_camera(&self) -> usize {
        let g = self.config.observation.image_size / self.config.observation.feature_stride;
        g * g
    }

    /// Floating-point operations of one keyframe prediction with the inference path (encode
    /// once, then `steps` Euler steps from the cached prefix), for `cameras` cameras: the image
    /// encoder, the token projections, the Mamba layers (prefix state, suffix with only the
    /// action token's output) and the heads. Positional encodings, norms, token selection and
    /// the text encoder (cached per instruction) are left out. What `flowram bench policy`
    /// divides by the latency to give the achieved GFLOP/s.
    pub fn keyframe_flops(&self, cameras: usize, steps: usize) -> f64 {
        let (c, o) = (self.config.model.channels, &self.config.observation);
        let mamba = self.mamba.config();
        let layers = mamba.n_layers as f64;
        let encoder = ImageEncoderConfig {
            image_size: o.image_size,
            patch_size: o.feature_stride,
            out_channels: c,
            ..ImageEncoderConfig::default()
        }
        .flops(cameras);
        let scan = |tokens: usize, last_output: bool| -> f64 {
            let t = tokens as f64;
            (layers - 1.0) * t * mamba.layer_flops_per_token(true)
                + t * mamba.layer_flops_per_token(false)
                + if last_output { mamba.layer_flops_per_token(true) - mamba.layer_flops_per_token(false) } else { 0.0 }
        };
        let pointer = usize::from(self.pointer.is_some());
        let cells = (cameras * (o.image_size / o.feature_stride).pow(2)) as f64;
        let colour = if self.colour_mlp.is_some() { cells * 2.0 * (3 * c + c * c) as f64 } else { 0.0 };
        let prefix = colour
            + 2.0 * (o.language_tokens * TEXT_HIDDEN_SIZE * c) as f64
            + 2.0 * ((o.semantic_tokens + 2) * c * c) as f64 * pointer as f64
            + scan(o.language_tokens + o.semantic_tokens + pointer, false);
        let mut heads = 2.0 * (3.0 * (c * c) as f64 + (c * (3 + 6 + 1)) as f64);
        if self.relation.is_some() {
            heads += 2.0 * c as f64 + 9.0;
        }
        if self.relation_rotation.is_some() {
            let input = if self.config.model.relation_rotation_reads_token { 3 + c } else { 3 };
            heads += 2.0 * ((input + 6) * RELATION_ROTATION_HIDDEN) as f64;
        }
        let mut once_per_observation = 0.0;
        if self.pooling_query.is_some() {
            // The conditioned pooling's keys, query and scores, once per observation.
            once_per_observation +=
                2.0 * (o.language_tokens * TEXT_HIDDEN_SIZE * c + c * c + o.language_tokens * c) as f64;
        }
        if self.language_attention.is_some() {
            // The instruction's keys and values once; per step the query, the scores, the
            // weighted values and the output projection.
            once_per_observation += 4.0 * (o.language_tokens * TEXT_HIDDEN_SIZE * c) as f64;
            heads += 4.0 * (c * c) as f64 + 4.0 * (o.language_tokens * c) as f64;
        }
        if self.position_pointer.is_some() {
            // Keys of the semantic tokens and the instruction's query once; per step the geometric
            // tokens' keys, the query, the scores and the weighted mean of the positions.
            once_per_observation += 2.0 * (o.semantic_tokens * c * c + TEXT_HIDDEN_SIZE * c) as f64;
            let n = (o.semantic_tokens + o.geometric_tokens) as f64;
            heads += 2.0 * ((o.geometric_tokens + 1) * c * c) as f64 + 2.0 * n * (c + 3) as f64;
        }
        let step = 2.0 * (ACTION_DIMS * c) as f64 + 2.0 * (c * c) as f64 + scan(o.geometric_tokens + 1, true) + heads;
        encoder + prefix + once_per_observation + steps as f64 * step
    }

    /// Image features of every feature pixel, [B * cams * cells, C] (row order: sample, camera,
    /// row, column); with `model.point_colour`, plus the colour MLP of the pixel's mean raw colour.
    pub fn image_features(&self, images: &Tensor) -> Result<Tensor> {
        let f = self.image_encoder.forward_channels_last(images)?;
        let (n, h, w, c) = f.dims4()?;
        let f = f.reshape((n * h * w, c))?;
        match &self.colour_mlp {
            None => Ok(f),
            Some(mlp) => {
                // [N, 3, H, W] u8 -> mean over each stride x stride cell, in [-1, 1].
                let stride = self.config.observation.feature_stride;
                let rgb = images.to_dtype(candle_core::DType::F32)?.affine(1.0 / 127.5, -1.0)?.avg_pool2d(stride)?;
                let cells = rgb.permute((0, 2, 3, 1))?.contiguous()?.reshape((n * h * w, 3))?;
                Ok(f.add(&mlp.forward(&cells)?)?)
            }
        }
    }

    fn type_embedding(&self, which: usize) -> Result<Tensor> {
        Ok(self.token_types.narrow(0, which, 1)?)
    }

    fn gather(features: &Tensor, cells: &Tensor, batch: usize) -> Result<Tensor> {
        let g = features.index_select(cells, 0)?;
        let (n, c) = g.dims2()?;
        Ok(g.reshape((batch, n / batch, c))?)
    }

    /// The prefix of a batch (see [`Prefix`]).
    fn prefix_tokens(&self, features: &Tensor, inputs: &PrefixInputs) -> Result<Prefix> {
        let c = self.config.model.channels;
        let b = inputs.proprio.dim(0)?;
        let language = self.language_proj.forward(&inputs.language)?.broadcast_add(&self.type_embedding(LANGUAGE)?)?;
        let semantic = Self::gather(features, &inputs.semantic_cells, b)?
            .add(&positional_encoding(&inputs.semantic_xyz, c)?)?
            .broadcast_add(&self.type_embedding(SEMANTIC)?)?;
        let mut condition = self.proprio_mlp.forward(&inputs.proprio)?;
        if let Some(table) = &self.keyframe_embedding {
            condition = condition.add(&table.index_select(&inputs.keyframe, 0)?)?;
        }
        let instruction = match &self.instruction_scores {
            None => inputs.instruction.clone(),
            Some(scores) => {
                let conditioned =
                    self.pooling_query.as_ref().map(|q| q.logits(&inputs.language, &condition)).transpose()?;
                attention_pool(&inputs.language, scores, conditioned.as_ref())?
            }
        };
        let memory = match &self.position_pointer {
            Some(p) => Some(p.memory(&semantic, &inputs.semantic_xyz, &instruction)?),
            None => None,
        };
        let (tokens, goal) = match &self.pointer {
            Some(pointer) => {
                let (token, log_weights, pointed) = pointer.forward(&instruction, &semantic, &inputs.semantic_xyz)?;
                (Tensor::cat(&[language, semantic, token], 1)?, Some((log_weights, pointed)))
            }
            None => (Tensor::cat(&[language, semantic], 1)?, None),
        };
        if let Some(mlp) = &self.instruction_mlp {
            condition = condition.add(&mlp.forward(&instruction)?)?;
        }
        let language = self.language_attention.as_ref().map(|a| a.memory(&inputs.language)).transpose()?;
        Ok(Prefix { tokens, condition, memory, goal, language })
    }

    /// The prefix's tokens before the scan, [B, Lt + N1 (+ 1 pointer), C] (for tests and probes).
    pub fn prefix_token_features(&self, inputs: &PrefixInputs) -> Result<Tensor> {
        let features = self.image_features(&inputs.images)?;
        Ok(self.prefix_tokens(&features, inputs)?.tokens)
    }

    /// Suffix tokens [B, N2 + 1, C] and the suffix condition [B, C]; `goal` [B, 3] is the
    /// instruction pointer's pointed position (`model.instruction_pointer`).
    fn suffix_tokens(
        &self,
        features: &Tensor,
        prefix_condition: &Tensor,
        goal: Option<&Tensor>,
        inputs: &SuffixInputs,
    ) -> Result<(Tensor, Tensor)> {
        let c = self.config.model.channels;
        let b = inputs.action.dim(0)?;
        let position = inputs.action.narrow(1, 0, 3)?;
        let offset = inputs.geometric_xyz.broadcast_sub(&position.unsqueeze(1)?)?;
        let geometric = Self::gather(features, &inputs.geometric_cells, b)?
            .add(&positional_encoding(&inputs.geometric_xyz, c)?)?
            .add(&positional_encoding(&offset, c)?)?
            .broadcast_add(&self.type_embedding(GEOMETRIC)?)?;
        let mut action = self
            .action_in
            .forward(&inputs.action)?
            .add(&positional_encoding(&position.clamp(-1.5f32, 1.5f32)?, c)?)?
            .broadcast_add(&self.type_embedding(ACTION)?)?;
        if let Some(goal) = goal {
            action = action.add(&positional_encoding(&goal.sub(&position)?.clamp(-3f32, 3f32)?, c)?)?;
        }
        let action = action.unsqueeze(1)?;
        let tokens = Tensor::cat(&[geometric, action], 1)?;
        let condition = prefix_condition.add(&self.time_mlp.forward(&time_embedding(&inputs.t, c)?)?)?;
        Ok((tokens, condition))
    }

    /// What the heads read: the action token's output `last` [B, C] and, for the position
    /// pointer's query, that output plus what it reads from the instruction's tokens
    /// (`language`, once per observation) with `model.language_attention_heads`; with
    /// `model.language_attention_reads = "token"` every head reads the latter.
    fn read_instruction(&self, last: &Tensor, language: Option<&LanguageMemory>) -> Result<Readout> {
        match (&self.language_attention, language) {
            (None, _) => Ok(Readout { token: last.clone(), query: last.clone() }),
            (Some(a), Some(memory)) => {
                let read = a.forward(memory, last)?;
                Ok(match self.config.model.language_attention_reads {
                    LanguageReads::Token => Readout { token: read.clone(), query: read },
                    LanguageReads::Pointer => Readout { token: last.clone(), query: read },
                })
            }
            (Some(_), None) => Err(PolicyError::Invalid(
                "the model attends to the instruction (model.language_attention_heads) but the encoded \
                 observation carries no instruction memory: encode it with this model"
                    .into(),
            )),
        }
    }

    /// The heads on the action token's output (`readout`, [B, C] each); with the position
    /// pointer, `pointer` holds its memory and the suffix's geometric tokens [B, N2, C] and
    /// positions [B, N2, 3];
    /// `goal` [B, 3] is the instruction pointer's pointed position (`model.relational_pointer`);
    /// `pointer_temperature` divides the position pointer's scores (1: as trained).
    fn heads(
        &self,
        readout: &Readout,
        pointer: Option<(&PointerMemory, &Tensor, &Tensor)>,
        goal: Option<&Tensor>,
        pointer_temperature: f64,
        posterior: Option<(&Tensor, PosteriorAt)>,
        guide: Option<(&Tensor, f64)>,
    ) -> Result<Velocity> {
        let last = &readout.token;
        let mut position = self.position_head.forward(last)?;
        let mut attention = None;
        let mut relation_used = None;
        let mut rotation = self.rotation_head.forward(last)?;
        match (&self.position_pointer, pointer) {
            (Some(p), Some((memory, geometric, xyz))) => {
                let posterior = posterior.map(|(a_t, at)| Posterior { position: a_t, offset: &position, at });
                let (pointed, log_weights, candidates) =
                    p.point(memory, geometric, xyz, &readout.query, pointer_temperature, posterior, guide)?;
                position = position.add(&pointed)?;
                if let Some(relation) = &self.relation {
                    let goal = goal.ok_or_else(|| {
                        PolicyError::Invalid(
                            "the model relates two pointers (model.relational_pointer) but no instruction-pointer \
                             position was given: encode the observation with this model"
                                .into(),
                        )
                    })?;
                    let beta = relation.forward(last)?; // [B, 1]
                    position = position.add(&pointed.sub(goal)?.broadcast_mul(&beta)?)?;
                    if let Some(r) = &self.relation_rotation {
                        let relation = goal.sub(&pointed)?;
                        let input = if self.config.model.relation_rotation_reads_token {
                            Tensor::cat(&[&relation, last], 1)?
                        } else {
                            relation
                        };
                        rotation = rotation.add(&r.forward(&input)?)?;
                    }
                    relation_used = Some((beta, goal.clone()));
                }
                attention = Some((log_weights, candidates));
            }
            (None, _) => {}
            (Some(_), None) => {
                return Err(PolicyError::Invalid(
                    "the model has a position pointer (model.position_pointer) but the encoded observation \
                     carries no pointer memory: encode it with this model"
                        .into(),
                ));
            }
        }
        let velocity = Tensor::cat(&[position, rotation], 1)?;
        let open_logit = self.open_head.forward(last)?.squeeze(1)?;
        Ok(Velocity { velocity, open_logit, pointer: attention, goal: None, relation: relation_used, grounding: None })
    }

    /// Training forward, differentiable: the whole sequence in one pass. The suffix may hold K
    /// flow samples per observation (`train.flow_samples`; sample `i` belongs to observation
    /// `i / K`, and its geometric cells index that observation's features): the image features
    /// are computed once per observation and the prefix tokens repeated.
    pub fn forward(&self, prefix: &PrefixInputs, suffix: &SuffixInputs) -> Result<Velocity> {
        let features = self.image_features(&prefix.images)?;
        let Prefix { tokens: mut p_tokens, condition: mut p_cond, mut memory, goal, mut language } =
            self.prefix_tokens(&features, prefix)?;
        let (goal_attention, mut goal) = goal.unzip();
        let grounding = match &memory {
            Some(m) if self.config.flow.grounding_weight > 0.0 => {
                Some(attention_scores(&m.query.unsqueeze(1)?, &m.keys)?.squeeze(1)?)
            }
            _ => None,
        };
        let (observations, samples) = (p_cond.dim(0)?, suffix.action.dim(0)?);
        if samples != observations {
            if observations == 0 || !samples.is_multiple_of(observations) {
                return Err(PolicyError::Invalid(format!(
                    "{samples} flow samples cannot be split evenly over {observations} observations"
                )));
            }
            let k = samples / observations;
            let owner: Vec<u32> = (0..samples as u32).map(|i| i / k as u32).collect();
            let owner = Tensor::from_vec(owner, samples, p_cond.device())?;
            p_tokens = p_tokens.index_select(&owner, 0)?;
            p_cond = p_cond.index_select(&owner, 0)?;
            memory = memory.map(|m| m.index_select(&owner)).transpose()?;
            goal = goal.map(|g| g.index_select(&owner, 0)).transpose()?;
            language = language.map(|m| m.index_select(&owner)).transpose()?;
        }
        let (s_tokens, s_cond) = self.suffix_tokens(&features, &p_cond, goal.as_ref(), suffix)?;
        let (lp, ls) = (p_tokens.dim(1)?, s_tokens.dim(1)?);
        let geometric = s_tokens.narrow(1, 0, ls - 1)?;
        let x = Tensor::cat(&[&p_tokens, &s_tokens], 1)?;
        let h = self.mamba.forward(&x, &Conditioning::prefix_suffix(lp, p_cond, ls, s_cond))?;
        let pointer = memory.as_ref().map(|m| (m, &geometric, &suffix.geometric_xyz));
        let readout = self.read_instruction(&h.narrow(1, lp + ls - 1, 1)?.squeeze(1)?, language.as_ref())?;
        let mut velocity = self.heads(&readout, pointer, goal.as_ref(), 1.0, None, None)?;
        velocity.goal = goal_attention;
        velocity.grounding = grounding;
        Ok(velocity)
    }

    /// Inference: encodes the observation once (image features, prefix scan state).
    pub fn encode(&self, prefix: &PrefixInputs) -> Result<EncodedObservation> {
        self.encode_with_features(self.image_features(&prefix.images)?.detach(), prefix)
    }

    /// [`Self::encode`] with the image features [B * cells_per_sample, C] of `prefix.images`
    /// already computed (the null instruction's encoding of an observation reuses the
    /// instructed one's: the image encoder does not read the instruction).
    pub fn encode_with_features(&self, features: Tensor, prefix: &PrefixInputs) -> Result<EncodedObservation> {
        let Prefix { tokens, condition, memory, goal, language } = self.prefix_tokens(&features, prefix)?;
        let state = self.mamba.forward_state(&tokens, &Conditioning::Shared(condition.clone()), None)?;
        let pointer =
            memory.map(|m| PointerMemory { keys: m.keys.detach(), xyz: m.xyz.detach(), query: m.query.detach() });
        let goal = goal.map(|(_, pointed)| pointed.detach());
        let language = language.map(|m| LanguageMemory {
            keys: m.keys.detach(),
            values: m.values.detach(),
            mask: m.mask.detach(),
        });
        Ok(EncodedObservation { features, state, condition, pointer, goal, language })
    }

    /// Inference: one flow step from the cached prefix.
    pub fn step(&self, encoded: &EncodedObservation, suffix: &SuffixInputs) -> Result<Velocity> {
        self.step_sharpened(encoded, suffix, 1.0, None)
    }

    /// [`Self::step`] with the position pointer's scores divided by `pointer_temperature` and,
    /// with `posterior_at` the flow time (and candidate width), the pointer made the posterior
    /// given the noisy position (`flow.pointer_sharpening`; no effect without
    /// `model.position_pointer`).
    pub fn step_sharpened(
        &self,
        encoded: &EncodedObservation,
        suffix: &SuffixInputs,
        pointer_temperature: f64,
        posterior_at: Option<PosteriorAt>,
    ) -> Result<Velocity> {
        self.step_guided(encoded, suffix, pointer_temperature, posterior_at, None)
    }

    /// [`Self::step_sharpened`] with, given `guidance` = (the same observation encoded with the
    /// null instruction, w), the position pointer's scores guided by the instruction
    /// (`flow.pointer_sharpening.guidance`): the null's step runs on the same suffix and its
    /// scores s_null make s_null + w (s - s_null). Everything else is the instructed step's.
    pub fn step_guided(
        &self,
        encoded: &EncodedObservation,
        suffix: &SuffixInputs,
        pointer_temperature: f64,
        posterior_at: Option<PosteriorAt>,
        guidance: Option<(&EncodedObservation, f64)>,
    ) -> Result<Velocity> {
        let (readout, geometric) = self.step_readout(encoded, suffix)?;
        let pointer = encoded.pointer.as_ref().map(|m| (m, &geometric, &suffix.geometric_xyz));
        let null_scores = match (guidance, &self.position_pointer) {
            (Some((null, w)), Some(p)) if w != 1.0 => {
                let memory = null.pointer.as_ref().ok_or_else(|| {
                    PolicyError::Invalid(
                        "the null instruction's encoding carries no pointer memory: encode it with this model".into(),
                    )
                })?;
                let (readout, geometric) = self.step_readout(null, suffix)?;
                let (scores, _) =
                    p.scores(memory, &geometric, &suffix.geometric_xyz, &readout.query, pointer_temperature)?;
                Some((scores, w))
            }
            _ => None,
        };
        // the noisy position a_t, only where the posterior reads it
        let position = posterior_at.map(|_| suffix.action.narrow(1, 0, 3)).transpose()?;
        self.heads(
            &readout,
            pointer,
            encoded.goal.as_ref(),
            pointer_temperature,
            position.as_ref().zip(posterior_at),
            null_scores.as_ref().map(|(s, w)| (s, *w)),
        )
    }

    /// One step's scan from the cached prefix: what the heads read, and the suffix's geometric
    /// tokens [B, N2, C] (the pointer's keys read them).
    fn step_readout(&self, encoded: &EncodedObservation, suffix: &SuffixInputs) -> Result<(Readout, Tensor)> {
        let (tokens, condition) =
            self.suffix_tokens(&encoded.features, &encoded.condition, encoded.goal.as_ref(), suffix)?;
        let last = self.mamba.forward_last_token(&tokens, &Conditioning::Shared(condition), Some(&encoded.state))?;
        let readout = self.read_instruction(&last, encoded.language.as_ref())?;
        let geometric = tokens.narrow(1, 0, tokens.dim(1)? - 1)?;
        Ok((readout, geometric))
    }
}

/// Classifier-free guidance of scores by the instruction: s_null + w (s - s_null).
pub fn guided_scores(scores: &Tensor, null: &Tensor, w: f64) -> Result<Tensor> {
    Ok(null.add(&scores.sub(null)?.affine(w, 0.0)?)?)
}

/// Scaled dot-product scores of one query per sequence [B, 1, C] against keys [B, N, C]: [B, 1, N].
fn attention_scores(query: &Tensor, keys: &Tensor) -> Result<Tensor> {
    let c = keys.dim(2)?;
    Ok(query.matmul(&keys.transpose(1, 2)?.contiguous()?)?.affine(1.0 / (c as f64).sqrt(), 0.0)?)
}

/// 1 where a token [B, L, D] is padding (all zeros), else 0: [B, L, 1].
fn padding(tokens: &Tensor) -> Result<Tensor> {
    Ok(tokens.abs()?.sum_keepdim(2)?.eq(0f32)?.to_dtype(tokens.dtype())?)
}

/// Softmax pooling of token features [B, L, D] by learned scores, over the non-padding tokens
/// (padding is all zeros), plus `conditioned` [B, L, 1] when given ([`PoolingQuery`]): [B, D].
fn attention_pool(tokens: &Tensor, scores: &Linear, conditioned: Option<&Tensor>) -> Result<Tensor> {
    let padding = padding(tokens)?;
    let mut logits = scores.forward(tokens)?;
    if let Some(extra) = conditioned {
        logits = logits.add(extra)?;
    }
    let logits = logits.sub(&padding.affine(1e9, 0.0)?)?;
    let weights = candle_nn::ops::softmax(&logits, 1)?;
    Ok(tokens.broadcast_mul(&weights)?.sum(1)?)
}

/// The CPU device the policy runs on.
pub fn device() -> Device {
    Device::Cpu
}
