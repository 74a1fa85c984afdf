//! `flowram run` (one episode to watch) and `flowram collect` (a demonstration dataset).
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::{Args, ValueEnum};
use flowram::data::Dataset;
use flowram::files::write_atomic;
use flowram::policy::inference::SamplingOptions;
use flowram::sim::{CameraRig, Visuals, image};
use flowram::tasks;
use flowram::tasks::episode::{Actor, EpisodeResult, Observer, run_episode, run_policy_episode};
use flowram::tasks::policy_actor::FlowRamActor;
use serde::Serialize;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Policy {
    /// The task's scripted expert.
    Expert,
    /// Nobody moves (the arm holds still for 5 s).
    Idle,
    /// A trained FlowRAM checkpoint (--checkpoint), closed loop on rendered observations.
    Flowram,
}

/// How a learned policy runs closed loop (`run --policy flowram`, `bench success`).
#[derive(Debug, Args)]
pub struct LearnedArgs {
    /// Run folder (runs/NAME) or checkpoint folder of a trained policy.
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Euler steps (default: the checkpoint's flow.sampling_steps).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Global geometric tokens at every step (the w/o-DRS ablation).
    #[arg(long)]
    pub no_drs: bool,
    /// Stop after this many predicted keyframes if the task has not succeeded.
    #[arg(long, default_value_t = 10)]
    pub max_keyframes: usize,
    /// Cameras the policy sees, in the training datasets' order.
    #[arg(long, value_delimiter = ',', default_value = "front,left_shoulder,right_shoulder,wrist")]
    pub cameras: Vec<String>,
}

/// A loaded learned policy, its cameras and its rig.
pub struct Learned {
    pub actor: FlowRamActor,
    rig: CameraRig,
    cameras: Vec<usize>,
    max_keyframes: usize,
}

impl LearnedArgs {
    /// Loads the checkpoint (`--checkpoint`), with the sampling options.
    pub fn load_actor(&self) -> anyhow::Result<FlowRamActor> {
        let checkpoint = self
            .checkpoint
            .as_ref()
            .context("the learned policy needs --checkpoint runs/NAME (a run folder from `flowram train`)")?;
        anyhow::ensure!(self.max_keyframes > 0, "--max-keyframes must be at least 1");
        let policy = flowram::policy::inference::Policy::load(checkpoint, super::policy::text_encoder()?)?;
        let options = SamplingOptions {
            steps: self.steps.unwrap_or(policy.config().flow.sampling_steps),
            samples: 1,
            drs: !self.no_drs,
            seed: 0,
        };
        Ok(FlowRamActor::new(policy, options))
    }

    /// `actor` with a camera rig for `world` at the checkpoint's image size.
    pub fn with_rig(&self, actor: FlowRamActor, world: &flowram::sim::World) -> anyhow::Result<Learned> {
        let rig = CameraRig::new(world, actor.policy.config().observation.image_size, Visuals::Full)?;
        let cameras = self.cameras.iter().map(|c| rig.camera_index(c)).collect::<Result<Vec<_>, _>>()?;
        Ok(Learned { actor, rig, cameras, max_keyframes: self.max_keyframes })
    }
}

impl Learned {
    /// One closed-loop episode.
    pub fn episode(
        &mut self,
        task: &dyn tasks::Task,
        world: &mut flowram::sim::World,
        variation: usize,
        seed: u64,
    ) -> anyhow::Result<EpisodeResult> {
        let mut observer = Observer { rig: &mut self.rig, cameras: self.cameras.clone() };
        Ok(run_policy_episode(task, world, variation, seed, &mut self.actor, &mut observer, self.max_keyframes)?)
    }
}

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Task name: open_drawer, push_buttons, slide_block, close_jar, stack_blocks.
    #[arg(long)]
    task: String,
    #[arg(long, value_enum, default_value_t = Policy::Expert)]
    policy: Policy,
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
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let task = tasks::by_name(&args.task)?;
    let variation = args.variation.unwrap_or(args.seed as usize % task.variation_count());
    let mut world = tasks::load_world(task.as_ref())?;
    if args.video.is_some() {
        world.start_recording(&args.video_camera, 256, 10.0)?;
    }
    if args.policy != Policy::Flowram && args.learned.checkpoint.is_some() {
        anyhow::bail!("--checkpoint is for --policy flowram (this run uses --policy {:?})", args.policy);
    }
    let start = Instant::now();
    let result = match args.policy {
        Policy::Expert => run_episode(task.as_ref(), &mut world, variation, args.seed, Actor::Expert, None)?,
        Policy::Idle => run_episode(task.as_ref(), &mut world, variation, args.seed, Actor::Idle { seconds: 5 }, None)?,
        Policy::Flowram => {
            let actor = args.learned.load_actor()?;
            args.learned.with_rig(actor, &world)?.episode(task.as_ref(), &mut world, variation, args.seed)?
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
    Ok(())
}

#[derive(Debug, Args)]
pub struct CollectArgs {
    #[arg(long)]
    task: String,
    /// Successful episodes to collect.
    #[arg(long)]
    episodes: usize,
    /// Seed of the first attempt; attempt i uses seed + i (variation = seed modulo variations).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Dataset folder (created, or extended if it holds the same task, cameras and size).
    #[arg(long)]
    out: PathBuf,
    #[arg(long, value_delimiter = ',', default_value = "front,left_shoulder,right_shoulder,wrist")]
    cameras: Vec<String>,
    #[arg(long, default_value_t = flowram::sim::camera::DEFAULT_IMAGE_SIZE)]
    size: usize,
    /// Give up after this many attempts (default: 3 x episodes).
    #[arg(long)]
    max_attempts: Option<usize>,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct CollectReport {
    task: String,
    episodes: usize,
    attempts: usize,
    successes: usize,
    keyframes_mean: f64,
    seconds: f64,
    episodes_per_minute: f64,
}

pub fn collect(args: CollectArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.episodes > 0, "--episodes must be at least 1");
    let task = tasks::by_name(&args.task)?;
    let mut world = tasks::load_world(task.as_ref())?;
    let mut rig = CameraRig::new(&world, args.size, Visuals::Full)?;
    let cameras = args.cameras.iter().map(|c| rig.camera_index(c)).collect::<Result<Vec<_>, _>>()?;
    let mut writer = Dataset::create_or_open(&args.out, task.name(), &args.cameras, [args.size, args.size])?;
    let max_attempts = args.max_attempts.unwrap_or(3 * args.episodes);
    let bar = episode_bar(task.name(), args.episodes);
    let start = Instant::now();
    let (mut attempts, mut successes, mut keyframes) = (0usize, 0usize, 0usize);
    while successes < args.episodes && attempts < max_attempts {
        let seed = args.seed + attempts as u64;
        attempts += 1;
        let variation = seed as usize % task.variation_count();
        let mut observer = Observer { rig: &mut rig, cameras: cameras.clone() };
        let result = run_episode(task.as_ref(), &mut world, variation, seed, Actor::Expert, Some(&mut observer))?;
        if !result.success {
            bar.println(format!(
                "seed {seed}: expert failed ({} keyframes reached of {}), not saved",
                result.reached, result.keyframes
            ));
            continue;
        }
        let episode = result.to_dataset_episode().context("the episode recorded no images")?;
        writer.append(&episode)?;
        successes += 1;
        keyframes += result.keyframes;
        bar.inc(1);
    }
    bar.finish_and_clear();
    let seconds = start.elapsed().as_secs_f64();
    let report = CollectReport {
        task: task.name().into(),
        episodes: writer.index().episodes.len(),
        attempts,
        successes,
        keyframes_mean: if successes > 0 { keyframes as f64 / successes as f64 } else { 0.0 },
        seconds,
        episodes_per_minute: successes as f64 / seconds * 60.0,
    };
    if args.json {
        super::print_json(&report)?;
    } else {
        println!(
            "{}: {} successful of {} attempts ({:.1} keyframes each), {:.1} episodes/min; dataset {} holds {} episodes",
            report.task,
            report.successes,
            report.attempts,
            report.keyframes_mean,
            report.episodes_per_minute,
            args.out.display(),
            report.episodes
        );
    }
    anyhow::ensure!(
        successes == args.episodes,
        "collected only {successes} of {} episodes in {attempts} attempts",
        args.episodes
    );
    Ok(())
}

#[derive(Debug, Args)]
pub struct SuccessBenchArgs {
    /// Tasks, comma-separated.
    #[arg(long, value_delimiter = ',', required = true)]
    tasks: Vec<String>,
    /// Episodes per task.
    #[arg(long, default_value_t = 10)]
    episodes: usize,
    /// Seed of the first episode (episode i: seed + i, variation = seed modulo variations);
    /// the default keeps clear of the seeds `flowram collect` starts from.
    #[arg(long, default_value_t = 1000)]
    seed: u64,
    #[command(flatten)]
    learned: LearnedArgs,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct TaskSuccess {
    task: String,
    episodes: usize,
    successes: usize,
    success_rate: f64,
    /// Mean predicted keyframes per episode.
    keyframes: f64,
    /// Fraction of predicted keyframes the controller reached (IK solvable, tracked to tolerance).
    reached: f64,
    inference_ms_median: f64,
}

/// `flowram bench success`: closed-loop success rate of a trained policy on held-out seeds.
pub fn success_bench(args: SuccessBenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.episodes > 0, "--episodes must be at least 1");
    let task_list = args.tasks.iter().map(|name| tasks::by_name(name)).collect::<Result<Vec<_>, _>>()?;
    let mut actor = args.learned.load_actor()?;
    let mut reports = Vec::new();
    for task in task_list {
        let mut world = tasks::load_world(task.as_ref())?;
        actor.inference_ms.clear();
        let mut learned = args.learned.with_rig(actor, &world)?;
        let bar = episode_bar(task.name(), args.episodes);
        let (mut successes, mut keyframes, mut reached) = (0usize, 0usize, 0usize);
        for i in 0..args.episodes {
            let seed = args.seed + i as u64;
            let variation = seed as usize % task.variation_count();
            let result = learned.episode(task.as_ref(), &mut world, variation, seed)?;
            successes += usize::from(result.success);
            keyframes += result.keyframes;
            reached += result.reached;
            bar.inc(1);
        }
        bar.finish_and_clear();
        reports.push(TaskSuccess {
            task: task.name().into(),
            episodes: args.episodes,
            successes,
            success_rate: successes as f64 / args.episodes as f64,
            keyframes: keyframes as f64 / args.episodes as f64,
            reached: if keyframes > 0 { reached as f64 / keyframes as f64 } else { 0.0 },
            inference_ms_median: super::bench::median(&learned.actor.inference_ms),
        });
        actor = learned.actor;
    }
    if args.json {
        return super::print_json(&reports);
    }
    for r in &reports {
        println!(
            "{}: {}/{} successes ({:.0} %), {:.1} keyframes per episode, {:.0} % reached, inference {:.0} ms (median)",
            r.task,
            r.successes,
            r.episodes,
            100.0 * r.success_rate,
            r.keyframes,
            100.0 * r.reached,
            r.inference_ms_median
        );
    }
    Ok(())
}

/// A progress bar over the episodes of a task.
fn episode_bar(task: &str, episodes: usize) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(episodes as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} {msg} [{bar:30}] {pos}/{len} episodes, {elapsed_precise} (eta {eta})",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(task.to_string());
    bar
}
