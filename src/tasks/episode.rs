//! Running a task's episode closed loop: reset (seeded), the expert's keyframes executed one
//! by one through IK -> ruckig -> OSC at 1 kHz on the simulated Panda (no teleporting), the
//! task observing after each keyframe, success checked at the end. Observations (RGB-D of the
//! chosen cameras, proprioception) are taken at each keyframe for datasets.
use nalgebra::Isometry3;
use rand::SeedableRng;
use rand::rngs::StdRng;

use super::{Episode, Task, TaskError};
use crate::control::backend::RobotBackend;
use crate::control::osc_config::OscConfig;
use crate::control::keyframe::Keyframe;
use crate::control::runner::Runner;
use crate::robot::{JointLimits, JointVector};
use crate::sim::{CameraRig, RgbdFrame, World};

/// Who acts in an episode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Actor {
    /// The task's scripted expert.
    Expert,
    /// Nobody: the arm holds still for the given seconds (checks that success is not trivial).
    Idle { seconds: u32 },
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
    pub episode: Episode,
    pub success: bool,
    /// Keyframes executed, and how many the controller reached to tolerance.
    pub keyframes: usize,
    pub reached: usize,
    pub sim_seconds: f64,
    /// One observation before each keyframe (k = 0 is the initial state).
    pub observations: Vec<KeyframeObservation>,
    /// The keyframe the expert went to from each observation (world frame), as `proprio`.
    pub actions: Vec<[f32; 8]>,
    /// Where the TCP actually was after each keyframe (world frame), as `proprio`.
    pub reached_poses: Vec<[f32; 8]>,
    /// Why keyframes were not reached (keyframe index, reason).
    pub problems: Vec<(usize, String)>,
}

/// Settling time after reset, before the first keyframe (objects come to rest).
const SETTLE_S: f64 = 0.3;

/// Resets the task (seeded) and runs one episode.
/// Which cameras to observe at each keyframe (indices into the rig's cameras).
pub struct Observer<'a> {
    pub rig: &'a mut CameraRig,
    pub cameras: Vec<usize>,
}

pub fn run_episode(
    task: &dyn Task,
    world: &mut World,
    variation: usize,
    seed: u64,
    actor: Actor,
    mut cameras: Option<&mut Observer<'_>>,
) -> Result<EpisodeResult, TaskError> {
    let (mut state, mut runner, t0) = begin(task, world, variation, seed)?;
    let keyframes = match actor {
        Actor::Expert => task.expert(world, &state)?,
        Actor::Idle { .. } => Vec::new(),
    };
    let base = world.base_pose();
    let mut result = EpisodeResult {
        episode: Episode {
            task: task.name(),
            variation,
            instruction: task.instruction(variation),
            seed,
            state: Default::default(),
        },
        success: false,
        keyframes: keyframes.len(),
        reached: 0,
        sim_seconds: 0.0,
        observations: Vec::with_capacity(keyframes.len()),
        actions: Vec::with_capacity(keyframes.len()),
        reached_poses: Vec::with_capacity(keyframes.len()),
        problems: Vec::new(),
    };
    let mut gripper_open = true;
    for (k, keyframe) in keyframes.iter().enumerate() {
        result.observations.push(observe(world, cameras.as_deref_mut(), gripper_open)?);
        execute(task, world, &mut runner, &base, k, keyframe, &mut state, &mut result)?;
        gripper_open = keyframe.gripper_open;
    }
    if let Actor::Idle { seconds } = actor {
        hold(world, &mut runner, f64::from(seconds))?;
        task.observe(world, &mut state);
    }
    result.success = task.success(world, &state);
    result.sim_seconds = world.time() - t0;
    result.episode.state = state;
    Ok(result)
}

/// Executes keyframe `k` (world frame) and records how it went.
#[allow(clippy::too_many_arguments)]
fn execute(
    task: &dyn Task,
    world: &mut World,
    runner: &mut Runner,
    base: &Isometry3<f64>,
    k: usize,
    keyframe: &Keyframe,
    state: &mut super::TaskState,
    result: &mut EpisodeResult,
) -> Result<(), TaskError> {
    result.actions.push(proprio_of(keyframe));
    let report = runner.run(world, &[in_base(base, keyframe)?]).map_err(|e| TaskError::Config(e.to_string()))?;
    for r in &report.keyframes {
        if r.reached {
            result.reached += 1;
        } else {
            result.problems.push((k, r.error.clone().unwrap_or_default()));
        }
    }
    task.observe(world, state);
    result.reached_poses.push(tcp_proprio(world, keyframe.gripper_open));
    Ok(())
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
    ) -> Result<Keyframe, TaskError>;
}

/// Resets the task (seeded) and lets `policy` act closed loop: observe with the observer's
/// cameras, predict the next keyframe, execute it through IK -> ruckig -> OSC, and again, until
/// the task succeeds or `max_keyframes` were executed. Lock-step: the simulation waits for the
/// policy (deterministic). Unreachable predictions are recorded as problems, not errors.
pub fn run_policy_episode(
    task: &dyn Task,
    world: &mut World,
    variation: usize,
    seed: u64,
    policy: &mut dyn KeyframePolicy,
    observer: &mut Observer<'_>,
    max_keyframes: usize,
) -> Result<EpisodeResult, TaskError> {
    let (mut state, mut runner, t0) = begin(task, world, variation, seed)?;
    let base = world.base_pose();
    let instruction = task.instruction(variation);
    let mut result = EpisodeResult {
        episode: Episode {
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
        observations: Vec::new(),
        actions: Vec::new(),
        reached_poses: Vec::new(),
        problems: Vec::new(),
    };
    let mut gripper_open = true;
    for k in 0..max_keyframes {
        let observation = observe(world, Some(&mut *observer), gripper_open)?;
        let keyframe = policy.next_keyframe(&instruction, k, &observation)?;
        result.observations.push(observation);
        execute(task, world, &mut runner, &base, k, &keyframe, &mut state, &mut result)?;
        result.keyframes += 1;
        gripper_open = keyframe.gripper_open;
        if task.success(world, &state) {
            break;
        }
    }
    result.success = task.success(world, &state);
    result.sim_seconds = world.time() - t0;
    result.episode.state = state;
    Ok(result)
}

/// Resets the world and the task (seeded), builds the control stack and lets the objects
/// settle while the controller holds the arm. Returns the task state, the runner and the start
/// time.
fn begin(
    task: &dyn Task,
    world: &mut World,
    variation: usize,
    seed: u64,
) -> Result<(super::TaskState, Runner, f64), TaskError> {
    if variation >= task.variation_count() {
        return Err(TaskError::BadVariation { task: task.name(), variation, max: task.variation_count() - 1 });
    }
    world.reset_to("home")?;
    let mut rng = StdRng::seed_from_u64(seed);
    let state = task.reset(world, variation, &mut rng)?;
    let limits = JointLimits::panda().map_err(|e| TaskError::Config(e.to_string()))?;
    let config = OscConfig::default_profile().map_err(|e| TaskError::Config(e.to_string()))?;
    let description = world.arm_description()?;
    let mut runner = Runner::build(&description, limits, config, &world.read_state(), world.timestep())
        .map_err(|e| TaskError::Config(e.to_string()))?;
    let t0 = world.time();
    hold(world, &mut runner, SETTLE_S)?;
    Ok((state, runner, t0))
}

/// Holds the arm where it is for `seconds`.
fn hold(world: &mut World, runner: &mut Runner, seconds: f64) -> Result<(), TaskError> {
    let q: JointVector = world.read_state().q;
    runner.controller.set_goal(&q);
    let end = world.time() + seconds;
    world
        .control(|state| {
            let command = runner.controller.tick(state);
            if state.time >= end {
                crate::control::backend::Cycle::Finish(command)
            } else {
                crate::control::backend::Cycle::Continue(command)
            }
        })
        .map_err(|e| TaskError::Config(e.to_string()))?;
    Ok(())
}

fn in_base(base: &Isometry3<f64>, keyframe: &Keyframe) -> Result<Keyframe, TaskError> {
    let pose = crate::control::ik::target_pose(keyframe.position, keyframe.quat_wxyz)
        .map_err(|e| TaskError::Config(format!("the expert produced an invalid keyframe: {e}")))?;
    Ok(Keyframe::at(&(base.inverse() * pose), keyframe.gripper_open))
}

fn proprio_of(k: &Keyframe) -> [f32; 8] {
    let (p, q) = (k.position, k.quat_wxyz);
    [p[0], p[1], p[2], q[0], q[1], q[2], q[3], if k.gripper_open { 1.0 } else { 0.0 }].map(|v| v as f32)
}

fn tcp_proprio(world: &World, gripper_open: bool) -> [f32; 8] {
    proprio_of(&Keyframe::at(&world.tcp_pose(), gripper_open))
}

fn observe(
    world: &mut World,
    cameras: Option<&mut Observer<'_>>,
    gripper_open: bool,
) -> Result<KeyframeObservation, TaskError> {
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
