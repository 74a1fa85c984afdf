//! A closed-loop episode on the real-time runtime (`flowram run --realtime`): the physics world
//! is stepped by the control thread at 1 kHz while the policy, on this thread, renders what the
//! cameras see and infers the next keyframe. The two do not share a MuJoCo world: when the
//! control thread asks for a keyframe it copies the physics state (qpos, qvel, act) into a
//! preallocated triple buffer, and this thread sets it on its own copy of the task's scene
//! (reset with the same seed, so the same objects, colours and poses) to render and to check
//! the task. The arm holds while the policy thinks; nothing waits for it.
use nalgebra::{Isometry3, Quaternion};
use rand::SeedableRng;
use rand::rngs::StdRng;

use super::RolloutError;
use super::episode::{
    EpisodeResult, KeyframePolicy, Observer, TaskEpisode, begin, camera_rig, observe, proprio_of, tcp_proprio,
};
use super::stack::{load_controller_config, realtime_stack};
use crate::control::keyframe::Keyframe;
use crate::runtime::control::{ControlSettings, Pacing, StopReason};
use crate::runtime::messages::{Answer, Event, Request};
use crate::runtime::planner::WorkspaceBox;
use crate::runtime::session::{KeyframeSource, Percentiles, SessionSettings, run_session};
use crate::sim::backend::DetachedWorld;
use crate::sim::{Visuals, World};
use crate::tasks::{Task, TaskState, load_world};

/// How a real-time episode runs.
#[derive(Debug, Clone, PartialEq)]
pub struct RealtimeOptions {
    /// `Some(t)`: the simulated-latency mode, each keyframe taking effect `t` ticks (ms of
    /// simulated time) after its request, reproducibly; `None`: wall-clock 1 kHz.
    pub latency_ticks: Option<u64>,
    pub max_keyframes: usize,
    /// Ask for SCHED_FIFO, mlockall and a pinned core for the control thread.
    pub realtime_scheduling: bool,
    /// Give up when the policy has not answered for this long (s, simulated = wall clock).
    pub watchdog_s: f64,
    /// Stop after this much simulated time (s).
    pub max_seconds: f64,
    pub cameras: Vec<String>,
    pub image_size: usize,
}

/// The runtime's figures for one episode.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RealtimeFigures {
    pub ticks: u64,
    pub deadline_misses: u64,
    pub waited_on_policy_ticks: u64,
    pub compute_us: Percentiles,
    pub sim_step_us: Percentiles,
    pub wake_latency_us: Percentiles,
    pub policy_inferences: u64,
    pub rejected_keyframes: u64,
    pub limit_violations: u64,
    pub stop: StopReason,
    pub rt_scheduling: bool,
}

/// The physics state of the request it was taken for.
#[derive(Debug, Clone)]
struct Snapshot {
    request: u64,
    values: Vec<f64>,
}

/// Who chooses the keyframes of a real-time episode.
pub enum RealtimeActor<'a> {
    /// The task's expert, planned from the settled scene at the start (no cameras needed).
    Expert,
    /// A learned policy, observing through the cameras before each keyframe.
    Policy(&'a mut dyn KeyframePolicy),
}

/// The policy's side: its own copy of the scene, the cameras, the policy (or the expert's plan).
struct PolicySide<'a, 'p> {
    task: &'a dyn Task,
    world: World,
    observer: Option<Observer<'a>>,
    policy: Option<&'p mut dyn KeyframePolicy>,
    planned: Vec<Keyframe>,
    instruction: String,
    state: TaskState,
    base: Isometry3<f64>,
    snapshots: triple_buffer::Output<Snapshot>,
    max_keyframes: usize,
    result: EpisodeResult,
    solved: bool,
}

impl KeyframeSource for PolicySide<'_, '_> {
    fn propose(&mut self, request: &Request) -> Result<Answer, String> {
        let snapshot = self.snapshots.read();
        if snapshot.request != request.id {
            return Err(format!("no physics state for request {} (latest is {})", request.id, snapshot.request));
        }
        self.world.set_physics_state(&snapshot.values).map_err(|e| e.to_string())?;
        let k = self.result.observations.len();
        if k > 0 {
            self.task.observe(&mut self.world, &mut self.state).map_err(|e| e.to_string())?;
            self.result.reached_poses.push(tcp_proprio(&self.world, request.gripper_open));
            // A learned policy stops once the task is solved; the expert runs its plan to the end
            // (as in lock-step).
            if self.policy.is_some() && self.task.success(&self.world, &self.state) {
                self.solved = true;
                return Ok(Answer::Finish);
            }
        }
        if k >= self.max_keyframes {
            return Ok(Answer::Finish);
        }
        let observation =
            observe(&mut self.world, self.observer.as_mut(), request.gripper_open).map_err(|e| e.to_string())?;
        let keyframe = match self.policy.as_mut() {
            Some(policy) => policy.next_keyframe(&self.instruction, k, &observation).map_err(|e| e.to_string())?,
            None => match self.planned.get(k) {
                Some(keyframe) => *keyframe,
                None => return Ok(Answer::Finish),
            },
        };
        self.result.observations.push(observation);
        self.result.actions.push(proprio_of(&keyframe));
        Ok(Answer::Keyframe(world_to_base(&self.base, &keyframe)))
    }
}

/// `keyframe` (world frame) in the base frame, without normalising or checking it: a
/// non-finite or non-unit prediction stays so, for the planner to refuse.
fn world_to_base(base: &Isometry3<f64>, keyframe: &Keyframe) -> Keyframe {
    let inverse = base.inverse();
    let p = keyframe.position;
    let position = inverse.transform_point(&nalgebra::Point3::new(p[0], p[1], p[2]));
    let [w, x, y, z] = keyframe.quat_wxyz;
    let q = inverse.rotation.quaternion() * Quaternion::new(w, x, y, z);
    Keyframe {
        position: [position.x, position.y, position.z],
        quat_wxyz: [q.w, q.i, q.j, q.k],
        gripper_open: keyframe.gripper_open,
    }
}

/// Resets `task` (seeded) and runs one episode on the real-time runtime with `actor` choosing
/// the keyframes (a policy from the cameras' views).
pub fn run_realtime_episode(
    task: &dyn Task,
    variation: usize,
    seed: u64,
    actor: RealtimeActor<'_>,
    options: &RealtimeOptions,
) -> Result<(EpisodeResult, RealtimeFigures), RolloutError> {
    if options.max_keyframes == 0 {
        return Err(RolloutError::Zero { what: "the keyframes per episode" });
    }
    let mut world = load_world(task)?;
    let (state, _, t0) = begin(task, &mut world, variation, seed)?;
    let (policy, planned) = match actor {
        RealtimeActor::Expert => (None, task.expert(&world, &state)?),
        RealtimeActor::Policy(policy) => {
            if options.cameras.is_empty() {
                return Err(RolloutError::NoCameras);
            }
            (Some(policy), Vec::new())
        }
    };
    // The policy's copy: the same reset, so the same model edits (colours, fixed poses).
    let mut view = load_world(task)?;
    view.reset_to("home")?;
    task.reset(&mut view, variation, &mut StdRng::seed_from_u64(seed))?;
    let mut rig = match policy {
        Some(_) => Some(camera_rig(&view, options.image_size, Visuals::Full, &options.cameras)?),
        None => None,
    };
    let n = world.physics_state_len();
    let (mut snapshot_in, snapshot_out) =
        triple_buffer::triple_buffer(&Snapshot { request: u64::MAX, values: vec![0.0; n] });
    let base = world.base_pose();
    let pacing = options.latency_ticks.map_or(Pacing::WallClock, |ticks| Pacing::SimulatedLatency { ticks });
    let settings = ControlSettings {
        pacing,
        max_ticks: (options.max_seconds * 1e3) as u64,
        keyframes: Some(options.max_keyframes as u64),
        watchdog_ticks: (options.watchdog_s * 1e3) as u64,
        max_rejections_in_a_row: 3,
        gripper_timeout: 2.0,
        stall_timeout_s: options.watchdog_s,
    };
    let (mut control, planner) = realtime_stack(world, load_controller_config(None)?, settings, WorkspaceBox::TABLE)?;
    control.tap = Some(Box::new(move |backend: &DetachedWorld, request: &Request| {
        let buffer = snapshot_in.input_buffer_mut();
        buffer.request = request.id;
        backend.world().copy_physics_state(&mut buffer.values);
        snapshot_in.publish();
    }));
    let instruction = task.instruction(variation);
    let mut side = PolicySide {
        task,
        world: view,
        observer: rig.as_mut().map(|(rig, cameras)| Observer { rig, cameras: cameras.clone() }),
        policy,
        planned,
        instruction: instruction.clone(),
        state,
        base,
        snapshots: snapshot_out,
        max_keyframes: options.max_keyframes,
        result: EpisodeResult {
            episode: TaskEpisode { task: task.name(), variation, instruction, seed, state: TaskState::default() },
            success: false,
            keyframes: 0,
            reached: 0,
            sim_seconds: 0.0,
            observations: Vec::new(),
            actions: Vec::new(),
            reached_poses: Vec::new(),
            problems: Vec::new(),
        },
        solved: false,
    };
    let session = SessionSettings { realtime_scheduling: options.realtime_scheduling, ..Default::default() };
    let out = run_session(control, planner, &mut side, session).map_err(|e| RolloutError::Thread(e.to_string()))?;
    let mut world = out.control.backend.into_world();
    let mut result = side.result;
    let mut state = side.state;
    task.observe(&mut world, &mut state)?;
    result.success = side.solved || task.success(&world, &state);
    result.sim_seconds = world.time() - t0;
    let c = out.control.controller.osc().config();
    for e in &out.events {
        let k = result.keyframes;
        match *e {
            Event::KeyframeDone { outcome, .. } => {
                result.keyframes += 1;
                match outcome.problem(c) {
                    None => result.reached += 1,
                    Some(problem) => result.problems.push((k, problem)),
                }
            }
            Event::Rejected { why, .. } => result.problems.push((k, format!("keyframe refused: {}", why.name()))),
            Event::WatchdogHold { ticks, .. } => {
                result.problems.push((k, format!("no keyframe after {ticks} ticks: the arm held and the run ended")));
            }
            _ => {}
        }
    }
    result.problems.extend(out.source_errors.iter().map(|e| (result.actions.len(), format!("policy: {e}"))));
    result.episode.state = state;
    let s = &out.summary;
    let figures = RealtimeFigures {
        ticks: s.ticks,
        deadline_misses: s.deadline_misses,
        waited_on_policy_ticks: s.waited_ticks,
        compute_us: out.compute,
        sim_step_us: out.backend,
        wake_latency_us: out.wake_latency,
        policy_inferences: result.actions.len() as u64,
        rejected_keyframes: s.rejections,
        limit_violations: s.monitor.violations,
        stop: s.stop,
        rt_scheduling: out.rt.as_ref().is_some_and(|r| r.fifo),
    };
    Ok((result, figures))
}
