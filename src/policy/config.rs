//! The policy's configuration: observation, network, flow and training hyper-parameters, read
//! from TOML (`models/policy/*.toml`) and stored as JSON in every checkpoint. Every value is
//! validated and a wrong one is named.
use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::policy::error::{PolicyError, Result};
use crate::policy::flow::{FlowTimeSampling, Prediction};
use crate::policy::scene::radius_schedule::RadiusSchedule;
use crate::policy::scene::workspace::WorkspaceBounds;

/// Everything that defines a FlowRAM model and how it is trained.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PolicyConfig {
    pub observation: ObservationConfig,
    pub model: ModelConfig,
    pub radius_schedule: RadiusSchedule,
    pub flow: FlowConfig,
    pub train: TrainConfig,
}

/// How an observation becomes tokens.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObservationConfig {
    /// Square camera images (pixels); datasets must match.
    pub image_size: usize,
    /// Output stride of the image encoder: each camera gives (size/stride)^2 feature pixels,
    /// each lifted to the world xyz of its depth pixel.
    pub feature_stride: usize,
    /// The workspace box (world frame, metres): points outside are dropped; positions (points and
    /// actions) are normalised to [-1, 1] over it.
    pub workspace: WorkspaceBounds,
    /// N1: semantic tokens (farthest point sampled from the lifted feature pixels).
    pub semantic_tokens: usize,
    /// N2: geometric tokens (sampled around the noisy action position by the radius schedule).
    pub geometric_tokens: usize,
    /// Fewer points than this within r(t): geometric tokens fall back to global sampling.
    pub min_inside: usize,
    /// Language tokens: the instruction's MiniLM tokens, truncated or padded to this count.
    pub language_tokens: usize,
    /// The cameras the policy sees, by name, in this order (a subset of the dataset's, e.g.
    /// `["front"]` for the paper's single-view setting). Empty (the default): every camera of the
    /// observation, in its order.
    #[serde(default)]
    pub cameras: Vec<String>,
    /// Condition on the keyframe index: how many keyframes of the episode were executed before
    /// this observation (0 at the start; clipped to [`MAX_KEYFRAME_INDEX`]), as a learned
    /// embedding added to every Mamba block's AdaLN condition. PerAct, RVT and RVT-2 give the
    /// policy the episode's timestep the same way; it tells the phases of a sequence apart that
    /// look alike (the second block of a stack; the second button of "push the maroon button,
    /// then the green button" before push_buttons' rings showed presses, expert version 2).
    /// Recovery detours do not count (see
    /// [`Observation::from_episode`](crate::policy::scene::observation::Observation::from_episode)).
    /// Off (the paper): the observation alone.
    #[serde(default)]
    pub keyframe_index: bool,
    /// Gripper poses the proprioception carries: the current one and the `proprio_history - 1`
    /// before it (the TCP pose and gripper state at the episode's earlier keyframe observations,
    /// most recent first; an episode's first keyframes repeat the oldest pose they have), each
    /// normalised as the current one is and fed together through the proprioception MLP into
    /// the AdaLN condition. The paper's release and 3D Diffuser Actor train with
    /// `--num_history 3`: where the gripper has been says which button was pushed (they spring
    /// back; since expert version 2 their rings also show it) and how high the last block was
    /// placed. Recovery detours are not part of the history (see `keyframe_index`). 1 (the default): the current pose alone.
    #[serde(default = "one")]
    pub proprio_history: usize,
}

/// The most gripper poses `observation.proprio_history` may ask for.
pub const MAX_PROPRIO_HISTORY: usize = 8;

/// Keyframe indices at or past this share the last embedding row (`observation.keyframe_index`):
/// RLBench's evaluation allows 25 keyframes.
pub const MAX_KEYFRAME_INDEX: usize = 31;

/// The network.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    /// C: token width = Mamba d_model (Table B: 120).
    pub channels: usize,
    pub d_state: usize,
    pub d_conv: usize,
    pub expand: usize,
    /// Mamba blocks over [language, semantic, geometric, action].
    pub layers: usize,
    /// Also modulate every Mamba block (AdaLN, added to the proprioception's embedding) by an
    /// MLP of the instruction's sentence embedding, so the instruction reaches the action token
    /// directly, as a class label conditions DiT and FiLM conditions DP3. Off (the paper): the
    /// instruction is only the first tokens of the scan.
    #[serde(default)]
    pub instruction_adaln: bool,
    /// What the instruction AdaLN reads: `"sentence"` (the MiniLM sentence embedding, a mean over
    /// the tokens) or `"attention"` (a learned softmax pooling of the instruction's token
    /// features, so the word that tells variations apart, "left" or "red", can dominate the
    /// condition rather than be averaged with the words every instruction of the task shares)
    /// or `"conditioned"` (that pooling with scores that also depend on the AdaLN condition,
    /// proprioception plus `observation.keyframe_index`, and on each token's place in the
    /// instruction, so "push the maroon button, then the green one" can pool to "maroon" before
    /// the first press and to "green" after it).
    #[serde(default)]
    pub instruction_pooling: InstructionPooling,
    /// Append an instruction-pointer token to the prefix: a softmax attention whose query is the
    /// instruction (pooled as `instruction_pooling` says) and whose keys and values are the
    /// semantic tokens, so "the red button" can pick out the tokens that look like it and hand
    /// their features and positions to the scan in one token. The token also carries the
    /// encoding of the pointed position (the attention-weighted mean of the tokens' positions),
    /// and the action token the encoding of its offset from that position, so the action can be
    /// placed relative to the object the instruction names (behind the block, seen from the
    /// named zone). `flow.goal_weight` supervises where it points. Off (the paper): the scan
    /// alone must carry the instruction to the right tokens.
    #[serde(default)]
    pub instruction_pointer: bool,
    /// Read the predicted position out as a pointer into the scene: a softmax attention whose
    /// query is the action token's output plus the instruction (pooled as `instruction_pooling`
    /// says) and whose keys are the semantic and geometric tokens; the predicted endpoint's
    /// position is the attention-weighted mean of those tokens' positions plus the position
    /// head's offset. Choosing "the red button" becomes choosing tokens, a classification with
    /// a direct gradient, as Act3D's ghost points and RVT's heatmaps point at the scene. Needs
    /// `flow.prediction = "endpoint"` (the pointer gives a point, not a velocity). Off (the
    /// paper): the position head regresses the position from the action token alone.
    #[serde(default)]
    pub position_pointer: bool,
    /// Add an MLP of each feature pixel's raw mean colour (its stride x stride image pixels,
    /// before any normalisation) to the image features every token gathers. The image encoder's
    /// per-pixel LayerNorms remove much of a colour's brightness, and half of RLBench's palette
    /// is pairs that differ only in brightness (red and maroon, blue and navy, lime and green,
    /// white, silver, gray and black). Off (the paper): tokens carry the encoder's features only.
    #[serde(default)]
    pub point_colour: bool,
    /// Heads of an attention from the action token's output to the instruction's tokens, added
    /// to that output before the heads read it (0: off). Keys are the tokens' MiniLM features
    /// plus a learned embedding of their place in the instruction; the query is the action
    /// token's output, which knows the phase (the AdaLN condition carries proprioception and
    /// `observation.keyframe_index`) and where the noisy sample is; the output projection starts
    /// at zero, so a new model starts as without it. 3D Diffuser Actor attends from its queries
    /// to every language token in every layer; here the one pooled instruction vector
    /// (`instruction_pooling`) had to name the k-th colour of "push the red button, then ...",
    /// and the second button's approach went to the third-named button in a third of held-out
    /// three-button episodes (docs/experiments.md, session 31). Must divide `channels`.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub language_attention_heads: usize,
    /// Which heads read the language attention's output (`model.language_attention_heads`):
    /// `"token"` (every head: the position offset, rotation, gripper, relation and the position
    /// pointer's query) or `"pointer"` (only the position pointer's query; the other heads read
    /// the action token's output as without the attention). On five tasks the attention added
    /// 45 / 24 stack_blocks episodes and cost 7 / 23 push_buttons ones over two training draws
    /// (session 32). `"pointer"` (arm LP5, session 33, the shipped five-task recipe): 103 / 72
    /// over two draws against the recipe without the attention, mostly slide_block and
    /// close_jar; push_buttons still 12 / 18 (docs/experiments.md).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub language_attention_reads: LanguageReads,
    /// Place the position relative to two pointed positions: the position pointer's p and the
    /// instruction pointer's g (needs both pointers), as p + beta * (p - g) + offset, with beta a
    /// linear function of the action token's output (zero at initialisation, so training starts
    /// as without it). Some keyframes are defined by two objects rather than one: slide_block's
    /// first ones are beside the block on the side away from the named zone (beta about 0.3 with
    /// p on the block and g on the zone), which a pointer whose keys are local token features
    /// cannot point at (the table there looks the same on every side), and which the offset head
    /// alone did not learn (docs/experiments.md, sessions 4-11). Off (the paper): one pointer.
    #[serde(default)]
    pub relational_pointer: bool,
    /// The rotation also reads the pointers' relation: the rotation head's output plus a small
    /// MLP of g - p (needs `relational_pointer`; the MLP's output layer is zero at
    /// initialisation, so training starts as without it). slide_block's gripper yaw is the push
    /// direction (0 deg along x, 90 deg along y), the direction from the block to the named zone;
    /// the relation gives the position that direction, but the rotation head sees only the action
    /// token, and on the held-out y pushes it predicted the x pushes' yaw in most samples,
    /// 81-92 deg off (docs/experiments.md, session 27). g - p is not detached: the rotation's
    /// loss also trains both pointers. With `flow.pointer_sharpening` the p it reads at inference
    /// is sharper than in training. Off (the paper): the rotation from the action token alone.
    #[serde(default)]
    pub relation_rotation: bool,
    /// `relation_rotation`'s MLP also reads the action token's output (its input is g - p and
    /// the token, so it can tell the tasks apart). On five tasks the MLP of g - p alone did not
    /// learn slide_block's y-push yaw (81-93 deg off on most held-out samples, arm GUR), where
    /// on slide_block alone it did (arm SR): g - p spans the same directions on every task, and
    /// only slide_block's yaw follows it. Measured: no help (arm GUT 151/250 against GUR's 155,
    /// paired 14 / 18; the y pushes' yaw still follows the source noise). Off: g - p alone.
    #[serde(default)]
    pub relation_rotation_reads_token: bool,
}

/// How the instruction is pooled into one vector for the instruction AdaLN
/// (`model.instruction_adaln`), the instruction-pointer token and the position pointer's query.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InstructionPooling {
    #[default]
    Sentence,
    Attention,
    /// `Attention` plus a zero-initialised query from the condition against keys of each
    /// token's features and its index in the instruction: a new model starts as `Attention`.
    Conditioned,
}

/// Which heads read the language attention's output (`model.language_attention_reads`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LanguageReads {
    /// Every head reads the action token's output with what it read from the instruction.
    #[default]
    Token,
    /// Only the position pointer's query does.
    Pointer,
}

/// Conditional flow matching.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlowConfig {
    /// Euler steps at inference (Table C: 2 to 32).
    pub sampling_steps: usize,
    /// Keyframe samples (source noises) drawn per observation at inference, as one batch; the
    /// keyframe executed is their consensus, the medoid of their positions
    /// ([`crate::policy::inference::consensus`]). 1 (the paper): the single sample.
    #[serde(default = "one")]
    pub consensus_samples: usize,
    /// Which of those samples is executed: `"medoid"` (the sample with the least summed distance
    /// to the others) or `"mode"` (the sample with the most others within
    /// [`crate::policy::inference::MODE_RADIUS`]; among equals, the least summed distance). See
    /// [`crate::policy::inference::consensus`].
    #[serde(default)]
    pub consensus: Consensus,
    /// Inference only: the position pointer's scores (`model.position_pointer`) are divided by
    /// `temperature` at the Euler steps whose flow time is below `until`, so that the first
    /// steps point at one object where the attention is split over several (four blocks of
    /// the named colour) instead of at the mean of their positions, between them; the later
    /// steps point as trained, for precision. `{ temperature = 1.0 }`: off (the default).
    #[serde(default)]
    pub pointer_sharpening: PointerSharpening,
    /// Loss = cfm_weight * velocity MSE + open_weight * gripper BCE (supplementary: 100, 10).
    pub cfm_weight: f64,
    pub open_weight: f64,
    /// What the action head predicts: `"velocity"` (Algorithm 1) or `"endpoint"` (the clean
    /// action a1; the Euler sampler then steps with v = (a1_hat - a_t) / (1 - t)).
    #[serde(default)]
    pub prediction: Prediction,
    /// How training draws the flow time t: `{ kind = "uniform" }` (Algorithm 1) or
    /// `{ kind = "logit_normal", mean = 0.0, std = 1.0 }`.
    #[serde(default)]
    pub time_sampling: FlowTimeSampling,
    /// Weight of the position pointer's own loss (`model.position_pointer`): the cross-entropy of
    /// its attention against a soft target on the tokens near the keyframe's position
    /// (softmax of -d^2 / (2 pointer_sigma^2), d in metres), added to the total. It supervises the
    /// choice of object at every flow time, where the flow loss does so only at early times, when
    /// a_t is mostly noise. 0 (the paper has no pointer): none.
    #[serde(default)]
    pub pointer_weight: f64,
    /// Metres; the width of that soft target (and of `goal_weight`'s).
    #[serde(default = "pointer_sigma")]
    pub pointer_sigma: f64,
    /// Weight of the instruction pointer's own loss (`model.instruction_pointer`): the
    /// cross-entropy of its attention over the semantic tokens against a soft target on the
    /// tokens near the episode's last keyframe (the goal the instruction names: the drawer
    /// pulled open, the zone the block ends in, the jar the lid goes on), added to the total.
    /// The position pointer's loss supervises only where the next keyframe is; on slide_block
    /// that is beside the block for the first keyframes, so the named zone, which decides which
    /// side of the block to go down on, is never pointed at until the push. 0 (the paper has no
    /// pointer): none.
    #[serde(default)]
    pub goal_weight: f64,
    /// Where `pointer_weight` asks the position pointer to point: `"keyframe"` (the tokens near
    /// the keyframe's position) or `"relational"` (with `model.relational_pointer`: near the
    /// point p* whose relation lands on the keyframe, p* + beta (p* - g) = keyframe, i.e.
    /// p* = (keyframe + beta g) / (1 + beta), with the model's own beta and g, not
    /// differentiated). On slide_block's first keyframes the keyframe target puts the pointer on
    /// the edge of the block on the side to go down on, so the pointer must choose the side
    /// itself and the relation's shift comes on top of it; the relational target leaves the
    /// pointer on the block and the side to the relation. Measured harmful on slide_block
    /// (`docs/experiments.md`, session 26: 10/50 against 17/50); the default stays "keyframe".
    #[serde(default)]
    pub pointer_target: PointerTarget,
    /// How `goal_weight`'s soft target measures nearness to the episode's last keyframe:
    /// `"keyframe"` (3-D distance) or `"under"` (horizontal distance only: the tokens under the
    /// goal, whatever their height). slide_block's last keyframe is 10 cm above the end of the
    /// push; in 3-D the nearest tokens are the block's far edge, not the named zone 12 cm below,
    /// so the instruction pointer learns to point at the block (`predict --json` shows g 2 cm
    /// from the block's centre on held-out episodes, session 27) and the relation p + beta (p - g)
    /// cannot say "opposite the named zone".
    #[serde(default)]
    pub goal_target: GoalTarget,
    /// Which keyframe `goal_weight`'s target is: `"last"` (the episode's last keyframe, the
    /// default) or `"stage_end"` (the end of the sample's stage, [`stage_end`]: the first
    /// keyframe from the sample's on that the arm reaches coming down and leaves going up: a
    /// press, a grasp, a placing, the end of a push; the last keyframe where none follows). On
    /// push_buttons' sequences the last keyframe is the last button, so the instruction
    /// pointer learnt to point there while the arm goes to the first, and the relation's shift
    /// beta (p - g) moved the first press 3-7 cm (`docs/experiments.md`, session 27); the stage's
    /// end is the button pressed now. On slide_block and open_drawer it is the last keyframe's
    /// place, as before; on close_jar and stack_blocks the object picked while picking.
    ///
    /// [`stage_end`]: crate::policy::scene::observation::stage_end
    #[serde(default, skip_serializing_if = "GoalKeyframe::is_last")]
    pub goal_keyframe: GoalKeyframe,
    /// Training only: the probability that a sample's instruction is replaced by the null
    /// instruction (the empty one, [`crate::policy::inputs::NULL_INSTRUCTION`]: its token
    /// features, sentence embedding and everything read from them), so the model also learns
    /// the unconditional keyframe distribution that `flow.pointer_sharpening.guidance` contrasts
    /// with (classifier-free guidance: DiT, pi0's and Octo's language dropout). Its own random
    /// stream, so the other draws of a step are unchanged. 0 (the paper): never.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub instruction_dropout: f64,
    /// Weight of the instruction-grounding loss (`model.position_pointer`; training only): a
    /// class-balanced logistic loss on the scores of the position pointer's instruction query
    /// against every semantic token's key, labelled 1 on the tokens within `grounding_radius`
    /// (horizontally) of any keyframe of the episode from the sample's on: every object the
    /// instruction still names (all the blocks of the named colour still to stack, the buttons
    /// still to press), not only the next one, which is all the pointer's own loss supervises.
    /// It adds no weight and changes no inference. 0 (the paper has no pointer): none.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub grounding_weight: f64,
    /// Metres; the horizontal radius of `grounding_weight`'s positive tokens.
    #[serde(default = "grounding_radius", skip_serializing_if = "is_grounding_radius")]
    pub grounding_radius: f64,
}

/// `flow.goal_keyframe`: which keyframe the instruction pointer's loss points at.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GoalKeyframe {
    /// The episode's last keyframe.
    #[default]
    Last,
    /// The end of the sample's stage ([`crate::policy::scene::observation::stage_end`]).
    StageEnd,
}

impl GoalKeyframe {
    fn is_last(&self) -> bool {
        *self == Self::Last
    }
}

/// `flow.goal_target`: how the instruction pointer's loss measures nearness to the goal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GoalTarget {
    /// The tokens near the episode's last keyframe (3-D distance).
    #[default]
    Keyframe,
    /// The tokens under it (horizontal distance only).
    Under,
}

/// `flow.pointer_target`: what the position pointer's loss points at.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PointerTarget {
    /// The tokens near the keyframe's position.
    #[default]
    Keyframe,
    /// The tokens near the point whose relation (`model.relational_pointer`) lands on the keyframe.
    Relational,
}

fn pointer_sigma() -> f64 {
    0.02
}

fn grounding_radius() -> f64 {
    0.03
}

fn is_grounding_radius(r: &f64) -> bool {
    *r == grounding_radius()
}

/// `flow.pointer_sharpening`: the position pointer's temperature over the first Euler steps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PointerSharpening {
    /// Divides the pointer's scores; 1: as trained, below 1: sharper.
    pub temperature: f64,
    /// Flow time: the steps at t < until are sharpened (0.5 of 8 steps: the first 4).
    #[serde(default = "half")]
    pub until: f64,
    /// At every Euler step (whatever `until`), add to each candidate i's score the log-likelihood
    /// of the noisy position a_t had the keyframe been that candidate's position x_i plus the
    /// position head's offset c: -|a_t - t (x_i + c)|^2 / (2 (1 - t)^2), from the straight path's
    /// a_t = t a1 + (1 - t) a0 with a0 ~ N(0, I) (normalised workspace units; the relational
    /// pointer's shift beta (p - g) is left out of c). The scores act as the prior over candidates,
    /// so the pointer becomes the posterior given where the sample already is: near t = 0 as
    /// trained, later committed to the candidates near the sample (one block of several alike,
    /// not their mean). Inference only; false: as trained.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub posterior: bool,
    /// m, with `posterior`: the keyframe's spread w about its candidate, so a1 ~ N(x_i + c, w^2)
    /// and the likelihood's variance per axis is (1 - t)^2 + t^2 w^2 (w in that axis's normalised
    /// units) instead of (1 - t)^2: a posterior that commits between candidates farther apart
    /// than w and snaps less to the one nearest the noisy sample among those closer. 0: the
    /// candidates are points (as shipped in session 30).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub posterior_width: f64,
    /// Classifier-free guidance of the pointer by the instruction, w: at every Euler step the
    /// scores are s_null + w (s - s_null), s_null the scores of the same step run with the null
    /// instruction (the empty one, [`crate::policy::inputs::NULL_INSTRUCTION`]), before the
    /// posterior's likelihood is added. 1: as trained (no second pass); above 1: the candidates
    /// the instruction favours over no instruction gain log-odds (the named colour's button over
    /// the others'); 0: the unconditional pointer. Meant for checkpoints trained with
    /// `flow.instruction_dropout`, which know the null instruction; needs `model.position_pointer`.
    /// Inference only; costs a second prefix scan per keyframe and a second suffix scan per Euler
    /// step (the image features are shared).
    #[serde(default = "one_f64", skip_serializing_if = "is_one")]
    pub guidance: f64,
}

fn one_f64() -> f64 {
    1.0
}

fn is_one(x: &f64) -> bool {
    *x == 1.0
}

fn is_zero<T: Default + PartialEq>(x: &T) -> bool {
    *x == T::default()
}

fn half() -> f64 {
    0.5
}

impl Default for PointerSharpening {
    fn default() -> Self {
        Self::OFF
    }
}

impl PointerSharpening {
    /// As trained at every step.
    pub const OFF: Self = Self { temperature: 1.0, until: 0.5, posterior: false, posterior_width: 0.0, guidance: 1.0 };

    /// This sharpening with its temperature replaced where one is given (a command line's
    /// `--pointer-temperature` over the checkpoint's setting).
    pub fn with_temperature(self, temperature: Option<f64>) -> Self {
        Self { temperature: temperature.unwrap_or(self.temperature), ..self }
    }

    /// This sharpening, made the posterior where a command line asks (`--pointer-posterior`).
    pub fn with_posterior(self, posterior: bool) -> Self {
        Self { posterior: self.posterior || posterior, ..self }
    }

    /// This sharpening with the posterior's candidate width replaced where one is given (a
    /// command line's `--pointer-posterior-width`, which also turns the posterior on).
    pub fn with_posterior_width(self, width: Option<f64>) -> Self {
        match width {
            Some(posterior_width) => Self { posterior: true, posterior_width, ..self },
            None => self,
        }
    }

    /// This sharpening with the instruction's guidance replaced where one is given (a command
    /// line's `--pointer-guidance`).
    pub fn with_guidance(self, guidance: Option<f64>) -> Self {
        Self { guidance: guidance.unwrap_or(self.guidance), ..self }
    }

    /// Whether sampling runs the null instruction's second pass (`guidance` other than 1).
    pub fn guided(&self) -> bool {
        self.guidance != 1.0
    }

    /// Errors: [`PolicyError::Invalid`] naming the field unless the temperature is positive, the
    /// flow time `until` in [0, 1], the posterior's width finite and at least 0 (0 without the
    /// posterior) and the guidance finite and at least 0.
    pub fn validate(&self) -> Result<()> {
        let bad = |field: &str, expected: &str, got: String| {
            Err(PolicyError::Invalid(format!("flow.pointer_sharpening.{field} must be {expected}; got {got}")))
        };
        if !(self.temperature.is_finite() && self.temperature > 0.0) {
            return bad("temperature", "positive (1: off)", self.temperature.to_string());
        }
        if !(0.0..=1.0).contains(&self.until) {
            return bad("until", "a flow time in [0, 1]", self.until.to_string());
        }
        if !(self.posterior_width.is_finite() && self.posterior_width >= 0.0) {
            return bad("posterior_width", "a width in metres, at least 0 (0: off)", self.posterior_width.to_string());
        }
        if !(self.guidance.is_finite() && self.guidance >= 0.0) {
            return bad("guidance", "a finite weight, at least 0 (1: off, as trained)", self.guidance.to_string());
        }
        if self.posterior_width > 0.0 && !self.posterior {
            return bad(
                "posterior_width",
                "0 unless posterior = true (the width is the posterior's; set posterior = true or drop the width)",
                self.posterior_width.to_string(),
            );
        }
        Ok(())
    }

    /// The pointer's temperature at flow time `t`.
    pub fn temperature_at(&self, t: f32) -> f64 {
        // in f32, as the sampler's t: 7 / 10 as f32 is below 0.7 as f64
        if t < self.until as f32 { self.temperature } else { 1.0 }
    }
}

/// How the executed keyframe is chosen among several samples of one observation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Consensus {
    /// The sample with the least summed distance to the others (arm C8).
    #[default]
    Medoid,
    /// The sample in the densest cluster: the most others within
    /// [`crate::policy::inference::MODE_RADIUS`]; among equals, the least summed distance to
    /// all samples (so within a cluster the sample nearest the rest, at most the radius from
    /// its centre). Where the samples split between several objects the medoid leans to the one
    /// nearest the middle of them all; the mode goes with the most samples.
    Mode,
}

impl Consensus {
    pub fn name(self) -> &'static str {
        match self {
            Self::Medoid => "medoid",
            Self::Mode => "mode",
        }
    }
}

/// Training.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub steps: usize,
    pub batch: usize,
    /// Peak learning rate (after warm-up).
    pub learning_rate: f64,
    /// Linear warm-up from 0 over this many steps.
    pub warmup_steps: usize,
    /// Cosine decay from `learning_rate` to `min_learning_rate` at `steps` (false: constant).
    pub cosine_decay: bool,
    pub min_learning_rate: f64,
    pub weight_decay: f64,
    pub betas: [f64; 2],
    /// Decay of the exponential moving average of the weights used for inference.
    pub ema_decay: f64,
    /// Gradient-norm clipping (0 = none).
    pub grad_clip: f64,
    pub seed: u64,
    /// Augmentation: the whole scene (points, proprioception, action) shifted by a uniform
    /// random offset of up to this many metres per axis.
    pub translation_jitter: f64,
    /// Augmentation: image brightness scaled by a uniform factor in [1 - b, 1 + b].
    pub brightness_jitter: f64,
    pub checkpoint_every: usize,
    pub log_every: usize,
    /// Flow samples (noise a0 and time t) per observation of the batch: the K samples of one
    /// observation share its image encoding, which is most of a step's cost, so the flow loss
    /// sees `batch x flow_samples` samples for little more compute (as Octo and MAR do). 1 (the
    /// paper): one sample per observation.
    #[serde(default = "one")]
    pub flow_samples: usize,
    /// How often each task is drawn relative to the others: task name -> weight (finite, > 0);
    /// a task not named weighs 1. Empty (the default): every task equally, as the release
    /// samples, with the same draws as before the option existed.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub task_weights: BTreeMap<String, f64>,
}

fn one() -> usize {
    1
}

impl PolicyConfig {
    /// Reads and validates a TOML file.
    pub fn from_toml_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| PolicyError::File {
            path: path.into(),
            message: format!("cannot read the policy config: {e}"),
        })?;
        let config: Self =
            toml::from_str(&text).map_err(|e| PolicyError::File { path: path.into(), message: e.to_string() })?;
        config.validate().map_err(|e| PolicyError::File { path: path.into(), message: e.to_string() })?;
        Ok(config)
    }

    /// The CPU-sized default (`models/policy/cpu.toml`).
    pub fn cpu_default() -> Result<Self> {
        Self::from_toml_file(&crate::deps::models_dir().join("policy/cpu.toml"))
    }

    /// Checks every value; the error names the field.
    pub fn validate(&self) -> Result<()> {
        let o = &self.observation;
        let bad = |field: &str, expected: &str, got: String| {
            Err(PolicyError::Invalid(format!("policy config: {field} must be {expected}; got {got}")))
        };
        if o.image_size == 0 || o.feature_stride == 0 || !o.image_size.is_multiple_of(o.feature_stride) {
            return bad(
                "observation.feature_stride",
                "positive and divide observation.image_size",
                format!("{} / {}", o.feature_stride, o.image_size),
            );
        }
        for (field, v) in [
            ("observation.semantic_tokens", o.semantic_tokens),
            ("observation.geometric_tokens", o.geometric_tokens),
            ("observation.min_inside", o.min_inside),
            ("observation.language_tokens", o.language_tokens),
            ("model.channels", self.model.channels),
            ("model.d_state", self.model.d_state),
            ("model.d_conv", self.model.d_conv),
            ("model.expand", self.model.expand),
            ("model.layers", self.model.layers),
            ("flow.sampling_steps", self.flow.sampling_steps),
            ("flow.consensus_samples", self.flow.consensus_samples),
            ("train.batch", self.train.batch),
            ("train.flow_samples", self.train.flow_samples),
            ("train.checkpoint_every", self.train.checkpoint_every),
            ("train.log_every", self.train.log_every),
        ] {
            if v == 0 {
                return bad(field, "positive", v.to_string());
            }
        }
        for (task, &w) in &self.train.task_weights {
            if !(w.is_finite() && w > 0.0) {
                return bad(
                    &format!("train.task_weights.{task}"),
                    "a finite weight above 0 (1: as the others)",
                    w.to_string(),
                );
            }
        }
        self.flow.pointer_sharpening.validate().map_err(|e| PolicyError::Invalid(format!("policy config: {e}")))?;
        if self.flow.pointer_sharpening.guided() && !self.model.position_pointer {
            return bad(
                "flow.pointer_sharpening.guidance",
                "1 unless model.position_pointer = true (it guides the pointer's scores)",
                self.flow.pointer_sharpening.guidance.to_string(),
            );
        }
        let dropout = self.flow.instruction_dropout;
        if !(0.0..1.0).contains(&dropout) {
            return bad("flow.instruction_dropout", "a probability in [0, 1) (0: off)", dropout.to_string());
        }
        if !self.model.channels.is_multiple_of(6) {
            return bad(
                "model.channels",
                "a multiple of 6 (the 3D positional encoding uses sin and cos per axis)",
                self.model.channels.to_string(),
            );
        }
        let heads = self.model.language_attention_heads;
        if heads > 0 && !self.model.channels.is_multiple_of(heads) {
            return bad(
                "model.language_attention_heads",
                &format!("0 (off) or a divisor of model.channels ({})", self.model.channels),
                heads.to_string(),
            );
        }
        if heads == 0 && self.model.language_attention_reads != LanguageReads::Token {
            return bad(
                "model.language_attention_reads",
                "\"token\" (the default) unless model.language_attention_heads is set: without the \
                 attention there is nothing for the pointer to read",
                "\"pointer\"".to_string(),
            );
        }
        if self.model.language_attention_reads == LanguageReads::Pointer && !self.model.position_pointer {
            return bad(
                "model.language_attention_reads",
                "\"token\" unless model.position_pointer is on (\"pointer\" feeds only its query)",
                "\"pointer\"".to_string(),
            );
        }
        if !(1..=MAX_PROPRIO_HISTORY).contains(&o.proprio_history) {
            return bad(
                "observation.proprio_history",
                &format!("1 (the current gripper pose alone) to {MAX_PROPRIO_HISTORY}"),
                o.proprio_history.to_string(),
            );
        }
        for (i, name) in o.cameras.iter().enumerate() {
            if name.is_empty() || o.cameras[..i].contains(name) {
                return bad("observation.cameras", "distinct, non-empty camera names", format!("{:?}", o.cameras));
            }
        }
        if self.model.position_pointer && self.flow.prediction != Prediction::Endpoint {
            return bad(
                "flow.prediction",
                "\"endpoint\" when model.position_pointer = true (the pointer predicts the endpoint's position)",
                format!("{:?}", self.flow.prediction),
            );
        }
        if self.model.relational_pointer && !(self.model.position_pointer && self.model.instruction_pointer) {
            return bad(
                "model.relational_pointer",
                "false unless model.position_pointer = true and model.instruction_pointer = true (it relates their two pointed positions)",
                "true".to_string(),
            );
        }
        if self.model.relation_rotation && !self.model.relational_pointer {
            return bad(
                "model.relation_rotation",
                "false unless model.relational_pointer = true (it reads the relation's g - p)",
                "true".to_string(),
            );
        }
        if self.model.relation_rotation_reads_token && !self.model.relation_rotation {
            return bad(
                "model.relation_rotation_reads_token",
                "false unless model.relation_rotation = true (it widens that MLP's input)",
                "true".to_string(),
            );
        }
        if self.flow.pointer_weight > 0.0 && !self.model.position_pointer {
            return bad(
                "flow.pointer_weight",
                "0 unless model.position_pointer = true (it is the pointer's loss)",
                self.flow.pointer_weight.to_string(),
            );
        }
        if self.flow.pointer_target == PointerTarget::Relational
            && !(self.model.relational_pointer && self.flow.pointer_weight > 0.0)
        {
            return bad(
                "flow.pointer_target",
                "\"keyframe\" unless model.relational_pointer = true and flow.pointer_weight > 0 (the relational target is the pointer loss's, through the relation)",
                "\"relational\"".to_string(),
            );
        }
        if self.flow.goal_keyframe == GoalKeyframe::StageEnd && self.flow.goal_weight <= 0.0 {
            return bad(
                "flow.goal_keyframe",
                "\"last\" unless flow.goal_weight > 0 (it chooses the instruction pointer loss's target)",
                "\"stage_end\"".to_string(),
            );
        }
        if self.flow.goal_target == GoalTarget::Under && self.flow.goal_weight <= 0.0 {
            return bad(
                "flow.goal_target",
                "\"keyframe\" unless flow.goal_weight > 0 (it shapes the instruction pointer's loss)",
                "\"under\"".to_string(),
            );
        }
        if self.flow.grounding_weight > 0.0 && !self.model.position_pointer {
            return bad(
                "flow.grounding_weight",
                "0 unless model.position_pointer = true (it scores the pointer's instruction query against its keys)",
                self.flow.grounding_weight.to_string(),
            );
        }
        if self.flow.goal_weight > 0.0 && !self.model.instruction_pointer {
            return bad(
                "flow.goal_weight",
                "0 unless model.instruction_pointer = true (it is the instruction pointer's loss)",
                self.flow.goal_weight.to_string(),
            );
        }
        self.radius_schedule.validate()?;
        self.flow.time_sampling.validate()?;
        let t = &self.train;
        for (field, v, ok) in [
            ("flow.cfm_weight", self.flow.cfm_weight, self.flow.cfm_weight >= 0.0),
            ("flow.open_weight", self.flow.open_weight, self.flow.open_weight >= 0.0),
            ("flow.pointer_weight", self.flow.pointer_weight, self.flow.pointer_weight >= 0.0),
            ("flow.pointer_sigma", self.flow.pointer_sigma, self.flow.pointer_sigma > 0.0),
            ("flow.goal_weight", self.flow.goal_weight, self.flow.goal_weight >= 0.0),
            ("flow.grounding_weight", self.flow.grounding_weight, self.flow.grounding_weight >= 0.0),
            ("flow.grounding_radius", self.flow.grounding_radius, self.flow.grounding_radius > 0.0),
            ("train.learning_rate", t.learning_rate, t.learning_rate > 0.0),
            ("train.weight_decay", t.weight_decay, t.weight_decay >= 0.0),
            ("train.min_learning_rate", t.min_learning_rate, (0.0..=t.learning_rate).contains(&t.min_learning_rate)),
            ("train.betas[0]", t.betas[0], (0.0..1.0).contains(&t.betas[0])),
            ("train.betas[1]", t.betas[1], (0.0..1.0).contains(&t.betas[1])),
            ("train.ema_decay", t.ema_decay, (0.0..1.0).contains(&t.ema_decay)),
            ("train.grad_clip", t.grad_clip, t.grad_clip >= 0.0),
            ("train.translation_jitter", t.translation_jitter, (0.0..0.2).contains(&t.translation_jitter)),
            ("train.brightness_jitter", t.brightness_jitter, (0.0..1.0).contains(&t.brightness_jitter)),
        ] {
            if !(v.is_finite() && ok) {
                return bad(field, "finite and in its range (see models/policy/cpu.toml)", v.to_string());
            }
        }
        Ok(())
    }
}
