//! `flowram run` (one episode to watch) and `flowram collect` (a demonstration dataset).
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::{Args, ValueEnum};
use flowram::files::write_atomic;
use flowram::rollout::collection::{self, CollectOptions};
use flowram::rollout::episode::{Actor, Observer, Perturbation, RecoveryTarget, camera_rig, run_episode};
use flowram::rollout::learned::DEFAULT_CAMERAS;
use flowram::rollout::realtime::{RealtimeActor, RealtimeFigures, RealtimeOptions, run_realtime_episode};
use flowram::sim::{Visuals, image};
use flowram::tasks;
use serde::Serialize;

use super::learned::LearnedArgs;
use super::progress::TaskBar;

/// Who chooses the keyframes of `flowram run`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ActorKind {
    /// The task's scripted expert.
    Expert,
    /// Nobody moves (the arm holds still for 5 s).
    Idle,
    /// A trained FlowRAM checkpoint (--checkpoint, default the shipped one), closed loop on
    /// rendered observations.
    Flowram,
}

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Task name: open_drawer, push_buttons, slide_block, close_jar, stack_blocks.
    #[arg(long)]
    task: String,
    #[arg(long, value_enum, default_value_t = ActorKind::Expert)]
    policy: ActorKind,
    #[command(flatten)]
    learned: LearnedArgs,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Variation; default: seed modulo the task's variations.
    #[arg(long)]
    variation: Option<usize>,
    /// Write an animated GIF of the front camera (10 frames per simulated second).
    #[arg(long)]
    video: Option<PathBuf>,
    #[arg(long, default_value = "front")]
    video_camera: String,
    /// Run on the real-time runtime: MuJoCo stepped at wall-clock 1 kHz by a control thread while
    /// the policy infers on its own thread (the arm holds while it thinks). Default: lock-step.
    #[arg(long)]
    realtime: bool,
    /// With --realtime: the simulated-latency mode instead of wall clock; each keyframe takes
    /// effect this many ms of simulated time after its observation (reproducible).
    #[arg(long, requires = "realtime")]
    latency_ms: Option<u64>,
    /// With --realtime: do not ask for SCHED_FIFO, mlockall and a pinned core.
    #[arg(long, requires = "realtime")]
    no_rt: bool,
    /// With --realtime: run the whole process on the control thread's core (the policy computes
    /// only while the tick sleeps; a shorter tick tail on 2-core machines, a slower policy).
    #[arg(long, requires = "realtime", conflicts_with = "latency_ms")]
    one_core: bool,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct RunReport {
    task: String,
    variation: usize,
    instruction: String,
    success: bool,
    keyframes: usize,
    keyframes_reached: usize,
    seconds: f64,
    sim_seconds: f64,
    problems: Vec<String>,
    /// The executed keyframes, world frame: position (m), quaternion w x y z, gripper open (1/0).
    actions: Vec<[f32; 8]>,
    /// With --realtime: the runtime's timing figures.
    #[serde(skip_serializing_if = "Option::is_none")]
    realtime: Option<RealtimeFigures>,
    /// Lock-step runs: where the scene's loose objects ended (world frame, m), with their colours
    /// (`--policy idle` gives the initial layout: nothing moves).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    objects: Vec<flowram::sim::SceneObject>,
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let task = tasks::by_name(&args.task)?;
    let variation = args.variation.unwrap_or(args.seed as usize % task.variation_count());
    let mut world = tasks::load_world(task.as_ref())?;
    if args.video.is_some() {
        world.start_recording(&args.video_camera, 256, 10.0)?;
    }
    if args.policy != ActorKind::Flowram && args.learned.checkpoint.is_some() {
        anyhow::bail!("--checkpoint is for --policy flowram (this run uses --policy {:?})", args.policy);
    }
    let start = Instant::now();
    let mut figures = None;
    let result = match args.policy {
        _ if args.realtime => {
            anyhow::ensure!(args.video.is_none(), "--video records in lock-step only; drop it or --realtime");
            anyhow::ensure!(args.policy != ActorKind::Idle, "--realtime runs --policy expert or flowram");
            if args.one_core {
                // before the policy loads, so its thread pool starts confined to that core
                flowram::runtime::pacing::share_one_core()
                    .context("--one-core: confining the process to the control thread's core")?;
            }
            if !args.no_rt && args.latency_ms.is_none() {
                // as `bench realtime`: the policy's pool threads at background priority, started
                // before the policy loads (and after --one-core, so it is sized for that core)
                flowram::runtime::pacing::start_background_pool();
            }
            let mut loaded = if args.policy == ActorKind::Flowram {
                Some(args.learned.load_actor(&[args.task.as_str()])?)
            } else {
                None
            };
            let options = RealtimeOptions {
                latency_ticks: args.latency_ms,
                max_keyframes: if loaded.is_some() { args.learned.max_keyframes } else { 100 },
                realtime_scheduling: !args.no_rt && args.latency_ms.is_none(),
                watchdog_s: 10.0,
                max_seconds: 300.0,
                cameras: args.learned.cameras.clone(),
                image_size: loaded.as_ref().map_or(128, |a| a.policy.config().observation.image_size),
            };
            let actor = match loaded.as_mut() {
                Some(a) => RealtimeActor::Policy(a),
                None => RealtimeActor::Expert,
            };
            let (result, f) = run_realtime_episode(task.as_ref(), variation, args.seed, actor, &options)?;
            figures = Some(f);
            result
        }
        ActorKind::Expert => run_episode(task.as_ref(), &mut world, variation, args.seed, Actor::Expert, None)?,
        ActorKind::Idle => {
            run_episode(task.as_ref(), &mut world, variation, args.seed, Actor::Idle { seconds: 5 }, None)?
        }
        ActorKind::Flowram => {
            let mut actor = args.learned.load_actor(&[args.task.as_str()])?;
            let size = actor.policy.config().observation.image_size;
            let (mut rig, cameras) = camera_rig(&world, size, Visuals::Full, &args.learned.cameras)?;
            let policy = Actor::Policy { policy: &mut actor, max_keyframes: args.learned.max_keyframes };
            let mut observer = Observer { rig: &mut rig, cameras };
            run_episode(task.as_ref(), &mut world, variation, args.seed, policy, Some(&mut observer))?
        }
    };
    let seconds = start.elapsed().as_secs_f64();
    if let Some(path) = &args.video {
        let video = world.stop_recording()?.context("no video was recorded")?;
        let gif = image::video_gif(&video).context("encoding the GIF")?;
        write_atomic(path, &gif).with_context(|| format!("writing {}", path.display()))?;
    }
    let report = RunReport {
        task: task.name().into(),
        variation,
        instruction: result.episode.instruction.clone(),
        success: result.success,
        keyframes: result.keyframes,
        keyframes_reached: result.reached,
        seconds,
        sim_seconds: result.sim_seconds,
        problems: result.problems.iter().map(|(k, p)| format!("keyframe {k}: {p}")).collect(),
        actions: result.actions.clone(),
        objects: if figures.is_none() { world.objects() } else { Vec::new() },
        realtime: figures,
    };
    if args.json {
        return super::print_json(&report);
    }
    println!(
        "{} (variation {}): \"{}\" -> {} ({} keyframes, {:.1} s simulated, {:.1} s wall)",
        report.task,
        report.variation,
        report.instruction,
        if report.success { "success" } else { "FAILED" },
        report.keyframes,
        report.sim_seconds,
        report.seconds
    );
    for p in &report.problems {
        println!("  {p}");
    }
    if let Some(f) = &report.realtime {
        println!(
            "  real-time: {} ticks, {} deadline misses, {} ticks waited on the policy, tick compute p99 {:.1} us (MuJoCo step p99 {:.1} us), wake latency p99 {:.1} / max {:.1} us, SCHED_FIFO {}, stop: {:?}",
            f.ticks,
            f.deadline_misses,
            f.waited_on_policy_ticks,
            f.compute_us.p99,
            f.sim_step_us.p99,
            f.wake_latency_us.p99,
            f.wake_latency_us.max,
            f.rt_scheduling,
            f.stop
        );
    }
    Ok(())
}

#[derive(Debug, Args)]
pub struct CollectArgs {
    #[arg(long)]
    task: String,
    /// Successful episodes to collect (episode slots 0..N).
    #[arg(long)]
    episodes: usize,
    /// Base seed: slot k's first attempt uses seed + k, its retry r seed + k + r N (variation =
    /// seed modulo variations).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Dataset folder (created; a folder holding this very collection is resumed).
    #[arg(long)]
    out: PathBuf,
    #[arg(long, value_delimiter = ',', default_values_t = DEFAULT_CAMERAS.map(String::from))]
    cameras: Vec<String>,
    #[arg(long, default_value_t = flowram::sim::camera::DEFAULT_IMAGE_SIZE)]
    size: usize,
    /// Expert attempts per episode slot before it is given up.
    #[arg(long, default_value_t = 3)]
    attempts_per_episode: usize,
    /// Recovery samples: before approach keyframes the arm first goes off target by this
    /// standard deviation (m; x, y and upward z) and the observation there is saved as an extra
    /// step, its action set by --perturb-target (README, "Recovery samples"). Off when not given.
    #[arg(long)]
    perturb_sigma: Option<f64>,
    /// The chance that an approach keyframe gets such a detour (with --perturb-sigma).
    #[arg(long, default_value_t = 0.5, requires = "perturb_sigma")]
    perturb_probability: f64,
    /// The action saved for the detour's observation: the keyframe after the approach (`next`),
    /// or the approach keyframe itself (`approach`, measured harmful: experiments arm R).
    #[arg(long, default_value = "next", value_parser = ["next", "approach"], requires = "perturb_sigma")]
    perturb_target: String,
    /// The chance that a grasp keyframe (closing the gripper after an approach) is first
    /// executed 4.5-5.5 cm beside its pose, closing on nothing; the observation there is saved
    /// with the approach keyframe as its action (re-open above), then the grasp is tried again
    /// (with --perturb-sigma; README, "Recovery samples").
    #[arg(long, default_value_t = 0.0, requires = "perturb_sigma")]
    perturb_grasp_probability: f64,
    /// Detours per approach keyframe that gets one (1 to 8): the further ones are other offsets
    /// around the same approach, each observation saved with the same action (with
    /// --perturb-sigma; README, "Recovery samples").
    #[arg(long, default_value_t = 1, requires = "perturb_sigma")]
    perturb_detours: u32,
    /// Each detour also turns the hand about the vertical by N(0, this) degrees, clipped to 2.5
    /// sigma (0 to 17.5; with --perturb-sigma; README, "Recovery samples"). 0: no turn.
    #[arg(long, default_value_t = 0.0, requires = "perturb_sigma")]
    perturb_yaw_deg: f64,
    /// Take the task's targets in a random order (from the episode seed) instead of the
    /// expert's; only for tasks whose success accepts any order (stack_blocks). With
    /// --perturb-sigma (README, "Recovery samples").
    #[arg(long, requires = "perturb_sigma")]
    shuffle_targets: bool,
    #[command(flatten)]
    shard: super::ShardArgs,
    #[arg(long)]
    json: bool,
}

pub fn collect(args: CollectArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.episodes > 0, "--episodes must be at least 1");
    let task = tasks::by_name(&args.task)?;
    let options = CollectOptions {
        episodes: args.episodes,
        seed: args.seed,
        attempts_per_episode: args.attempts_per_episode,
        cameras: args.cameras.clone(),
        size: args.size,
        shard: args.shard.resolve()?,
        perturbation: args.perturb_sigma.map(|sigma_m| Perturbation {
            probability: args.perturb_probability,
            sigma_m,
            // clap accepts only the names
            target: RecoveryTarget::named(&args.perturb_target).unwrap_or_default(),
            grasp_probability: args.perturb_grasp_probability,
            detours: args.perturb_detours,
            yaw_sigma_deg: args.perturb_yaw_deg,
            shuffle_targets: args.shuffle_targets,
        }),
    };
    let owned = options.shard.items(args.episodes).count();
    let mut bar = TaskBar::for_collection(task.name(), owned);
    let report = collection::collect(task.as_ref(), &args.out, &options, &mut bar)?;
    bar.finish();
    if args.json {
        super::print_json(&report)?;
    } else {
        let shard = if report.shard.is_whole() {
            String::new()
        } else {
            format!(
                " (shard {} of {}: {} of the {} slots)",
                report.shard.index, report.shard.count, report.owned, args.episodes
            )
        };
        println!(
            "{}{shard}: {} successful of {} attempts ({:.1} keyframes each), {} done before (resumed), {:.1} episodes/min; dataset {} holds {} episodes",
            report.task,
            report.successes,
            report.attempts,
            report.keyframes_mean,
            report.resumed,
            report.episodes_per_minute,
            args.out.display(),
            report.episodes
        );
    }
    anyhow::ensure!(
        report.given_up == 0,
        "{} of {} episode slots failed all {} attempts (see the failures above); the dataset holds the others",
        report.given_up,
        report.owned,
        args.attempts_per_episode
    );
    Ok(())
}
