//! One episode of a task, closed loop: reset (seeded), the objects settle while the controller
//! holds the arm, then observe -> next keyframe -> execute through IK -> ruckig -> OSC at 1 kHz
//! on the simulated Panda (no teleporting), the task observing after each keyframe, until the
//! keyframes run out (expert), the task succeeds (learned policy) or the budget is spent.
//! Observations (RGB-D of the chosen cameras, proprioception) are taken at each keyframe for
//! datasets and for the policy.
use nalgebra::Isometry3;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use super::RolloutError;
use super::stack::build_runner;
use crate::control::backend::{Cycle, RobotBackend};
use crate::control::gripper::GraspState;
use crate::control::keyframe::Keyframe;
use crate::control::osc_config::OscConfig;
use crate::control::runner::Runner;
use crate::robot::JointVector;
use crate::sim::{CameraRig, RgbdFrame, Visuals, World};
use crate::tasks::{Task, TaskError, TaskState};

/// A task's episode: what reset chose, and what happened so far.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskEpisode {
    pub task: &'static str,
    pub variation: usize,
    pub instruction: String,
    pub seed: u64,
    /// Task-specific choices of the reset (object names, targets), and progress.
    pub state: TaskState,
}

/// A learned policy as an episode's actor: the next keyframe from what the cameras see.
pub trait KeyframePolicy {
    /// Keyframe `k` of the episode (world frame) for `instruction`, from `observation` (the
    /// observer's camera frames and the proprioception).
    fn next_keyframe(
        &mut self,
        instruction: &str,
        k: usize,
        observation: &KeyframeObservation,
    ) -> Result<Keyframe, RolloutError>;
}

/// Where an episode's keyframes come from.
pub enum Actor<'a> {
    /// The task's scripted expert (all its keyframes, computed at the start).
    Expert,
    /// The expert with recovery samples ([`Perturbation`]): some approach keyframes are first
    /// executed off target, and the observation there is recorded with the intended keyframe.
    PerturbedExpert(Perturbation),
    /// Nobody: the arm holds still for the given seconds (checks that success is not trivial).
    Idle { seconds: u32 },
    /// A learned policy, one keyframe per observation, until the task succeeds or
    /// `max_keyframes` were executed. Lock-step: the simulation waits for the policy
    /// (deterministic). Needs an observer with cameras.
    Policy { policy: &'a mut dyn KeyframePolicy, max_keyframes: usize },
}

/// Recovery samples in expert demonstrations (DART, Laskey et al. 2017, for keyframes): a
/// policy trained only on the expert's own states has never seen itself a few centimetres off,
/// and closed loop it soon is. Before an *approach* keyframe (one the next keyframe is at least
/// [`Perturbation::APPROACH_DROP_M`] below: above a handle, a cap, a block, the far side of a
/// block, a stack; always in free space), with chance `probability` the arm first goes to that
/// keyframe moved by a random offset (x and y ~ N(0, sigma), z ~ |N(0, sigma)| upward only, each
/// clipped to 2.5 sigma); the observation taken there joins the episode with the action
/// [`RecoveryTarget`] says, and the approach keyframe is then executed as usual. The expert's
/// plan is unchanged (nothing is touched on the detour), so the episode keeps its success
/// check. Offsets are drawn from the episode seed: a collection is reproducible.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Perturbation {
    /// Chance that an approach keyframe gets a detour, in [0, 1].
    pub probability: f64,
    /// Standard deviation of the offset per axis, m (> 0, at most 0.1).
    pub sigma_m: f64,
    /// The action of the observation taken on the detour (absent in manifests written before
    /// it existed: `approach`, what they did).
    #[serde(default)]
    pub target: RecoveryTarget,
    /// Chance that a *grasp* keyframe (one that closes the gripper right after an approach) is
    /// first executed missed, in [0, 1] (absent in manifests written before it existed: 0).
    /// The missed grasp closes the fingers on nothing, [`Perturbation::GRASP_MISS_M`] beside
    /// the intended pose across the fingers' closing direction; the observation there (the
    /// gripper closed and empty) joins the episode with the approach keyframe as its action
    /// (re-open above the object), the approach is executed, and the grasp is then tried again
    /// as planned. A policy that has seen no demonstration re-open never recovers from a
    /// missed grasp (`docs/experiments.md`, why stack_blocks fails). A missed grasp that is not
    /// reached or does not close on nothing (the fingers met a long object's end or a
    /// neighbour) makes the episode unsuccessful: a collection tries another seed.
    #[serde(default)]
    pub grasp_probability: f64,
    /// Detours per approach keyframe that gets one, at least 1 (absent in manifests written
    /// before it existed: 1). The first is drawn as described above; each further one is
    /// another offset around the same approach keyframe, from its own seeded stream (so a
    /// collection with more detours has the same first detours as one with one), executed
    /// from the detour before it, its observation given the same action. More of the samples
    /// then teach the step from near an approach pose to the keyframe after it, which closed
    /// loop is where slide_block's episodes fail (`docs/experiments.md`, session 25).
    #[serde(default = "Perturbation::one_detour")]
    pub detours: u32,
    /// Standard deviation of a turn about the vertical given to every detour, degrees (0, the
    /// default and what manifests written before it existed mean: none; at most
    /// [`Perturbation::MAX_YAW_SIGMA_DEG`]). The angle is clipped to 2.5 sigma and drawn from its
    /// own seeded stream, so a collection with turns has the same detour positions as one
    /// without. The detour's observation then shows the hand turned off the approach's yaw with
    /// the next keyframe's (the expert's) yaw as its action: the step down learns to correct the
    /// yaw from the close view, which an expert that never turns on the way down cannot teach
    /// (`docs/experiments.md`, session 29: stack_blocks' picks go down 10-30 deg off the faces).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub yaw_sigma_deg: f64,
    /// Take the task's targets in a random order (drawn from the episode seed, its own stream)
    /// instead of the expert's (false, the default and what manifests written before it existed
    /// mean). Only for tasks whose success accepts any order ([`Task::targets_interchangeable`]:
    /// stack_blocks). Its blocks' visible order (smallest y first) lets a policy pick "the next
    /// block along y" without reading the colour; in shuffled demonstrations only the colour
    /// (and not being stacked yet) tells the targets apart (`docs/experiments.md`, session 38).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub shuffle_targets: bool,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// The action recorded for an observation taken on a detour.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RecoveryTarget {
    /// The keyframe after the approach (the expert, from near the approach pose, goes on to
    /// where it was going): consistent with the clean sample at the approach pose.
    #[default]
    Next,
    /// The approach keyframe itself. Measured harmful (`docs/experiments.md`, arm R): near the
    /// approach pose it teaches "go to the approach pose", a fixed point the policy never
    /// leaves closed loop.
    Approach,
}

impl RecoveryTarget {
    /// Every target, with its name (as in manifests and `collect --perturb-target`).
    pub const NAMES: [(&'static str, RecoveryTarget); 2] = [("next", Self::Next), ("approach", Self::Approach)];

    pub fn name(self) -> &'static str {
        match self {
            Self::Next => "next",
            Self::Approach => "approach",
        }
    }

    /// The target called `name`, if any.
    pub fn named(name: &str) -> Option<Self> {
        Self::NAMES.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
    }
}

impl Perturbation {
    /// How far below an approach keyframe its successor is, at least (m).
    pub const APPROACH_DROP_M: f64 = 0.04;
    /// The offsets' clip, in standard deviations.
    const CLIP: f64 = 2.5;
    /// Mixed into the episode seed for the offsets' RNG (independent of the reset's draws).
    const SEED_SALT: u64 = 0x5eed_da27;
    /// How far beside the intended grasp pose a missed grasp closes (m, along the hand's x axis,
    /// across the fingers' closing direction: the fingers close next to a 4 cm block).
    pub const GRASP_MISS_M: std::ops::RangeInclusive<f64> = 0.045..=0.055;
    /// Mixed into the episode seed for the missed grasps' RNG (its own stream, so adding them
    /// leaves the approach detours of a collection as they were).
    const GRASP_SEED_SALT: u64 = 0x9a5b_0f75;
    /// Mixed into the episode seed for the further detours' RNG ([`Perturbation::detours`]).
    const EXTRA_DETOUR_SEED_SALT: u64 = 0xde70_0a25;
    /// The most detours per approach keyframe.
    pub const MAX_DETOURS: u32 = 8;
    /// The largest turn's standard deviation (deg): 2.5 sigma stays under 45 deg, where a
    /// cube's nearest faces change.
    pub const MAX_YAW_SIGMA_DEG: f64 = 17.5;
    /// Mixed into the episode seed for the detours' turns' RNG.
    const YAW_SEED_SALT: u64 = 0x7a11_7e5d;
    /// Mixed into the episode seed for the targets' order ([`Perturbation::shuffle_targets`]).
    const ORDER_SEED_SALT: u64 = 0x0dde_5a1f;

    fn one_detour() -> u32 {
        1
    }

    /// Checks the ranges; the error says what is expected.
    pub fn validate(&self) -> Result<(), String> {
        if !(0.0..=1.0).contains(&self.probability) {
            return Err(format!("the perturbation probability is {}; expected a value in [0, 1]", self.probability));
        }
        if !(0.0..=1.0).contains(&self.grasp_probability) {
            return Err(format!(
                "the missed-grasp probability is {}; expected a value in [0, 1]",
                self.grasp_probability
            ));
        }
        if !(self.sigma_m > 0.0 && self.sigma_m <= 0.1) {
            return Err(format!(
                "the perturbation sigma is {} m; expected more than 0 and at most 0.1 m (a few centimetres)",
                self.sigma_m
            ));
        }
        if !(0.0..=Self::MAX_YAW_SIGMA_DEG).contains(&self.yaw_sigma_deg) {
            return Err(format!(
                "the detours' turn sigma is {} deg; expected 0 (no turn) to {} deg",
                self.yaw_sigma_deg,
                Self::MAX_YAW_SIGMA_DEG
            ));
        }
        if !(1..=Self::MAX_DETOURS).contains(&self.detours) {
            return Err(format!(
                "the detours per approach keyframe are {}; expected 1 to {}",
                self.detours,
                Self::MAX_DETOURS
            ));
        }
        Ok(())
    }

    /// [`Perturbation::validate`], and whether `task` accepts what it asks of it (a shuffled
    /// order only where the task's success accepts any order).
    pub fn validate_for(&self, task: &dyn Task) -> Result<(), String> {
        self.validate()?;
        if self.shuffle_targets && !task.targets_interchangeable() {
            return Err(format!(
                "{}'s targets must be taken in the expert's order (its success depends on it); \
                 collect it without --shuffle-targets",
                task.name()
            ));
        }
        Ok(())
    }

    /// Whether keyframe `k` of `plan` is an approach keyframe.
    pub fn is_approach(plan: &[Keyframe], k: usize) -> bool {
        matches!((plan.get(k), plan.get(k + 1)), (Some(a), Some(b)) if a.position[2] - b.position[2] >= Self::APPROACH_DROP_M)
    }

    /// Whether keyframe `k` of `plan` is a grasp keyframe: it closes the gripper right after
    /// an open approach keyframe.
    pub fn is_grasp(plan: &[Keyframe], k: usize) -> bool {
        k >= 1 && Self::is_approach(plan, k - 1) && plan[k - 1].gripper_open && !plan[k].gripper_open
    }

    /// The missed version of grasp keyframe `k` of `plan`, if it gets one (draws from `rng` for
    /// every grasp keyframe): the same pose moved by [`Self::GRASP_MISS_M`] along the hand's x
    /// axis (either way), in the horizontal plane. Grasps whose x axis is far from horizontal
    /// (a horizontal hand) get none.
    fn missed_grasp(&self, plan: &[Keyframe], k: usize, rng: &mut StdRng) -> Option<Keyframe> {
        if !Self::is_grasp(plan, k) {
            return None;
        }
        let go = rng.random::<f64>() < self.grasp_probability;
        let side = if rng.random::<bool>() { 1.0 } else { -1.0 };
        let distance = rng.random_range(Self::GRASP_MISS_M);
        let [w, x, y, z] = plan[k].quat_wxyz;
        let hand_x =
            nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z)) * nalgebra::Vector3::x();
        let across = nalgebra::Vector2::new(hand_x.x, hand_x.y);
        let norm = across.norm();
        (go && norm > 0.7).then(|| {
            let mut missed = plan[k];
            missed.position[0] += side * distance * across.x / norm;
            missed.position[1] += side * distance * across.y / norm;
            missed
        })
    }

    /// The detour before keyframe `k` of `plan`, if it gets one (draws from `rng` for every
    /// approach keyframe, so each episode's draws depend only on its seed and plan).
    fn detour(&self, plan: &[Keyframe], k: usize, rng: &mut StdRng) -> Option<Keyframe> {
        if !Self::is_approach(plan, k) {
            return None;
        }
        let go = rng.random::<f64>() < self.probability;
        let detour = self.offset(&plan[k], rng);
        go.then_some(detour)
    }

    /// `detour` turned about the world's vertical by N(0, yaw sigma) clipped to 2.5 sigma (no
    /// draw and no turn when the sigma is 0).
    fn turn(&self, detour: Keyframe, rng: &mut StdRng) -> Keyframe {
        if self.yaw_sigma_deg == 0.0 {
            return detour;
        }
        let angle =
            crate::policy::flow::standard_normal(rng).clamp(-Self::CLIP, Self::CLIP) * self.yaw_sigma_deg.to_radians();
        let [w, x, y, z] = detour.quat_wxyz;
        let q = nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, angle)
            * nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
        let q = q.quaternion();
        Keyframe { quat_wxyz: [q.w, q.i, q.j, q.k], ..detour }
    }

    /// `approach` moved by a random offset (x, y ~ N(0, sigma), z ~ |N(0, sigma)| upward, each
    /// clipped to [`Self::CLIP`] sigma).
    fn offset(&self, approach: &Keyframe, rng: &mut StdRng) -> Keyframe {
        let clip = |v: f64| v.clamp(-Self::CLIP, Self::CLIP) * self.sigma_m;
        let offset = [
            clip(crate::policy::flow::standard_normal(rng)),
            clip(crate::policy::flow::standard_normal(rng)),
            clip(crate::policy::flow::standard_normal(rng)).abs(),
        ];
        let mut detour = *approach;
        for (p, o) in detour.position.iter_mut().zip(offset) {
            *p += o;
        }
        detour
    }
}

/// The state at one keyframe: images (if cameras were given) and the TCP pose + gripper.
#[derive(Debug, Clone)]
pub struct KeyframeObservation {
    pub frames: Vec<RgbdFrame>,
    /// TCP position (world, m), quaternion w, x, y, z, gripper open (1/0).
    pub proprio: [f32; 8],
}

/// How an episode went.
#[derive(Debug, Clone)]
pub struct EpisodeResult {
    pub episode: TaskEpisode,
    pub success: bool,
    /// Keyframes executed, and how many the controller reached to tolerance.
    pub keyframes: usize,
    pub reached: usize,
    pub sim_seconds: f64,
    /// One observation before each keyframe (k = 0 is the initial state).
    pub observations: Vec<KeyframeObservation>,
    /// The keyframe executed from each observation (world frame), as `proprio`.
    pub actions: Vec<[f32; 8]>,
    /// Where the TCP actually was after each keyframe (world frame), as `proprio`.
    pub reached_poses: Vec<[f32; 8]>,
    /// Why keyframes were not reached (keyframe index, reason). Unreachable predictions of a
    /// learned policy are recorded here, not returned as errors.
    pub problems: Vec<(usize, String)>,
}

/// Which cameras to observe at each keyframe (indices into the rig's cameras).
pub struct Observer<'a> {
    pub rig: &'a mut CameraRig,
    pub cameras: Vec<usize>,
}

/// A camera rig for `world` (square images of `size` pixels, the arm drawn as `visuals`) and
/// the indices of the cameras named `cameras` in it, in that order.
pub fn camera_rig(
    world: &World,
    size: usize,
    visuals: Visuals,
    cameras: &[impl AsRef<str>],
) -> Result<(CameraRig, Vec<usize>), RolloutError> {
    let rig = CameraRig::new(world, size, visuals)?;
    let indices = cameras.iter().map(|c| rig.camera_index(c.as_ref())).collect::<Result<Vec<_>, _>>()?;
    Ok((rig, indices))
}

/// Settling time after reset, before the first keyframe (objects come to rest).
const SETTLE_S: f64 = 0.3;

/// Resets the task (seeded) and runs one episode with `actor` choosing the keyframes, observing
/// with `observer`'s cameras before each keyframe (none: proprioception only).
pub fn run_episode(
    task: &dyn Task,
    world: &mut World,
    variation: usize,
    seed: u64,
    mut actor: Actor<'_>,
    mut observer: Option<&mut Observer<'_>>,
) -> Result<EpisodeResult, RolloutError> {
    if let Actor::Policy { max_keyframes, .. } = actor {
        if max_keyframes == 0 {
            return Err(RolloutError::Zero { what: "the keyframes per episode" });
        }
        if observer.as_ref().is_none_or(|o| o.cameras.is_empty()) {
            return Err(RolloutError::NoCameras);
        }
    }
    if let Actor::PerturbedExpert(p) = &actor {
        p.validate_for(task).map_err(|problem| RolloutError::Perturbation { problem })?;
    }
    let (mut state, mut runner, t0) = begin(task, world, variation, seed)?;
    if let Actor::PerturbedExpert(p) = &actor
        && p.shuffle_targets
    {
        state.targets.shuffle(&mut StdRng::seed_from_u64(seed ^ Perturbation::ORDER_SEED_SALT));
    }
    let base = world.base_pose();
    let instruction = task.instruction(variation);
    let (planned, budget) = match actor {
        Actor::Expert | Actor::PerturbedExpert(_) => {
            let planned = task.expert(world, &state)?;
            let budget = planned.len();
            (planned, budget)
        }
        Actor::Idle { .. } => (Vec::new(), 0),
        Actor::Policy { max_keyframes, .. } => (Vec::new(), max_keyframes),
    };
    let mut result = EpisodeResult {
        episode: TaskEpisode {
            task: task.name(),
            variation,
            instruction: instruction.clone(),
            seed,
            state: Default::default(),
        },
        success: false,
        keyframes: 0,
        reached: 0,
        sim_seconds: 0.0,
        observations: Vec::with_capacity(budget),
        actions: Vec::with_capacity(budget),
        reached_poses: Vec::with_capacity(budget),
        problems: Vec::new(),
    };
    let mut perturbation = match actor {
        Actor::PerturbedExpert(p) => Some((p, StdRng::seed_from_u64(seed ^ Perturbation::SEED_SALT))),
        _ => None,
    };
    let mut grasp_rng = StdRng::seed_from_u64(seed ^ Perturbation::GRASP_SEED_SALT);
    let mut extra_detour_rng = StdRng::seed_from_u64(seed ^ Perturbation::EXTRA_DETOUR_SEED_SALT);
    let mut yaw_rng = StdRng::seed_from_u64(seed ^ Perturbation::YAW_SEED_SALT);
    // A missed grasp that touched something: the episode is no demonstration (unsuccessful, so
    // a collection tries another seed).
    let mut spoiled = false;
    let mut gripper_open = true;
    for k in 0..budget {
        let mut observation = observe(world, observer.as_deref_mut(), gripper_open)?;
        let keyframe = match (&mut actor, planned.get(k)) {
            (Actor::Policy { policy, .. }, _) => policy.next_keyframe(&instruction, k, &observation)?,
            (_, Some(keyframe)) => *keyframe,
            (_, None) => break,
        };
        let mut action = keyframe;
        let missed = match &perturbation {
            Some((p, _)) if p.grasp_probability > 0.0 => p.missed_grasp(&planned, k, &mut grasp_rng),
            _ => None,
        };
        let grasp_missed = missed.is_some();
        if let Some(missed) = missed {
            // The grasp is this observation's action; the missed grasp is what runs. From the
            // closed, empty gripper the action is the approach keyframe (re-open above); then
            // the grasp is tried again from the approach as planned.
            let approach = planned[k - 1]; // a grasp follows an approach (`is_grasp`)
            result.observations.push(observation);
            result.actions.push(proprio_of(&keyframe));
            let (reached, grasp) = execute(task, world, &mut runner, &base, k, &missed, &mut state, &mut result)?;
            if !reached || grasp != Some(GraspState::Empty) {
                // Beside a long object (a handle's end, a neighbouring block) the fingers can
                // touch or hold it: not the closed, empty gripper this sample is meant to show.
                spoiled = true;
                result.problems.push((
                    k,
                    format!(
                        "the missed grasp was {} with the gripper {grasp:?}, not closed on nothing: not a demonstration",
                        if reached { "reached" } else { "not reached" }
                    ),
                ));
            }
            result.keyframes += 1;
            result.observations.push(observe(world, observer.as_deref_mut(), missed.gripper_open)?);
            result.actions.push(proprio_of(&approach));
            execute(task, world, &mut runner, &base, k, &approach, &mut state, &mut result)?;
            result.keyframes += 1;
            observation = observe(world, observer.as_deref_mut(), approach.gripper_open)?;
        }
        // Drawn at every approach keyframe whatever happens, so that the detours of a collection
        // do not depend on the missed grasps; no experts' grasp is also an approach, but if one
        // were, its missed grasp would stand for the detour.
        let detour = perturbation.as_mut().and_then(|(p, rng)| Some((*p, p.detour(&planned, k, rng)?)));
        if let Some((p, detour)) = detour.filter(|_| !grasp_missed) {
            let detour = p.turn(detour, &mut yaw_rng);
            // The intended keyframe is this observation's action, the detour is what runs.
            result.observations.push(observation);
            result.actions.push(proprio_of(&keyframe));
            execute(task, world, &mut runner, &base, k, &detour, &mut state, &mut result)?;
            result.keyframes += 1;
            observation = observe(world, observer.as_deref_mut(), detour.gripper_open)?;
            if p.target == RecoveryTarget::Next {
                // An approach keyframe has a successor (`is_approach`).
                action = planned.get(k + 1).copied().unwrap_or(keyframe);
            }
            // Further detours around the same approach, each observed with the same action.
            for _ in 1..p.detours {
                let further = p.turn(p.offset(&keyframe, &mut extra_detour_rng), &mut yaw_rng);
                result.observations.push(observation);
                result.actions.push(proprio_of(&action));
                execute(task, world, &mut runner, &base, k, &further, &mut state, &mut result)?;
                result.keyframes += 1;
                observation = observe(world, observer.as_deref_mut(), further.gripper_open)?;
            }
        }
        result.observations.push(observation);
        result.actions.push(proprio_of(&action));
        execute(task, world, &mut runner, &base, k, &keyframe, &mut state, &mut result)?;
        result.keyframes += 1;
        gripper_open = keyframe.gripper_open;
        if matches!(actor, Actor::Policy { .. }) && task.success(world, &state) {
            break;
        }
    }
    if let Actor::Idle { seconds } = actor {
        hold(world, &mut runner, f64::from(seconds))?;
        task.observe(world, &mut state)?;
    }
    result.success = !spoiled && task.success(world, &state);
    result.sim_seconds = world.time() - t0;
    result.episode.state = state;
    Ok(result)
}

/// Executes keyframe `k` (world frame) and records how it went (the caller records the action).
/// Returns whether it was reached and what the gripper did.
#[allow(clippy::too_many_arguments)]
fn execute(
    task: &dyn Task,
    world: &mut World,
    runner: &mut Runner,
    base: &Isometry3<f64>,
    k: usize,
    keyframe: &Keyframe,
    state: &mut TaskState,
    result: &mut EpisodeResult,
) -> Result<(bool, Option<GraspState>), RolloutError> {
    let report = runner.run(world, &[in_base(base, k, keyframe)?])?;
    let mut outcome = (false, None);
    for r in &report.keyframes {
        if r.reached {
            result.reached += 1;
        } else {
            result.problems.push((k, r.error.clone().unwrap_or_default()));
        }
        outcome = (r.reached, r.gripper);
    }
    task.observe(world, state)?;
    result.reached_poses.push(tcp_proprio(world, keyframe.gripper_open));
    Ok(outcome)
}

/// The expert's keyframes for `variation` at `seed`, planned from the settled start of that
/// episode and not executed (what `run_episode` with [`Actor::Expert`] goes to first).
/// Returns the plan with the settled scene's fingerprint ([`World::scene_fingerprint`]).
pub fn expert_plan(
    task: &dyn Task,
    world: &mut World,
    variation: usize,
    seed: u64,
) -> Result<(Vec<Keyframe>, Vec<f64>), RolloutError> {
    let (state, _, _) = begin(task, world, variation, seed)?;
    let fingerprint = world.scene_fingerprint();
    Ok((task.expert(world, &state)?, fingerprint))
}

/// The expert's plans in one scene toward the task's [`Task::target_alternatives`].
#[derive(Debug, Clone)]
pub struct AlternativePlans {
    pub own: Vec<Keyframe>,
    /// To objects the instruction also accepts.
    pub right: Vec<Vec<Keyframe>>,
    /// To objects it does not.
    pub wrong: Vec<Vec<Keyframe>>,
}

/// [`AlternativePlans`] in the scene of `variation` at `seed`, planned from the settled start,
/// not executed.
pub fn expert_alternative_plans(
    task: &dyn Task,
    world: &mut World,
    variation: usize,
    seed: u64,
) -> Result<AlternativePlans, RolloutError> {
    let (state, _, _) = begin(task, world, variation, seed)?;
    let alternatives = task.target_alternatives(&state);
    let plan = |s: &TaskState| task.expert(world, s);
    let right = alternatives.right.iter().map(plan).collect::<Result<_, _>>()?;
    let wrong = alternatives.wrong.iter().map(plan).collect::<Result<_, _>>()?;
    Ok(AlternativePlans { own: task.expert(world, &state)?, right, wrong })
}

/// Resets the world and the task (seeded), builds the control stack and lets the objects
/// settle while the controller holds the arm. Returns the task state, the runner and the start
/// time.
pub(super) fn begin(
    task: &dyn Task,
    world: &mut World,
    variation: usize,
    seed: u64,
) -> Result<(TaskState, Runner, f64), RolloutError> {
    if variation >= task.variation_count() {
        return Err(TaskError::BadVariation { task: task.name(), variation, max: task.variation_count() - 1 }.into());
    }
    world.reset_to("home")?;
    let mut rng = StdRng::seed_from_u64(seed);
    let state = task.reset(world, variation, &mut rng)?;
    let mut runner = build_runner(world, OscConfig::default_profile()?)?;
    let t0 = world.time();
    hold(world, &mut runner, SETTLE_S)?;
    Ok((state, runner, t0))
}

/// Holds the arm where it is for `seconds`.
fn hold(world: &mut World, runner: &mut Runner, seconds: f64) -> Result<(), RolloutError> {
    let q: JointVector = world.read_state().q;
    runner.controller.set_goal(&q);
    let end = world.time() + seconds;
    world.control(|state| {
        let command = runner.controller.tick(state);
        if state.time >= end { Cycle::Finish(command) } else { Cycle::Continue(command) }
    })?;
    Ok(())
}

/// Keyframe `k` (world frame) in the arm's base frame.
fn in_base(base: &Isometry3<f64>, k: usize, keyframe: &Keyframe) -> Result<Keyframe, RolloutError> {
    let pose = crate::control::ik::target_pose(keyframe.position, keyframe.quat_wxyz)
        .map_err(|source| RolloutError::InvalidKeyframe { index: k, source })?;
    Ok(Keyframe::at(&(base.inverse() * pose), keyframe.gripper_open))
}

/// A keyframe in the dataset layout of `proprio`: position, quaternion w x y z, gripper open.
pub(super) fn proprio_of(k: &Keyframe) -> [f32; 8] {
    let (p, q) = (k.position, k.quat_wxyz);
    [p[0], p[1], p[2], q[0], q[1], q[2], q[3], if k.gripper_open { 1.0 } else { 0.0 }].map(|v| v as f32)
}

/// The TCP pose now (world frame) and the gripper state, in the layout of `proprio`.
pub(super) fn tcp_proprio(world: &World, gripper_open: bool) -> [f32; 8] {
    proprio_of(&Keyframe::at(&world.tcp_pose(), gripper_open))
}

/// The observation before a keyframe: the observer's camera frames (none without an observer)
/// and the proprioception.
pub(super) fn observe(
    world: &mut World,
    cameras: Option<&mut Observer<'_>>,
    gripper_open: bool,
) -> Result<KeyframeObservation, RolloutError> {
    let mut frames = Vec::new();
    if let Some(o) = cameras {
        for &i in &o.cameras {
            frames.push(o.rig.render(world, i)?);
        }
    }
    Ok(KeyframeObservation { frames, proprio: tcp_proprio(world, gripper_open) })
}

impl EpisodeResult {
    /// The episode as a dataset record (needs observations with images).
    pub fn to_dataset_episode(&self) -> Option<crate::data::Episode> {
        let first = self.observations.first()?;
        let cameras: Vec<String> = first.frames.iter().map(|f| f.camera.clone()).collect();
        if cameras.is_empty() {
            return None;
        }
        let (h, w) = (first.frames[0].intrinsics.height, first.frames[0].intrinsics.width);
        let mut e = crate::data::Episode {
            task: self.episode.task.to_string(),
            variation: self.episode.variation,
            instruction: self.episode.instruction.clone(),
            seed: self.episode.seed,
            cameras,
            success: self.success,
            height: h,
            width: w,
            rgb: Vec::new(),
            depth: Vec::new(),
            intrinsics: first
                .frames
                .iter()
                .flat_map(|f| f.intrinsics.matrix().transpose().iter().map(|&v| v as f32).collect::<Vec<_>>())
                .collect(),
            extrinsics: Vec::new(),
            proprio: self.observations.iter().flat_map(|o| o.proprio).collect(),
            action: self.actions.iter().flatten().copied().collect(),
        };
        for o in &self.observations {
            for f in &o.frames {
                e.rgb.extend_from_slice(&f.rgb);
                e.depth.extend_from_slice(&f.depth);
                // Row-major 4x4 (nalgebra stores column-major: transpose).
                e.extrinsics.extend(f.extrinsics.to_homogeneous().transpose().iter().map(|&v| v as f32));
            }
        }
        Some(e)
    }
}
