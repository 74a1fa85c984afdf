//! Evaluations of a trained policy:
//! - closed-loop success rates on held-out seeds of tasks ([`success_rates`]), recorded per
//!   episode in a [`SuccessRecord`] that a sharded evaluation writes, resumes and merges
//!   ([`merge_success_records`]);
//! - held-out keyframe errors (position, rotation, gripper) against two trivial baselines,
//!   always the training set's mean keyframe and always the mean keyframe of the same task
//!   ([`heldout_errors`]).
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::RolloutError;
use super::episode::{Actor, Observer, camera_rig, expert_alternative_plans, expert_plan, run_episode};
use super::learned::FlowRamActor;
use super::shard::{Shard, check_shard_set, source_revision};
use crate::control::keyframe::Keyframe;
use crate::data::{DataError, Episode};
use crate::files::write_atomic;
use crate::policy::checkpoint::format::weights_digest;
use crate::policy::config::Consensus;
use crate::policy::inference::{Policy, SamplingOptions};
use crate::policy::scene::observation::{KeyframePose, Observation};
use crate::policy::scene::rotation::{quaternion_from_6d, quaternion_to_6d};
use crate::policy::training::data::TrainingData;
use crate::sim::Visuals;
use crate::stats::{median, wilson_interval};
use crate::tasks::{self, Task};

/// Progress of an evaluation, for a progress bar: `done` of `total` items of `group` (a task).
pub trait EvaluationProgress {
    fn started(&mut self, group: &str, total: usize);
    fn advanced(&mut self, done: usize);
    fn finished(&mut self);
}

/// No progress report.
impl EvaluationProgress for () {
    fn started(&mut self, _: &str, _: usize) {}
    fn advanced(&mut self, _: usize) {}
    fn finished(&mut self) {}
}

/// How the closed-loop episodes of [`success_rates`] run.
#[derive(Debug, Clone)]
pub struct SuccessOptions {
    /// Episodes per task.
    pub episodes: usize,
    /// Seed of the first episode (episode i: seed + i, variation = seed modulo variations).
    pub seed: u64,
    /// Stop after this many predicted keyframes if the task has not succeeded.
    pub max_keyframes: usize,
    /// Cameras the policy sees, in the training datasets' order.
    pub cameras: Vec<String>,
    /// The episodes this process runs: episode i of every task when the shard owns i.
    pub shard: Shard,
}

/// Closed-loop success of one task.
#[derive(Debug, Clone, Serialize)]
pub struct TaskSuccess {
    pub task: String,
    pub episodes: usize,
    pub successes: usize,
    pub success_rate: f64,
    /// The 95 % Wilson interval of the success rate.
    pub success_ci95: [f64; 2],
    /// Mean predicted keyframes per episode.
    pub keyframes: f64,
    /// Fraction of predicted keyframes the controller reached (IK solvable, tracked to tolerance).
    pub reached: f64,
    /// Median over the episodes of each episode's median inference time (ms).
    pub inference_ms_median: f64,
    /// The seed of each episode and whether it succeeded, in seed order.
    pub outcomes: Vec<SeedOutcome>,
}

impl TaskSuccess {
    /// The table row of `task` from its episodes' outcomes (any order; sorted by seed here).
    pub fn from_outcomes(task: &str, outcomes: &[SeedOutcome]) -> Self {
        let mut outcomes = outcomes.to_vec();
        outcomes.sort_by_key(|o| o.seed);
        let n = outcomes.len();
        let successes = outcomes.iter().filter(|o| o.success).count();
        let keyframes: usize = outcomes.iter().map(|o| o.keyframes).sum();
        let reached: usize = outcomes.iter().map(|o| o.reached).sum();
        let inference: Vec<f64> = outcomes.iter().map(|o| o.inference_ms).collect();
        Self {
            task: task.into(),
            episodes: n,
            successes,
            success_rate: successes as f64 / n.max(1) as f64,
            success_ci95: wilson_interval(successes, n),
            keyframes: keyframes as f64 / n.max(1) as f64,
            reached: if keyframes > 0 { reached as f64 / keyframes as f64 } else { 0.0 },
            inference_ms_median: median(&inference),
            outcomes,
        }
    }
}

/// One closed-loop episode's result.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SeedOutcome {
    pub seed: u64,
    pub variation: usize,
    pub success: bool,
    /// Keyframes predicted, and how many of them the controller reached.
    pub keyframes: usize,
    pub reached: usize,
    /// Median wall-clock inference time of the episode's predictions (ms; timing, so it differs
    /// from run to run).
    pub inference_ms: f64,
}

/// Value of the `format` field of a results file.
pub const SUCCESS_FORMAT: &str = "flowram-success-v1";

/// One episode of one task, as a results file records it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RecordedOutcome {
    /// Index of the task in [`SuccessRecord::tasks`].
    pub task: usize,
    #[serde(flatten)]
    pub outcome: SeedOutcome,
}

/// The results file of `bench success --out` (one per shard): what was evaluated, how, by
/// which source revision, and every episode's outcome so far. A re-run with the same
/// arguments skips the episodes it holds; `flowram merge` combines the shards' files.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SuccessRecord {
    pub format: String,
    /// `git describe` of the source tree that ran it (a merge lists every shard's, comma-separated).
    pub revision: String,
    /// The checkpoint folder evaluated, and [`weights_digest`] of it.
    pub checkpoint: String,
    pub checkpoint_digest: String,
    pub tasks: Vec<String>,
    pub episodes: usize,
    pub seed: u64,
    pub max_keyframes: usize,
    /// Sampling: Euler steps, keyframe samples per observation (their consensus executed; absent
    /// in records from before there was a choice: 1) and DRS (true when the samples used the
    /// Dynamic Radius Schedule: `--no-drs` not given and the checkpoint trained with a dynamic
    /// schedule; records written before 2026-12-04 session 14 say true for a checkpoint trained
    /// with `kind = "global"` unless `--no-drs` was given).
    pub steps: usize,
    #[serde(default = "one_sample")]
    pub samples: usize,
    /// Which sample was executed (absent in records from before there was a choice: medoid).
    #[serde(default)]
    pub consensus: Consensus,
    /// The position pointer's temperature over the first Euler steps
    /// (`flow.pointer_sharpening`; 1, as trained, when absent).
    #[serde(default = "as_trained")]
    pub pointer_temperature: f64,
    /// The pointer as the posterior given the noisy position (`flow.pointer_sharpening.posterior`;
    /// false, as trained, when absent).
    #[serde(default)]
    pub pointer_posterior: bool,
    /// m, the posterior's candidate width (`flow.pointer_sharpening.posterior_width`; 0 when
    /// absent).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub pointer_posterior_width: f64,
    /// The instruction's guidance of the pointer (`flow.pointer_sharpening.guidance`; 1, as
    /// trained, when absent).
    #[serde(default = "as_trained", skip_serializing_if = "is_one")]
    pub pointer_guidance: f64,
    pub drs: bool,
    pub cameras: Vec<String>,
    /// Each task's expert version ([`Task::expert_version`]), in the order of `tasks`: a version
    /// fixes the scenes a seed makes (push_buttons' version 2 recoloured its buttons), so records
    /// of other versions hold other episodes. Absent in records from before 2026-12-07
    /// (session 35): unknown.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub expert_versions: Vec<u32>,
    pub shard: Shard,
    pub outcomes: Vec<RecordedOutcome>,
}

fn one_sample() -> usize {
    1
}

fn as_trained() -> f64 {
    1.0
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

fn is_one(x: &f64) -> bool {
    *x == 1.0
}

impl SuccessRecord {
    /// An empty record of `actor` evaluated on `task_list` with `options`.
    pub fn new(
        actor: &FlowRamActor,
        task_list: &[Box<dyn Task>],
        options: &SuccessOptions,
    ) -> Result<Self, RolloutError> {
        let (checkpoint, checkpoint_digest) = match &actor.policy.checkpoint {
            Some(dir) => (dir.display().to_string(), weights_digest(dir)?),
            None => ("random initialisation".into(), "random".into()),
        };
        Ok(Self {
            format: SUCCESS_FORMAT.into(),
            revision: source_revision(),
            checkpoint,
            checkpoint_digest,
            tasks: task_list.iter().map(|t| t.name().to_string()).collect(),
            episodes: options.episodes,
            seed: options.seed,
            max_keyframes: options.max_keyframes,
            steps: actor.options.steps,
            samples: actor.options.samples,
            consensus: actor.options.consensus,
            pointer_temperature: actor.options.sharpening.temperature,
            pointer_posterior: actor.options.sharpening.posterior,
            pointer_posterior_width: actor.options.sharpening.posterior_width,
            pointer_guidance: actor.options.sharpening.guidance,
            drs: actor.options.samples_with_drs(actor.policy.config().radius_schedule),
            cameras: options.cameras.clone(),
            expert_versions: task_list.iter().map(|t| t.expert_version()).collect(),
            shard: options.shard,
            outcomes: Vec::new(),
        })
    }

    /// The tasks' expert versions as text, for messages ("unknown" for records from before
    /// they were recorded).
    pub fn expert_versions_text(&self) -> String {
        if self.expert_versions.is_empty() {
            "unknown".into()
        } else {
            self.tasks.iter().zip(&self.expert_versions).map(|(t, v)| format!("{t} {v}")).collect::<Vec<_>>().join(", ")
        }
    }

    /// The same evaluation (all but the outcomes, the revision and the checkpoint's path)?
    fn same_evaluation(&self, other: &Self) -> Result<(), String> {
        let fields = |r: &Self| {
            format!(
                "checkpoint digest {}, tasks {:?}, episodes {}, seed {}, max keyframes {}, steps {}, samples {}, consensus {}, \
                 pointer temperature {}, pointer posterior {} (width {} m), pointer guidance {}, drs {}, cameras {:?}, \
                 expert versions {}",
                r.checkpoint_digest,
                r.tasks,
                r.episodes,
                r.seed,
                r.max_keyframes,
                r.steps,
                r.samples,
                r.consensus.name(),
                r.pointer_temperature,
                r.pointer_posterior,
                r.pointer_posterior_width,
                r.pointer_guidance,
                r.drs,
                r.cameras,
                r.expert_versions_text()
            )
        };
        let (a, b) = (fields(self), fields(other));
        if a == b { Ok(()) } else { Err(format!("{a} vs {b}")) }
    }

    fn outcome(&self, task: usize, seed: u64) -> Option<&SeedOutcome> {
        self.outcomes.iter().find(|o| o.task == task && o.outcome.seed == seed).map(|o| &o.outcome)
    }

    /// Whether every episode of the shard is recorded.
    pub fn complete(&self) -> bool {
        (0..self.tasks.len())
            .all(|t| self.shard.items(self.episodes).all(|i| self.outcome(t, self.seed + i as u64).is_some()))
    }

    /// The success table of the recorded outcomes, one row per task.
    pub fn table(&self) -> Vec<TaskSuccess> {
        (0..self.tasks.len())
            .map(|t| {
                let outcomes: Vec<SeedOutcome> =
                    self.outcomes.iter().filter(|o| o.task == t).map(|o| o.outcome).collect();
                TaskSuccess::from_outcomes(&self.tasks[t], &outcomes)
            })
            .collect()
    }

    /// Reads a results file; `None` when there is none.
    pub fn read(path: &Path) -> Result<Option<Self>, RolloutError> {
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read(path).map_err(|source| DataError::Read { path: path.to_path_buf(), source })?;
        let record: Self = serde_json::from_slice(&text)
            .map_err(|e| RolloutError::Manifest { path: path.to_path_buf(), problem: e.to_string() })?;
        if record.format != SUCCESS_FORMAT {
            return Err(RolloutError::Manifest {
                path: path.to_path_buf(),
                problem: format!("format is {:?}, expected {SUCCESS_FORMAT:?}", record.format),
            });
        }
        Ok(Some(record))
    }

    /// Writes the file atomically.
    pub fn write(&self, path: &Path) -> Result<(), RolloutError> {
        let json = serde_json::to_vec_pretty(self)
            .map_err(|e| RolloutError::Manifest { path: path.to_path_buf(), problem: e.to_string() })?;
        write_atomic(path, &json).map_err(|source| DataError::Write { path: path.to_path_buf(), source })?;
        Ok(())
    }

    /// Continues the results file at `path` if it holds this very evaluation (same checkpoint
    /// weights, tasks, seeds, sampling and shard): its outcomes are kept and those episodes are
    /// not run again. Any other file there is an error, never overwritten.
    pub fn resume_from(&mut self, path: &Path) -> Result<(), RolloutError> {
        let Some(found) = Self::read(path)? else { return Ok(()) };
        let describe = |r: &Self| format!("{} (shard {} of {})", r.checkpoint, r.shard.index, r.shard.count);
        if let Err(difference) = self.same_evaluation(&found) {
            return Err(RolloutError::OtherRun {
                dir: path.to_path_buf(),
                found: format!("{}: {difference}", describe(&found)),
                asked: describe(self),
            });
        }
        if found.shard != self.shard {
            return Err(RolloutError::OtherRun {
                dir: path.to_path_buf(),
                found: describe(&found),
                asked: describe(self),
            });
        }
        self.outcomes = found.outcomes;
        Ok(())
    }
}

/// Closed-loop success rates of `actor` on the held-out seeds of each task that
/// `options.shard` owns. Episodes already in `record` are not run again; each new outcome is
/// added to it and `save` is called with it (to write the results file after every episode, so
/// a killed shard loses at most the episode it was in). Returns the table of `record`.
pub fn success_rates(
    actor: &mut FlowRamActor,
    task_list: &[Box<dyn Task>],
    options: &SuccessOptions,
    record: &mut SuccessRecord,
    save: &mut dyn FnMut(&SuccessRecord) -> Result<(), RolloutError>,
    progress: &mut dyn EvaluationProgress,
) -> Result<Vec<TaskSuccess>, RolloutError> {
    if options.episodes == 0 {
        return Err(RolloutError::Zero { what: "the episodes per task" });
    }
    if options.max_keyframes == 0 {
        return Err(RolloutError::Zero { what: "the keyframes per episode" });
    }
    for (t, task) in task_list.iter().enumerate() {
        let mut world = tasks::load_world(task.as_ref())?;
        let size = actor.policy.config().observation.image_size;
        let (mut rig, cameras) = camera_rig(&world, size, Visuals::Full, &options.cameras)?;
        let owned: Vec<usize> = options.shard.items(options.episodes).collect();
        progress.started(task.name(), owned.len());
        for (done, i) in owned.into_iter().enumerate() {
            let seed = options.seed + i as u64;
            if record.outcome(t, seed).is_some() {
                progress.advanced(done + 1);
                continue;
            }
            let variation = seed as usize % task.variation_count();
            let mut observer = Observer { rig: &mut rig, cameras: cameras.clone() };
            actor.inference_ms.clear();
            let policy = Actor::Policy { policy: &mut *actor, max_keyframes: options.max_keyframes };
            let result = run_episode(task.as_ref(), &mut world, variation, seed, policy, Some(&mut observer))?;
            let outcome = SeedOutcome {
                seed,
                variation,
                success: result.success,
                keyframes: result.keyframes,
                reached: result.reached,
                inference_ms: median(&actor.inference_ms),
            };
            record.outcomes.push(RecordedOutcome { task: t, outcome });
            save(record)?;
            progress.advanced(done + 1);
        }
        progress.finished();
    }
    Ok(record.table())
}

/// Merges the results files of all shards of one evaluation: the merged record (shard
/// [`Shard::WHOLE`], outcomes in task and seed order) whose [`SuccessRecord::table`] is what
/// one unsharded run prints. Refuses files of different evaluations (checkpoint weights, tasks,
/// seeds, sampling, cameras, shard count), a missing or repeated shard, and an incomplete one.
pub fn merge_success_records(files: &[PathBuf]) -> Result<SuccessRecord, RolloutError> {
    let refuse = |problem: String| Err(RolloutError::Merge { problem });
    let mut records = Vec::with_capacity(files.len());
    for path in files {
        match SuccessRecord::read(path)? {
            Some(r) => records.push((path, r)),
            None => return refuse(format!("{} does not exist", path.display())),
        }
    }
    let Some((first_path, first)) = records.first() else { return refuse("no results files given".into()) };
    let set: Vec<(Shard, String)> = records.iter().map(|(p, r)| (r.shard, p.display().to_string())).collect();
    check_shard_set(&set).map_err(|problem| RolloutError::Merge { problem })?;
    let count = first.shard.count;
    for (path, r) in &records {
        if let Err(difference) = first.same_evaluation(r) {
            return refuse(format!(
                "{} and {} are shards of different evaluations: {difference}",
                first_path.display(),
                path.display()
            ));
        }
        if !r.complete() {
            return refuse(format!(
                "{} (shard {} of {count}) is incomplete: re-run its `flowram bench success` with the same arguments; it resumes",
                path.display(),
                r.shard.index
            ));
        }
    }
    let mut revisions: Vec<String> = records.iter().map(|(_, r)| r.revision.clone()).collect();
    revisions.sort();
    revisions.dedup();
    let mut outcomes: Vec<RecordedOutcome> = records.iter().flat_map(|(_, r)| r.outcomes.iter().copied()).collect();
    outcomes.sort_by_key(|o| (o.task, o.outcome.seed));
    Ok(SuccessRecord { revision: revisions.join(","), shard: Shard::WHOLE, outcomes, ..first.clone() })
}

/// Summary of keyframe errors.
#[derive(Debug, Clone, Serialize, Default)]
pub struct Errors {
    pub position_mm_mean: f64,
    pub position_mm_median: f64,
    pub rotation_deg_mean: f64,
    pub rotation_deg_median: f64,
    pub gripper_accuracy: f64,
    /// Mean signed position error, predicted minus expert, along the world axes (mm): a model
    /// that is precise but offset (a press that stops above the button) shows here, not in the
    /// error's magnitude.
    pub position_bias_mm: [f64; 3],
}

/// The errors of the model and the two baselines on the held-out keyframes of one task (or all).
#[derive(Debug, Clone, Serialize)]
pub struct HeldOutErrors {
    /// The task's name, or "all".
    pub task: String,
    pub keyframes: usize,
    pub model: Errors,
    /// Always the training set's mean keyframe.
    pub training_mean: Errors,
    /// Always the mean keyframe of the training episodes of the same task (the instruction names
    /// the task, so this is what a model that ignores the scene could reach).
    pub task_mean: Errors,
    /// The instruction probe: how far (mm, median) the predicted first keyframe moves when the
    /// instruction names another variation of the task (same observation, same noise seed).
    /// Every task here is a choice the instruction decides, so a model that reads it moves.
    pub instruction_swap_mm: f64,
    /// Observation / instruction pairs of the probe.
    pub instruction_swaps: usize,
    /// The target probe: of the held-out episodes' first keyframes that the instruction decides
    /// (the first keyframe where the expert of another variation, in the same scene, goes 3 cm
    /// or more elsewhere), the fraction predicted nearer the instructed variation's target than
    /// any such other target.
    pub target_accuracy: f64,
    /// Keyframes of the target probe.
    pub target_choices: usize,
}

/// Held-out keyframe errors, over all tasks and per task.
#[derive(Debug, Clone, Serialize)]
pub struct HeldOutReport {
    pub keyframes: usize,
    pub episodes: usize,
    pub steps: usize,
    /// Keyframe samples per observation; the scored keyframe is their consensus.
    pub samples: usize,
    pub consensus: Consensus,
    /// `flow.pointer_sharpening.temperature` (1: as trained).
    pub pointer_temperature: f64,
    /// `flow.pointer_sharpening.posterior` (false: as trained).
    pub pointer_posterior: bool,
    /// m, `flow.pointer_sharpening.posterior_width` (0: candidates are points).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub pointer_posterior_width: f64,
    /// `flow.pointer_sharpening.guidance` (1: as trained).
    #[serde(default = "as_trained", skip_serializing_if = "is_one")]
    pub pointer_guidance: f64,
    pub model: Errors,
    pub training_mean: Errors,
    pub task_mean: Errors,
    /// The instruction probe over all tasks (see [`HeldOutErrors::instruction_swap_mm`]).
    pub instruction_swap_mm: f64,
    pub instruction_swaps: usize,
    /// The target probe over all tasks (see [`HeldOutErrors::target_accuracy`]).
    pub target_accuracy: f64,
    pub target_choices: usize,
    /// The same per task.
    pub tasks: Vec<HeldOutErrors>,
    /// Every held-out keyframe the model predicted: tasks in name order, each task's episodes
    /// and keyframes in dataset order.
    pub per_keyframe: Vec<HeldOutKeyframe>,
    pub seconds: f64,
}

/// One held-out keyframe: where the expert went and where the model (the consensus keyframe)
/// predicted, world frame (m).
#[derive(Debug, Clone, Serialize)]
pub struct HeldOutKeyframe {
    pub task: String,
    pub variation: usize,
    pub seed: u64,
    /// The keyframe's index in its episode.
    pub keyframe: usize,
    pub expert_position: [f32; 3],
    pub predicted_position: [f32; 3],
    pub position_mm: f64,
    pub rotation_deg: f64,
    pub expert_gripper_open: bool,
    pub predicted_gripper_open: bool,
}

/// Position offset predicted - expert (m), rotation error (rad) and whether the gripper is right,
/// of one keyframe.
#[derive(Debug, Clone, Copy)]
struct KeyframeError {
    offset: [f32; 3],
    rotation: f32,
    gripper_right: bool,
}

impl KeyframeError {
    fn between(predicted: &KeyframePose, target: &KeyframePose) -> KeyframeError {
        KeyframeError {
            offset: std::array::from_fn(|i| predicted.position[i] - target.position[i]),
            rotation: predicted.error_to(target).1,
            gripper_right: predicted.gripper_open == target.gripper_open,
        }
    }

    /// The position error (mm).
    fn distance_mm(&self) -> f64 {
        self.offset.iter().map(|d| f64::from(*d).powi(2)).sum::<f64>().sqrt() * 1e3
    }
}

fn summarise(rows: &[KeyframeError]) -> Errors {
    let n = rows.len().max(1) as f64;
    let pos: Vec<f64> = rows.iter().map(KeyframeError::distance_mm).collect();
    let rot: Vec<f64> = rows.iter().map(|r| f64::from(r.rotation).to_degrees()).collect();
    Errors {
        position_mm_mean: pos.iter().sum::<f64>() / n,
        position_mm_median: median(&pos),
        rotation_deg_mean: rot.iter().sum::<f64>() / n,
        rotation_deg_median: median(&rot),
        gripper_accuracy: rows.iter().filter(|r| r.gripper_right).count() as f64 / n,
        position_bias_mm: std::array::from_fn(|i| rows.iter().map(|r| f64::from(r.offset[i])).sum::<f64>() * 1e3 / n),
    }
}

/// The mean keyframe of `episodes` (mean position, chordal-mean rotation, majority gripper);
/// `None` when they hold no keyframes.
pub fn mean_keyframe<'a>(episodes: impl Iterator<Item = &'a Episode>) -> Result<Option<KeyframePose>, RolloutError> {
    let mut sum = [0f64; 9];
    let (mut count, mut open) = (0usize, 0usize);
    for e in episodes {
        for k in 0..e.keyframes() {
            let a = Observation::episode_action(e, k);
            let r = quaternion_to_6d(a.quat_wxyz)?;
            for (s, v) in sum.iter_mut().zip(a.position.iter().chain(&r)) {
                *s += f64::from(*v);
            }
            count += 1;
            open += usize::from(a.gripper_open);
        }
    }
    if count == 0 {
        return Ok(None);
    }
    let mean = |i: usize| (sum[i] / count as f64) as f32;
    Ok(Some(KeyframePose {
        position: [mean(0), mean(1), mean(2)],
        quat_wxyz: quaternion_from_6d(std::array::from_fn(|i| mean(3 + i))),
        gripper_open: 2 * open >= count,
    }))
}

/// At most this many other instructions per held-out episode in the instruction probe.
const SWAPS_PER_EPISODE: usize = 2;

/// Instructions of other variations of `episode`'s task (the next ones after its own, at most
/// `n`, skipping any with the same text); none for a task this build does not know.
fn other_instructions(episode: &Episode, n: usize) -> Vec<String> {
    let Ok(task) = tasks::by_name(&episode.task) else { return Vec::new() };
    let count = task.variation_count();
    (1..count)
        .map(|d| task.instruction((episode.variation + d) % count))
        .filter(|i| *i != episode.instruction)
        .take(n)
        .collect()
}

/// Variations' keyframes this far apart (m) are different targets.
const DISTINCT_TARGETS_M: f64 = 0.03;

/// A keyframe that the instruction decides: its index, the positions there of the instructed
/// variation's expert and of experts sent to other objects the instruction also accepts (stack
/// any block of the named colour), and the positions of experts sent elsewhere at least
/// [`DISTINCT_TARGETS_M`] from the own expert's (world frame, m).
struct InstructedKeyframe {
    k: usize,
    own: Vec<[f64; 3]>,
    others: Vec<[f64; 3]>,
}

/// The first keyframe of `episode` that its instruction decides: the first index at which the
/// expert of another variation of the task, in the same scene (same seed, and a reset that
/// leaves every colour and placement as the episode's own), goes at least [`DISTINCT_TARGETS_M`]
/// from where the episode's own expert goes. In colour tasks, whose variations also paint the
/// objects (another colour's scene is another observation), the other experts are the same
/// scene's experts sent to the objects of other colours ([`tasks::Task::target_alternatives`]).
/// `None` for tasks this build does not know, for episodes whose instruction is not what this
/// build's task says for their variation (another expert version's scene), or where the
/// alternatives never part.
fn instructed_keyframe(
    episode: &Episode,
    world: &mut Option<crate::sim::World>,
) -> Result<Option<InstructedKeyframe>, RolloutError> {
    let Ok(task) = tasks::by_name(&episode.task) else { return Ok(None) };
    // An episode of another expert version whose variation now reads differently (push_buttons'
    // version 1 colours) is another scene: its alternatives cannot be replanned here.
    if episode.variation >= task.variation_count() || task.instruction(episode.variation) != episode.instruction {
        return Ok(None);
    }
    if world.is_none() {
        *world = Some(tasks::load_world(task.as_ref())?);
    }
    let world = world.as_mut().expect("loaded above");
    let plans = (0..task.variation_count())
        .map(|v| expert_plan(task.as_ref(), world, v, episode.seed))
        .collect::<Result<Vec<_>, _>>()?;
    let (own, scene) = &plans[episode.variation];
    let same_scene: Vec<&Vec<Keyframe>> =
        plans.iter().filter(|(_, fingerprint)| fingerprint == scene).map(|(plan, _)| plan).collect();
    if let Some(found) = first_parting(own, &[], &same_scene, episode.keyframes()) {
        return Ok(Some(found));
    }
    let plans = expert_alternative_plans(task.as_ref(), world, episode.variation, episode.seed)?;
    let right: Vec<&Vec<Keyframe>> = plans.right.iter().collect();
    let wrong: Vec<&Vec<Keyframe>> = plans.wrong.iter().collect();
    Ok(first_parting(&plans.own, &right, &wrong, episode.keyframes()))
}

/// The first of `keyframes` indices at which a plan of `others` goes at least
/// [`DISTINCT_TARGETS_M`] from `own` (and from every plan of `also_right`).
fn first_parting(
    own: &[Keyframe],
    also_right: &[&Vec<Keyframe>],
    others: &[&Vec<Keyframe>],
    keyframes: usize,
) -> Option<InstructedKeyframe> {
    for (k, mine) in own.iter().enumerate().take(keyframes) {
        let right: Vec<[f64; 3]> = std::iter::once(mine.position)
            .chain(also_right.iter().filter_map(|p| p.get(k)).map(|r| r.position))
            .collect();
        let parted: Vec<[f64; 3]> = others
            .iter()
            .filter_map(|plan| plan.get(k))
            .map(|other| other.position)
            .filter(|p| right.iter().all(|r| distance(p, r) >= DISTINCT_TARGETS_M))
            .collect();
        if !parted.is_empty() {
            return Some(InstructedKeyframe { k, own: right, others: parted });
        }
    }
    None
}

fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt()
}

/// Held-out keyframe errors of `policy` (sampled with `options`, always with DRS, the noise
/// seed the keyframe index) on every keyframe of `held_out`, against the mean keyframes of
/// `train` (overall and per task).
pub fn heldout_errors(
    policy: &mut Policy,
    train: &TrainingData,
    held_out: &TrainingData,
    options: &SamplingOptions,
    progress: &mut dyn EvaluationProgress,
) -> Result<HeldOutReport, RolloutError> {
    let baseline = mean_keyframe(train.episodes().iter())?
        .ok_or_else(|| RolloutError::NoBaseline { of: "the training datasets".into() })?;
    let mut task_names: Vec<String> = held_out.episodes().iter().map(|e| e.task.clone()).collect();
    task_names.sort();
    task_names.dedup();
    let started = Instant::now();
    // per held-out keyframe: task index, (model, training mean, task mean) errors
    let mut rows: Vec<(usize, [KeyframeError; 3])> = Vec::new();
    // per swapped instruction: task index, how far the first keyframe moved (mm)
    let mut swaps: Vec<(usize, f64)> = Vec::new();
    // per instructed keyframe: task index, whether the nearest variation's target is the own
    let mut choices: Vec<(usize, bool)> = Vec::new();
    let mut per_keyframe: Vec<HeldOutKeyframe> = Vec::new();
    for (ti, task) in task_names.iter().enumerate() {
        let mut world = None;
        let task_baseline = mean_keyframe(train.episodes().iter().filter(|e| &e.task == task))?
            .ok_or_else(|| RolloutError::NoBaseline { of: format!("task {task}") })?;
        let episodes: Vec<&Episode> = held_out.episodes().iter().filter(|e| &e.task == task).collect();
        progress.started(task, episodes.iter().map(|e| e.keyframes()).sum());
        let mut done = 0;
        for e in episodes {
            let instructed = instructed_keyframe(e, &mut world)?;
            for k in 0..e.keyframes() {
                let observation = Observation::from_episode(e, k)?;
                let target = Observation::episode_action(e, k);
                let options = SamplingOptions { drs: true, seed: k as u64, ..*options };
                let predicted = policy.predict_keyframe(&observation, &options)?;
                let row = |p: &KeyframePose| KeyframeError::between(p, &target);
                let model = row(&predicted);
                rows.push((ti, [model, row(&baseline), row(&task_baseline)]));
                per_keyframe.push(HeldOutKeyframe {
                    task: task.clone(),
                    variation: e.variation,
                    seed: e.seed,
                    keyframe: k,
                    expert_position: target.position,
                    predicted_position: predicted.position,
                    position_mm: model.distance_mm(),
                    rotation_deg: f64::from(model.rotation).to_degrees(),
                    expert_gripper_open: target.gripper_open,
                    predicted_gripper_open: predicted.gripper_open,
                });
                if let Some(at) = instructed.as_ref().filter(|at| at.k == k) {
                    let p = predicted.position.map(f64::from);
                    let nearest_other = at.others.iter().map(|o| distance(&p, o)).fold(f64::INFINITY, f64::min);
                    let nearest_own = at.own.iter().map(|o| distance(&p, o)).fold(f64::INFINITY, f64::min);
                    choices.push((ti, nearest_own < nearest_other));
                }
                if k == 0 {
                    for instruction in other_instructions(e, SWAPS_PER_EPISODE) {
                        let swapped = Observation { instruction, ..observation.clone() };
                        let moved = policy.predict_keyframe(&swapped, &options)?;
                        swaps.push((ti, f64::from(moved.error_to(&predicted).0) * 1e3));
                    }
                }
                done += 1;
                progress.advanced(done);
            }
        }
        progress.finished();
    }
    let errors = |name: &str, filter: &dyn Fn(usize) -> bool| {
        let pick = |j: usize| rows.iter().filter(|r| filter(r.0)).map(|r| r.1[j]).collect::<Vec<_>>();
        HeldOutErrors {
            task: name.to_string(),
            keyframes: rows.iter().filter(|r| filter(r.0)).count(),
            model: summarise(&pick(0)),
            training_mean: summarise(&pick(1)),
            task_mean: summarise(&pick(2)),
            instruction_swap_mm: median(&swaps.iter().filter(|s| filter(s.0)).map(|s| s.1).collect::<Vec<_>>()),
            instruction_swaps: swaps.iter().filter(|s| filter(s.0)).count(),
            target_accuracy: {
                let picked: Vec<bool> = choices.iter().filter(|c| filter(c.0)).map(|c| c.1).collect();
                picked.iter().filter(|&&c| c).count() as f64 / picked.len().max(1) as f64
            },
            target_choices: choices.iter().filter(|c| filter(c.0)).count(),
        }
    };
    let all = errors("all", &|_| true);
    let tasks = task_names.iter().enumerate().map(|(ti, name)| errors(name, &|t| t == ti)).collect();
    Ok(HeldOutReport {
        keyframes: all.keyframes,
        episodes: held_out.episodes().len(),
        steps: options.steps,
        samples: options.samples,
        consensus: options.consensus,
        pointer_temperature: options.sharpening.temperature,
        pointer_posterior: options.sharpening.posterior,
        pointer_posterior_width: options.sharpening.posterior_width,
        pointer_guidance: options.sharpening.guidance,
        model: all.model,
        training_mean: all.training_mean,
        task_mean: all.task_mean,
        instruction_swap_mm: all.instruction_swap_mm,
        instruction_swaps: all.instruction_swaps,
        target_accuracy: all.target_accuracy,
        target_choices: all.target_choices,
        tasks,
        per_keyframe,
        seconds: started.elapsed().as_secs_f64(),
    })
}
