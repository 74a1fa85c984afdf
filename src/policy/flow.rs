//! Conditional flow matching for the next keyframe action (FlowRAM, supplementary
//! Algorithms 1 and 2): the action layout, the noisy training pair
//! (`a_t = t*a1 + (1-t)*a0`, target velocity `a1 - a0`), the weighted loss
//! (`100 * L_CFM + 10 * L_open`, Table B) and the accumulating Euler sampler.
//!
//! Action layout (one row of a `[B, ACTION_DIMS]` tensor):
//! `[x, y, z, r00, r10, r20, r01, r11, r21]` — the keyframe position normalised
//! to the workspace box (each axis in [-1, 1]) followed by the 6D rotation, the
//! first two *columns* of the rotation matrix (Zhou et al. 2019). These nine
//! dimensions are flowed. The gripper-open state is not flowed: the network
//! predicts it as one logit per sample, trained with BCE.

use candle_core::{DType, Device, Tensor};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::policy::error::{PolicyError, Result};
use crate::policy::scene::observation::ACTION_DIMS;

/// Weights of the two loss terms (supplementary Table B: L_CFM 100, L_open 10).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LossWeights {
    /// Weight of the velocity MSE (L_CFM).
    pub cfm: f64,
    /// Weight of the gripper-open BCE-with-logits (L_open).
    pub open: f64,
}

impl Default for LossWeights {
    fn default() -> Self {
        Self { cfm: 100.0, open: 10.0 }
    }
}

/// How the flow time `t` of a training sample is drawn.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum FlowTimeSampling {
    /// `t ~ U[0, 1)` (Algorithm 1; the default).
    #[default]
    Uniform,
    /// `t = sigmoid(mean + std * z)`, `z ~ N(0, 1)` (Esser et al. 2024): more
    /// samples at intermediate times. Off unless asked for.
    LogitNormal { mean: f64, std: f64 },
}

impl FlowTimeSampling {
    /// Checks the parameters (a logit-normal std must be positive and finite).
    pub fn validate(&self) -> Result<()> {
        match *self {
            FlowTimeSampling::Uniform => Ok(()),
            FlowTimeSampling::LogitNormal { mean, std } => {
                if mean.is_finite() && std.is_finite() && std > 0.0 {
                    Ok(())
                } else {
                    Err(PolicyError::Invalid(format!(
                        "flow time sampling: logit-normal needs a finite mean and a positive finite std, got mean {mean}, std {std}"
                    )))
                }
            }
        }
    }
}

/// What the network's action head predicts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Prediction {
    /// The velocity `a1 - a0` of the straight path (Algorithm 1).
    #[default]
    Velocity,
    /// The path's endpoint, the clean action `a1` (DP3's "sample" prediction). The regression
    /// target does not carry the noise `a0`, so late flow times are not dominated by it; the
    /// sampler's velocity is `(a1_hat - a_t) / (1 - t)`, which lands on `a1_hat` at the last
    /// Euler step.
    Endpoint,
}

impl Prediction {
    /// What the head regresses for a training sample with clean actions `a1`.
    pub fn target(self, sample: &FlowTrainingSample, a1: &Tensor) -> Tensor {
        match self {
            Prediction::Velocity => sample.target_velocity.clone(),
            Prediction::Endpoint => a1.clone(),
        }
    }

    /// The velocity at `(a_t, t)` for the Euler sampler from the head's output `out`.
    pub fn velocity(self, out: Tensor, a_t: &Tensor, t: f32) -> Result<Tensor> {
        match self {
            Prediction::Velocity => Ok(out),
            Prediction::Endpoint => {
                // Euler steps run t = k / steps < 1; the guard keeps a caller's t = 1 finite.
                let remaining = f64::from(1.0 - t).max(1e-3);
                Ok((out - a_t)?.affine(1.0 / remaining, 0.0)?)
            }
        }
    }
}

/// One standard-normal draw (Box–Muller; deterministic given the RNG).
pub fn standard_normal<R: Rng + ?Sized>(rng: &mut R) -> f64 {
    // 1 - U[0,1) lies in (0, 1], so the log is finite.
    let u1: f64 = 1.0 - rng.random::<f64>();
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Draws `batch` flow times in [0, 1) (`[B]` as a Vec, f32).
pub fn sample_flow_times<R: Rng + ?Sized>(rng: &mut R, batch: usize, sampling: FlowTimeSampling) -> Result<Vec<f32>> {
    sampling.validate()?;
    let times = (0..batch)
        .map(|_| match sampling {
            FlowTimeSampling::Uniform => rng.random_range(0.0f32..1.0),
            FlowTimeSampling::LogitNormal { mean, std } => {
                let logit = mean + std * standard_normal(rng);
                // Keep strictly below 1 like the uniform case.
                ((1.0 / (1.0 + (-logit).exp())) as f32).min(1.0 - f32::EPSILON)
            }
        })
        .collect();
    Ok(times)
}

/// Source noise `a0 ~ N(0, I)` of the flow, `[batch, dims]` f32 on `device`.
pub fn sample_source_noise<R: Rng + ?Sized>(rng: &mut R, batch: usize, dims: usize, device: &Device) -> Result<Tensor> {
    let values: Vec<f32> = (0..batch * dims).map(|_| standard_normal(rng) as f32).collect();
    Ok(Tensor::from_vec(values, (batch, dims), device)?)
}

fn check_same_shape(what: &str, a: &Tensor, b: &Tensor) -> Result<()> {
    if a.dims() != b.dims() {
        return Err(PolicyError::Invalid(format!(
            "{what}: shapes differ, {:?} vs {:?}; both must be [B, {ACTION_DIMS}]",
            a.dims(),
            b.dims()
        )));
    }
    if a.dtype() != b.dtype() {
        return Err(PolicyError::Invalid(format!("{what}: dtypes differ, {:?} vs {:?}", a.dtype(), b.dtype())));
    }
    Ok(())
}

/// Reshapes per-sample times `t [B]` so they broadcast over `like [B, ...]`.
fn broadcast_times(t: &Tensor, like: &Tensor) -> Result<Tensor> {
    let batch = like.dim(0)?;
    if t.dims() != [batch] {
        return Err(PolicyError::Invalid(format!(
            "flow times must be [B] = [{batch}] (one t per sample), got {:?}",
            t.dims()
        )));
    }
    let mut shape = vec![1usize; like.rank()];
    shape[0] = batch;
    Ok(t.to_dtype(like.dtype())?.reshape(shape)?)
}

/// The point on the straight path from noise to data:
/// `a_t = t * a1 + (1 - t) * a0`.
///
/// `a0` (noise) and `a1` (expert action): `[B, D]` (D = `ACTION_DIMS` for
/// FlowRAM); `t`: `[B]`, one flow time per sample. Returns `[B, D]`.
pub fn interpolate(a0: &Tensor, a1: &Tensor, t: &Tensor) -> Result<Tensor> {
    check_same_shape("interpolate(a0, a1)", a0, a1)?;
    if a0.rank() < 1 {
        return Err(PolicyError::Invalid("interpolate: actions must be batched, [B, D]".into()));
    }
    let t = broadcast_times(t, a1)?;
    Ok((a0.broadcast_mul(&t.affine(-1.0, 1.0)?)? + a1.broadcast_mul(&t)?)?)
}

/// The conditional target velocity of the straight path, `u = a1 - a0` (`[B, D]`).
pub fn target_velocity(a0: &Tensor, a1: &Tensor) -> Result<Tensor> {
    check_same_shape("target_velocity(a0, a1)", a0, a1)?;
    Ok((a1 - a0)?)
}

/// Everything one training step needs from Algorithm 1 for a batch of expert
/// actions.
#[derive(Debug, Clone)]
pub struct FlowTrainingSample {
    /// Source noise `a0 ~ N(0, I)`, `[B, D]`.
    pub a0: Tensor,
    /// Flow times, `[B]` f32 in [0, 1).
    pub t: Tensor,
    /// Noisy action `a_t`, `[B, D]` — the network's action input.
    pub a_t: Tensor,
    /// Target velocity `a1 - a0`, `[B, D]` — what the network regresses.
    pub target_velocity: Tensor,
}

/// Draws `a0` and `t` (in that order from `rng`) for expert actions
/// `a1 [B, D]` (f32) and builds `a_t` and the target velocity.
pub fn flow_training_sample<R: Rng + ?Sized>(
    a1: &Tensor,
    rng: &mut R,
    sampling: FlowTimeSampling,
) -> Result<FlowTrainingSample> {
    let (batch, dims) = a1
        .dims2()
        .map_err(|_| PolicyError::Invalid(format!("expert actions must be [B, {ACTION_DIMS}], got {:?}", a1.dims())))?;
    let a1 = a1.to_dtype(DType::F32)?;
    let a0 = sample_source_noise(rng, batch, dims, a1.device())?;
    let t = Tensor::from_vec(sample_flow_times(rng, batch, sampling)?, batch, a1.device())?;
    let a_t = interpolate(&a0, &a1, &t)?;
    let target_velocity = target_velocity(&a0, &a1)?;
    Ok(FlowTrainingSample { a0, t, a_t, target_velocity })
}

/// Mean binary cross-entropy with logits, computed stably as
/// `max(x, 0) - x*y + ln(1 + exp(-|x|))`. `logits`, `targets`: same shape,
/// targets in [0, 1]. Returns a scalar.
pub fn bce_with_logits(logits: &Tensor, targets: &Tensor) -> Result<Tensor> {
    if logits.dims() != targets.dims() {
        return Err(PolicyError::Invalid(format!(
            "bce_with_logits: logits {:?} and targets {:?} must have the same shape",
            logits.dims(),
            targets.dims()
        )));
    }
    let targets = targets.to_dtype(logits.dtype())?;
    let softplus_neg_abs = logits.abs()?.neg()?.exp()?.affine(1.0, 1.0)?.log()?;
    let per_sample = ((logits.relu()? - (logits * &targets)?)? + softplus_neg_abs)?;
    Ok(per_sample.mean_all()?)
}

/// The FlowRAM training loss.
///
/// `v_pred`, `target`: `[B, ACTION_DIMS]` predicted and target velocities;
/// `open_logit`, `open_target`: `[B]` gripper-open logit and label (1 = open).
/// Returns scalars `(total, cfm, bce)` with `cfm` = mean squared error over all
/// `B * D` elements, `bce` = mean BCE-with-logits, and
/// `total = weights.cfm * cfm + weights.open * bce`.
pub fn flow_matching_loss(
    v_pred: &Tensor,
    target: &Tensor,
    open_logit: &Tensor,
    open_target: &Tensor,
    weights: &LossWeights,
) -> Result<(Tensor, Tensor, Tensor)> {
    check_same_shape("flow_matching_loss(v_pred, target)", v_pred, target)?;
    let batch = v_pred.dim(0)?;
    if open_logit.dims() != [batch] || open_target.dims() != [batch] {
        return Err(PolicyError::Invalid(format!(
            "flow_matching_loss: open_logit {:?} and open_target {:?} must both be [B] = [{batch}]",
            open_logit.dims(),
            open_target.dims()
        )));
    }
    let cfm = (v_pred - target)?.sqr()?.mean_all()?;
    let bce = bce_with_logits(open_logit, open_target)?;
    let total = (cfm.affine(weights.cfm, 0.0)? + bce.affine(weights.open, 0.0)?)?;
    Ok((total, cfm, bce))
}

/// The position pointer's loss (`flow.pointer_weight`): the cross-entropy of its log attention
/// `log_weights` [B, N] over candidates at normalised positions `candidates` [B, N, 3] against
/// the soft target softmax(-d^2 / (2 sigma^2)), d the distance in metres from each candidate to
/// the keyframe position `target` [B, 3] (normalised; `half_extent` [3] metres per normalised
/// unit). A scalar, averaged over the batch.
pub fn pointer_loss(
    log_weights: &Tensor,
    candidates: &Tensor,
    target: &Tensor,
    half_extent: [f32; 3],
    sigma: f64,
) -> Result<Tensor> {
    let (b, n) = log_weights.dims2()?;
    if candidates.dims() != [b, n, 3] || target.dims() != [b, 3] {
        return Err(PolicyError::Invalid(format!(
            "pointer_loss: log weights {:?}, candidates {:?} and target {:?} must be [B, N], [B, N, 3], [B, 3]",
            log_weights.dims(),
            candidates.dims(),
            target.dims()
        )));
    }
    let scale = Tensor::from_vec(half_extent.to_vec(), (1, 1, 3), candidates.device())?;
    let d2 = candidates.broadcast_sub(&target.unsqueeze(1)?)?.broadcast_mul(&scale)?.sqr()?.sum(2)?;
    let soft = candle_nn::ops::softmax_last_dim(&d2.affine(-1.0 / (2.0 * sigma * sigma), 0.0)?)?.detach();
    Ok(soft.mul(log_weights)?.sum(1)?.neg()?.mean_all()?)
}

/// The labels of the instruction-grounding loss (`flow.grounding_weight`), one row of candidates:
/// 1 on the candidates (normalised positions) within `radius` metres horizontally of any of
/// the `later` positions (normalised: the episode's keyframes from the sample's on), else 0.
/// `half_extent`: metres per normalised unit per axis (z is not read).
pub fn grounding_labels(candidates: &[[f32; 3]], later: &[[f32; 3]], half_extent: [f32; 3], radius: f64) -> Vec<f32> {
    let r2 = (radius * radius) as f32;
    candidates
        .iter()
        .map(|c| {
            let near = later.iter().any(|p| {
                let (dx, dy) = ((c[0] - p[0]) * half_extent[0], (c[1] - p[1]) * half_extent[1]);
                dx * dx + dy * dy <= r2
            });
            if near { 1.0 } else { 0.0 }
        })
        .collect()
}

/// The instruction-grounding loss (`flow.grounding_weight`): logistic losses of `scores`
/// [B, N] against `labels` [B, N] (1: a token the instruction still names), the positives' and
/// the negatives' each averaged over their own count in the batch and the two halved, so that
/// the few tokens on the named objects weigh as much as the many others. A class absent from
/// the batch contributes nothing. The classes are counted over the whole batch, so rows with
/// more positives (a stack_blocks sample early in its episode) weigh more in the positives' mean.
pub fn grounding_loss(scores: &Tensor, labels: &Tensor) -> Result<Tensor> {
    if scores.rank() != 2 || scores.dims() != labels.dims() {
        return Err(PolicyError::Invalid(format!(
            "grounding_loss: scores {:?} and labels {:?} must both be [B, N]",
            scores.dims(),
            labels.dims()
        )));
    }
    let labels = labels.to_dtype(scores.dtype())?;
    let negatives = labels.affine(-1.0, 1.0)?;
    let positives_n = labels.sum_all()?.to_scalar::<f32>()?;
    let negatives_n = negatives.sum_all()?.to_scalar::<f32>()?;
    // softplus(s) = relu(s) + log(1 + e^-|s|) is a negative's loss; a positive's, softplus(-s),
    // is softplus(s) - s (the form of `bce_with_logits`, whose gradient is right at s = 0 too)
    let tail = scores.abs()?.neg()?.exp()?.affine(1.0, 1.0)?.log()?;
    let on_negative = scores.relu()?.add(&tail)?;
    let on_positive = on_negative.sub(scores)?;
    let mut loss = Tensor::zeros((), scores.dtype(), scores.device())?;
    if positives_n > 0.0 {
        loss = loss.add(&on_positive.mul(&labels)?.sum_all()?.affine(0.5 / f64::from(positives_n), 0.0)?)?;
    }
    if negatives_n > 0.0 {
        loss = loss.add(&on_negative.mul(&negatives)?.sum_all()?.affine(0.5 / f64::from(negatives_n), 0.0)?)?;
    }
    Ok(loss)
}

/// The position pointer's target under `flow.pointer_target = "relational"`: the point p* whose
/// relation lands on the keyframe position `target` [B, 3], p* + beta (p* - g) = target, so
/// p* = (target + beta g) / (1 + beta), with the model's `beta` [B, 1] and instruction-pointer
/// position `goal` [B, 3] (all normalised), not differentiated. beta is clamped to
/// [`RELATIONAL_BETA_RANGE`] so that 1 + beta stays away from 0.
pub fn relational_pointer_target(target: &Tensor, beta: &Tensor, goal: &Tensor) -> Result<Tensor> {
    let b = target.dim(0)?;
    if target.dims() != [b, 3] || beta.dims() != [b, 1] || goal.dims() != [b, 3] {
        return Err(PolicyError::Invalid(format!(
            "relational_pointer_target: target {:?}, beta {:?} and goal {:?} must be [B, 3], [B, 1], [B, 3]",
            target.dims(),
            beta.dims(),
            goal.dims()
        )));
    }
    let (lo, hi) = RELATIONAL_BETA_RANGE;
    let beta = beta.detach().clamp(lo, hi)?;
    let numerator = target.add(&goal.detach().broadcast_mul(&beta)?)?;
    Ok(numerator.broadcast_div(&beta.affine(1.0, 1.0)?)?)
}

/// The range beta is clamped to in [`relational_pointer_target`].
pub const RELATIONAL_BETA_RANGE: (f32, f32) = (-0.5, 4.0);

/// Euler integration of the learned velocity field from noise to an action
/// (Algorithm 2, accumulating): `a <- a + v(a, k/K) / K` for `k = 0..K`.
///
/// `a0`: `[B, D]` source noise; `steps` = K >= 1; `velocity(a, t)` returns
/// `[B, D]` at the current state `a` and flow time `t = k/K` (so t runs over
/// 0, 1/K, ..., (K-1)/K and never reaches 1). Returns the final `a`.
pub fn euler_sample<F>(a0: Tensor, steps: usize, mut velocity: F) -> Result<Tensor>
where
    F: FnMut(&Tensor, f32) -> Result<Tensor>,
{
    if steps == 0 {
        return Err(PolicyError::Invalid("euler_sample: steps must be at least 1 (the paper uses 2..50)".into()));
    }
    let dt = 1.0 / steps as f64;
    let mut a = a0;
    for k in 0..steps {
        let t = k as f32 / steps as f32;
        let v = velocity(&a, t)?;
        if v.dims() != a.dims() {
            return Err(PolicyError::Invalid(format!(
                "euler_sample: the velocity at step {k} has shape {:?}, expected the action's {:?}",
                v.dims(),
                a.dims()
            )));
        }
        let step = v.to_dtype(a.dtype())?.affine(dt, 0.0)?;
        a = (a + step)?;
    }
    Ok(a)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn t2(values: &[f32], rows: usize) -> Tensor {
        Tensor::from_slice(values, (rows, values.len() / rows), &Device::Cpu).unwrap()
    }

    #[test]
    fn a_zero_scale_on_z_measures_the_pointer_target_horizontally() {
        // Candidates (normalised, 0.3 m per unit): 0 straight under the target 24 cm below, 1
        // beside it at its height 15 cm away, 2 far away. In 3-D the one beside it is the
        // target; horizontally the one under it.
        let d = Device::Cpu;
        let candidates = Tensor::new(&[[[0.0f32, 0.0, -0.8], [0.5, 0.0, 0.0], [0.9, 0.9, 0.0]]], &d).unwrap();
        let target = Tensor::new(&[[0.0f32, 0.0, 0.0]], &d).unwrap();
        let loss = |on: usize, extent: [f32; 3]| {
            let mut logits = [-20.0f32; 3];
            logits[on] = 20.0;
            let log_weights = candle_nn::ops::log_softmax(&Tensor::new(&[logits], &d).unwrap(), 1).unwrap();
            pointer_loss(&log_weights, &candidates, &target, extent, 0.02).unwrap().to_scalar::<f32>().unwrap()
        };
        let (all, horizontal) = ([0.3f32, 0.3, 0.3], [0.3f32, 0.3, 0.0]);
        assert!(loss(1, all) < 0.01 && loss(0, all) > 1.0, "3-D: {} {}", loss(1, all), loss(0, all));
        assert!(
            loss(0, horizontal) < 0.01 && loss(1, horizontal) > 1.0,
            "{} {}",
            loss(0, horizontal),
            loss(1, horizontal)
        );
        assert!([0, 1, 2].iter().all(|&i| loss(i, horizontal).is_finite()));
    }

    #[test]
    fn grounding_labels_mark_the_tokens_under_every_later_keyframe_and_only_those() {
        // 0.3 m per normalised unit: candidates 0, 1.5, 6 and 30 cm (in x) from the first later
        // keyframe, and one 50 cm above the second (horizontal distance 0).
        let candidates = [[0.0f32, 0.0, 0.0], [0.05, 0.0, 0.0], [0.2, 0.0, 0.0], [1.0, 0.0, 0.0], [-0.5, 0.5, -0.9]];
        let later = [[0.0f32, 0.0, 0.3], [-0.5, 0.5, 0.8]];
        assert_eq!(grounding_labels(&candidates, &later, [0.3; 3], 0.03), vec![1.0, 1.0, 0.0, 0.0, 1.0]);
        assert_eq!(grounding_labels(&candidates, &[], [0.3; 3], 0.03), vec![0.0; 5]);
    }

    #[test]
    fn the_grounding_loss_balances_the_classes_and_falls_as_the_scores_separate_them() {
        // One positive among four tokens.
        let labels = t2(&[1.0, 0.0, 0.0, 0.0], 1);
        let loss = |s: [f32; 4]| grounding_loss(&t2(&s, 1), &labels).unwrap().to_scalar::<f32>().unwrap();
        // All scores 0: each class's mean loss is ln 2, halved and summed: ln 2.
        assert!((loss([0.0; 4]) - std::f32::consts::LN_2).abs() < 1e-6, "{}", loss([0.0; 4]));
        // The positive up and the negatives down lowers it; the reverse raises it.
        assert!(loss([4.0, -4.0, -4.0, -4.0]) < 0.02);
        assert!(loss([-4.0, 4.0, 4.0, 4.0]) > 3.9);
        // Balanced: the one positive at -4 costs as much as the three negatives at +4 together.
        let (pos, neg) = (loss([-4.0, -4.0, -4.0, -4.0]), loss([4.0, 4.0, 4.0, 4.0]));
        assert!((pos - neg).abs() < 1e-5, "{pos} {neg}");
        // A batch without positives: only the negatives' half, and finite at large scores.
        let none = grounding_loss(&t2(&[50.0, -50.0], 1), &t2(&[0.0, 0.0], 1)).unwrap().to_scalar::<f32>().unwrap();
        assert!((none - 12.5).abs() < 1e-3, "{none}");
        // The gradient at s = 0: -1/2 sigmoid(0) / 1 on the positive, +1/2 sigmoid(0) / 1 on the negative.
        let s = Var::from_tensor(&t2(&[0.0, 0.0], 1)).unwrap();
        let grads = grounding_loss(s.as_tensor(), &t2(&[1.0, 0.0], 1)).unwrap().backward().unwrap();
        let g = grads.get(s.as_tensor()).unwrap().to_vec2::<f32>().unwrap();
        assert!((g[0][0] + 0.25).abs() < 1e-6 && (g[0][1] - 0.25).abs() < 1e-6, "{g:?}");
        let wrong = grounding_loss(&t2(&[0.0; 4], 1), &t2(&[0.0; 2], 1));
        assert!(wrong.unwrap_err().to_string().contains("grounding_loss"));
    }

    #[test]
    fn the_relational_pointer_target_is_the_point_whose_relation_lands_on_the_keyframe() {
        let d = Device::Cpu;
        let target = Tensor::new(&[[0.1f32, -0.2, 0.3], [0.5, 0.5, 0.5]], &d).unwrap();
        let goal = Tensor::new(&[[0.4f32, 0.2, -0.1], [0.0, 0.0, 0.0]], &d).unwrap();
        let beta = Tensor::new(&[[0.5f32], [0.0]], &d).unwrap();
        let p = relational_pointer_target(&target, &beta, &goal).unwrap();
        // p + beta (p - g) recovers the target; beta = 0 leaves it as it was.
        let back = p.add(&p.sub(&goal).unwrap().broadcast_mul(&beta).unwrap()).unwrap();
        let (back, target) = (back.to_vec2::<f32>().unwrap(), target.to_vec2::<f32>().unwrap());
        for (r, t) in back.iter().flatten().zip(target.iter().flatten()) {
            assert!((r - t).abs() < 1e-6, "{r} against {t}");
        }
        assert_eq!(p.to_vec2::<f32>().unwrap()[1], vec![0.5, 0.5, 0.5]);
        // beta near -1 is clamped: the target stays finite.
        let near = Tensor::new(&[[-0.999f32], [-3.0]], &d).unwrap();
        let p =
            relational_pointer_target(&Tensor::new(&[[0.1f32, 0.1, 0.1], [0.1, 0.1, 0.1]], &d).unwrap(), &near, &goal);
        assert!(p.unwrap().to_vec2::<f32>().unwrap().iter().flatten().all(|v| v.is_finite() && v.abs() < 2.0));
        let wrong = relational_pointer_target(&goal, &goal, &goal);
        assert!(wrong.unwrap_err().to_string().contains("relational_pointer_target"));
    }

    #[test]
    fn the_pointer_loss_rewards_attention_on_the_candidates_near_the_keyframe() {
        let d = Device::Cpu;
        // Two samples, three candidates: (0, 0, 0), (0.1, 0, 0) and (1, 0, 0) normalised; 0.3 m per
        // unit, so they are 0, 3 and 30 cm from a keyframe at the origin.
        let candidates = Tensor::from_slice(&[0f32, 0., 0., 0.1, 0., 0., 1., 0., 0.], (1, 3, 3), &d)
            .unwrap()
            .repeat((2, 1, 1))
            .unwrap();
        let target = Tensor::zeros((2, 3), DType::F32, &d).unwrap();
        let loss = |weights: [f32; 3]| -> f32 {
            let log = Tensor::from_slice(&weights, (1, 3), &d).unwrap().log().unwrap().repeat((2, 1)).unwrap();
            pointer_loss(&log, &candidates, &target, [0.3; 3], 0.02).unwrap().to_scalar::<f32>().unwrap()
        };
        let (near, next, far) = (loss([0.98, 0.01, 0.01]), loss([0.01, 0.98, 0.01]), loss([0.01, 0.01, 0.98]));
        assert!(near < next && next < far, "near {near}, next {next}, far {far}");
        // The soft target: weights 1 : e^(-9/8) : e^(-112.5) on the three (d^2 / (2 sigma^2) =
        // 0, 0.03^2 / 0.0008, 0.3^2 / 0.0008), so 75.5 % / 24.5 % / 0.
        let p1 = (-1.125f32).exp() / (1.0 + (-1.125f32).exp());
        let expected = -((1.0 - p1) * 0.98f32.ln() + p1 * 0.01f32.ln());
        assert!((near - expected).abs() < 1e-4, "{near} vs {expected}");
        let wrong = pointer_loss(&Tensor::zeros((2, 4), DType::F32, &d).unwrap(), &candidates, &target, [0.3; 3], 0.02);
        assert!(wrong.unwrap_err().to_string().contains("pointer_loss"));
    }

    fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    #[test]
    fn interpolate_and_target_follow_the_straight_path() {
        let a0 = t2(&[0.0, 1.0, 2.0, 4.0], 2);
        let a1 = t2(&[2.0, 3.0, -2.0, 0.0], 2);
        let t = Tensor::new(&[0.25f32, 1.0], &Device::Cpu).unwrap();
        let a_t = interpolate(&a0, &a1, &t).unwrap();
        assert_eq!(a_t.to_vec2::<f32>().unwrap(), vec![vec![0.5, 1.5], vec![-2.0, 0.0]]);
        let u = target_velocity(&a0, &a1).unwrap();
        assert_eq!(u.to_vec2::<f32>().unwrap(), vec![vec![2.0, 2.0], vec![-4.0, -4.0]]);
        // t = 0 gives the noise.
        let t0 = Tensor::zeros(2, DType::F32, &Device::Cpu).unwrap();
        assert_eq!(max_abs_diff(&interpolate(&a0, &a1, &t0).unwrap(), &a0), 0.0);
    }

    #[test]
    fn interpolate_rejects_wrong_time_shape() {
        let a = t2(&[0.0; 18], 2);
        let t = Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap();
        assert!(matches!(interpolate(&a, &a, &t), Err(PolicyError::Invalid(_))));
    }

    #[test]
    fn training_sample_is_consistent_and_reproducible() {
        let a1 = t2(&[0.3f32; 4 * ACTION_DIMS], 4);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let s = flow_training_sample(&a1, &mut rng, FlowTimeSampling::Uniform).unwrap();
        assert_eq!(s.a_t.dims(), &[4, ACTION_DIMS]);
        assert_eq!(s.t.dims(), &[4]);
        // a_t + (1 - t) * u == a1
        let one_minus_t = s.t.affine(-1.0, 1.0).unwrap().reshape((4, 1)).unwrap();
        let back = (&s.a_t + s.target_velocity.broadcast_mul(&one_minus_t).unwrap()).unwrap();
        assert!(max_abs_diff(&back, &a1) < 1e-5);
        let mut rng2 = ChaCha8Rng::seed_from_u64(7);
        let s2 = flow_training_sample(&a1, &mut rng2, FlowTimeSampling::Uniform).unwrap();
        assert_eq!(max_abs_diff(&s.a0, &s2.a0), 0.0);
    }

    #[test]
    fn flow_times_lie_in_unit_interval_and_noise_is_standard() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for sampling in [FlowTimeSampling::Uniform, FlowTimeSampling::LogitNormal { mean: 0.0, std: 1.0 }] {
            let t = sample_flow_times(&mut rng, 10_000, sampling).unwrap();
            assert!(t.iter().all(|&x| (0.0..1.0).contains(&x)));
            let mean = t.iter().map(|&x| x as f64).sum::<f64>() / t.len() as f64;
            assert!((mean - 0.5).abs() < 0.02, "{sampling:?} mean {mean}");
        }
        let bad = FlowTimeSampling::LogitNormal { mean: 0.0, std: -1.0 };
        assert!(sample_flow_times(&mut rng, 1, bad).is_err());
        let noise = sample_source_noise(&mut rng, 1000, ACTION_DIMS, &Device::Cpu).unwrap();
        let v: Vec<f32> = noise.flatten_all().unwrap().to_vec1().unwrap();
        let mean = v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64;
        let var = v.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / v.len() as f64;
        assert!(mean.abs() < 0.05 && (var - 1.0).abs() < 0.05, "mean {mean} var {var}");
    }

    #[test]
    fn loss_matches_hand_computation() {
        let v_pred = t2(&[1.0, 2.0, 3.0, 4.0], 2);
        let target = t2(&[0.0, 2.0, 3.0, 6.0], 2);
        let logit = Tensor::new(&[0.0f32, 2.0], &Device::Cpu).unwrap();
        let label = Tensor::new(&[1.0f32, 0.0], &Device::Cpu).unwrap();
        let (total, cfm, bce) = flow_matching_loss(&v_pred, &target, &logit, &label, &LossWeights::default()).unwrap();
        let cfm = cfm.to_scalar::<f32>().unwrap();
        let bce = bce.to_scalar::<f32>().unwrap();
        assert!((cfm - 5.0 / 4.0).abs() < 1e-6);
        let expected_bce = ((2f64).ln() + (1.0 + 2f64.exp()).ln()) / 2.0;
        assert!((bce as f64 - expected_bce).abs() < 1e-6, "{bce} vs {expected_bce}");
        let total = total.to_scalar::<f32>().unwrap();
        assert!((total as f64 - (100.0 * 1.25 + 10.0 * expected_bce)).abs() < 1e-4);
    }

    #[test]
    fn bce_is_stable_for_huge_logits_and_has_right_gradient() {
        let logits = Var::new(&[1000.0f32, -1000.0, 0.5], &Device::Cpu).unwrap();
        let labels = Tensor::new(&[0.0f32, 1.0, 1.0], &Device::Cpu).unwrap();
        let bce = bce_with_logits(logits.as_tensor(), &labels).unwrap();
        let value = bce.to_scalar::<f32>().unwrap();
        let expected = (1000.0 + 1000.0 + (1.0 + (-0.5f64).exp()).ln()) / 3.0;
        assert!(value.is_finite() && ((value as f64) - expected).abs() < 1e-3, "{value}");
        // d/dx mean BCE = (sigmoid(x) - y) / N.
        let grads = bce.backward().unwrap();
        let g: Vec<f32> = grads.get(&logits).unwrap().to_vec1().unwrap();
        let sig = 1.0 / (1.0 + (-0.5f32).exp());
        let expected = [1.0 / 3.0, -1.0 / 3.0, (sig - 1.0) / 3.0];
        for (a, b) in g.iter().zip(expected) {
            assert!((a - b).abs() < 1e-6, "{g:?}");
        }
    }

    #[test]
    fn euler_lands_on_target_for_the_conditional_straight_field() {
        let x1 = t2(&[0.5, -0.25, 0.9, 0.1, 0.0, -1.0, 0.3, 0.7, -0.6], 1);
        let a0 = t2(&[1.2, 0.4, -2.0, 0.3, 1.1, -0.4, 0.0, 2.2, -1.3], 1);
        for steps in [1usize, 2, 8, 32] {
            let mut calls = Vec::new();
            let out = euler_sample(a0.clone(), steps, |a, t| {
                calls.push(t);
                Ok(((&x1 - a)? / (1.0 - t as f64))?)
            })
            .unwrap();
            assert!(max_abs_diff(&out, &x1) < 1e-5, "steps {steps}");
            let expected: Vec<f32> = (0..steps).map(|k| k as f32 / steps as f32).collect();
            assert_eq!(calls, expected);
        }
    }

    #[test]
    fn endpoint_prediction_integrates_to_the_predicted_endpoint() {
        // A head that predicts the same endpoint at every step: the sampler lands on it exactly
        // (the last step covers the remaining 1 - t), for any number of steps and any noise.
        let endpoint = t2(&[0.5, -0.25, 0.9, 0.1, 0.0, -1.0, 0.3, 0.7, -0.6], 1);
        let a0 = t2(&[1.2, 0.4, -2.0, 0.3, 1.1, -0.4, 0.0, 2.2, -1.3], 1);
        for steps in [1usize, 2, 8, 16] {
            let out =
                euler_sample(a0.clone(), steps, |a, t| Prediction::Endpoint.velocity(endpoint.clone(), a, t)).unwrap();
            assert!(max_abs_diff(&out, &endpoint) < 1e-5, "steps {steps}");
        }
        // Velocity prediction passes the head's output through.
        let v = Prediction::Velocity.velocity(endpoint.clone(), &a0, 0.5).unwrap();
        assert_eq!(max_abs_diff(&v, &endpoint), 0.0);
        // The training targets: a1 - a0 for velocity, a1 for the endpoint.
        let a1 = t2(&[0.3f32; 2 * ACTION_DIMS], 2);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let s = flow_training_sample(&a1, &mut rng, FlowTimeSampling::Uniform).unwrap();
        assert_eq!(max_abs_diff(&Prediction::Velocity.target(&s, &a1), &s.target_velocity), 0.0);
        assert_eq!(max_abs_diff(&Prediction::Endpoint.target(&s, &a1), &a1), 0.0);
    }

    #[test]
    fn euler_with_constant_field_adds_it_once() {
        let a0 = t2(&[1.0, 2.0, 3.0], 1);
        let v = t2(&[0.5, -1.0, 4.0], 1);
        for steps in [1usize, 3, 50] {
            let out = euler_sample(a0.clone(), steps, |_, _| Ok(v.clone())).unwrap();
            let expected = (&a0 + &v).unwrap();
            assert!(max_abs_diff(&out, &expected) < 1e-5, "steps {steps}");
        }
    }

    #[test]
    fn euler_rejects_zero_steps_and_bad_velocity_shape() {
        let a0 = t2(&[1.0, 2.0], 1);
        assert!(matches!(euler_sample(a0.clone(), 0, |a, _| Ok(a.clone())), Err(PolicyError::Invalid(_))));
        let r = euler_sample(a0, 2, |_, _| Ok(t2(&[1.0, 2.0, 3.0], 1)));
        assert!(matches!(r, Err(PolicyError::Invalid(_))));
    }
}
