//! `flowram run` (one episode to watch) and `flowram collect` (a demonstration dataset).
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::{Args, ValueEnum};
use flowram::data::Dataset;
use flowram::files::write_atomic;
use flowram::sim::{CameraRig, Visuals, image};
use flowram::tasks::episode::{Actor, Observer, run_episode};
use flowram::tasks;
use serde::Serialize;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Policy {
    /// The task's scripted expert.
    Expert,
    /// Nobody moves (the arm holds still for 5 s).
    Idle,
}

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Task name: open_drawer, push_buttons.
    #[arg(long)]
    task: String,
    #[arg(long, value_enum, default_value_t = Policy::Expert)]
    policy: Policy,
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
}

fn actor(policy: Policy) -> Actor {
    match policy {
        Policy::Expert => Actor::Expert,
        Policy::Idle => Actor::Idle { seconds: 5 },
    }
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let task = tasks::by_name(&args.task)?;
    let variation = args.variation.unwrap_or(args.seed as usize % task.variation_count());
    let mut world = tasks::load_world(task.as_ref())?;
    if args.video.is_some() {
        world.start_recording(&args.video_camera, 256, 10.0)?;
    }
    let start = Instant::now();
    let result = run_episode(task.as_ref(), &mut world, variation, args.seed, actor(args.policy), None)?;
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
    let bar = indicatif::ProgressBar::new(args.episodes as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg} [{bar:30}] {pos}/{len} episodes, {elapsed_precise} (eta {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(task.name().to_string());
    let start = Instant::now();
    let (mut attempts, mut successes, mut keyframes) = (0usize, 0usize, 0usize);
    while successes < args.episodes && attempts < max_attempts {
        let seed = args.seed + attempts as u64;
        attempts += 1;
        let variation = seed as usize % task.variation_count();
        let mut observer = Observer { rig: &mut rig, cameras: cameras.clone() };
        let result = run_episode(task.as_ref(), &mut world, variation, seed, Actor::Expert, Some(&mut observer))?;
        if !result.success {
            bar.println(format!("seed {seed}: expert failed ({} keyframes reached of {}), not saved", result.reached, result.keyframes));
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
            report.task, report.successes, report.attempts, report.keyframes_mean, report.episodes_per_minute, args.out.display(), report.episodes
        );
    }
    anyhow::ensure!(successes == args.episodes, "collected only {successes} of {} episodes in {attempts} attempts", args.episodes);
    Ok(())
}

