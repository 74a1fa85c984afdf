//! `flowram bench policy` (latency and training-step time), `bench heldout` (held-out keyframe
//! errors against trivial baselines) and `bench success` (closed-loop success rates).
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use flowram::policy::config::PolicyConfig;
use flowram::policy::inference::{Policy, SampleProfile, SamplingOptions};
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::policy::scene::observation::Observation;
use flowram::policy::training::data::TrainingData;
use flowram::policy::training::trainer::Trainer;
use flowram::rollout::collection::demonstration;
use flowram::rollout::evaluation::{Errors, SuccessOptions, heldout_errors, success_rates};
use flowram::rollout::learned::DEFAULT_CAMERAS;
use flowram::sim::Visuals;
use flowram::stats::median;
use flowram::tasks;
use serde::Serialize;

use super::learned::LearnedArgs;
use super::policy::load_training_data;
use super::progress::TaskBar;

#[derive(Debug, Args)]
pub struct PolicyBenchArgs {
    /// Time a trained checkpoint instead of random weights.
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// Policy config for random weights; default models/policy/paper.toml (N1 4096, N2 1024).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Repeats per figure (the median is printed).
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Batch of the timed training step (the paper's 320 does not fit a 24 GiB CPU machine).
    #[arg(long, default_value_t = 8)]
    train_batch: usize,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct StepTimes {
    #[serde(rename = "2")]
    s2: f64,
    #[serde(rename = "4")]
    s4: f64,
    #[serde(rename = "8")]
    s8: f64,
    #[serde(rename = "16")]
    s16: f64,
    #[serde(rename = "32")]
    s32: f64,
}

#[derive(Serialize)]
struct InferTimes {
    drs: StepTimes,
    global: StepTimes,
}

#[derive(Serialize)]
struct PolicyBenchReport {
    n1: usize,
    n2: usize,
    layers: usize,
    cameras: usize,
    image_size: usize,
    threads: usize,
    prepare_ms: f64,
    encode_ms: f64,
    infer_ms: InferTimes,
    /// The 8 DRS steps after encoding: token selection vs network, summed over steps.
    drs8_steps: SampleProfile,
    train_step_ms: f64,
    train_batch: usize,
}

pub fn bench_cmd(args: PolicyBenchArgs) -> anyhow::Result<()> {
    if args.repeats == 0 {
        bail!("--repeats must be at least 1");
    }
    let text = TextEncoder::load_installed()?;
    let mut policy = match (&args.checkpoint, &args.config) {
        (Some(c), None) => Policy::load(c, text)?,
        (None, config) => {
            let path = config.clone().unwrap_or_else(|| flowram::deps::models_dir().join("policy/paper.toml"));
            Policy::random(&PolicyConfig::from_toml_file(&path)?, text)?
        }
        (Some(_), Some(_)) => bail!("give either --checkpoint or --config"),
    };
    let config = policy.config().clone();
    // A real observation: the open_drawer scene from all four cameras, and its demonstration
    // (for the training step).
    let task = tasks::by_name("open_drawer")?;
    let episode = demonstration(task.as_ref(), 0, 0, &DEFAULT_CAMERAS, config.observation.image_size, Visuals::Full)
        .context("rendering the benchmark's observation")?;
    let observation = Observation::from_episode(&episode, 0)?;
    policy.prepare(&observation)?; // caches the instruction's embedding, as in a closed loop
    let mut prepare_ms = Vec::new();
    let mut encode_ms = Vec::new();
    for _ in 0..args.repeats {
        let t0 = Instant::now();
        let prepared = policy.prepare(&observation)?;
        let t1 = Instant::now();
        policy.encode(&prepared)?;
        prepare_ms.push((t1 - t0).as_secs_f64() * 1e3);
        encode_ms.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    let mut time_steps = |drs: bool| -> anyhow::Result<StepTimes> {
        let mut at = |steps: usize| -> anyhow::Result<f64> {
            let mut v = Vec::new();
            for r in 0..args.repeats {
                let t0 = Instant::now();
                policy.predict(&observation, &SamplingOptions { steps, samples: 1, drs, seed: r as u64 })?;
                v.push(t0.elapsed().as_secs_f64() * 1e3);
            }
            Ok(median(&v))
        };
        Ok(StepTimes { s2: at(2)?, s4: at(4)?, s8: at(8)?, s16: at(16)?, s32: at(32)? })
    };
    let infer_ms = InferTimes { drs: time_steps(true)?, global: time_steps(false)? };
    // Where the 8 DRS steps' time goes (the sum over steps; median over repeats).
    let prepared = policy.prepare(&observation)?;
    let encoded = policy.encode(&prepared)?;
    let mut profiles = Vec::new();
    for r in 0..args.repeats {
        let mut profile = SampleProfile::default();
        policy.sample_profiled(
            &prepared,
            &encoded,
            &SamplingOptions { steps: 8, samples: 1, drs: true, seed: r as u64 },
            &mut profile,
        )?;
        profiles.push(profile);
    }
    let drs8 = SampleProfile {
        selection_ms: median(&profiles.iter().map(|p| p.selection_ms).collect::<Vec<_>>()),
        network_ms: median(&profiles.iter().map(|p| p.network_ms).collect::<Vec<_>>()),
    };
    // Training step at the config's batch size, on the rendered demonstration.
    let mut train_config = config.clone();
    train_config.train.batch = args.train_batch;
    train_config.validate()?;
    let mut trainer = Trainer::new(&train_config)?;
    let mut data = TrainingData::from_episodes(vec![episode])?;
    let mut text = TextEncoder::load_installed()?;
    trainer.train_step(&mut data, &mut text)?; // prepares the observations once
    let mut train_ms = Vec::new();
    for _ in 0..args.repeats {
        let t0 = Instant::now();
        trainer.train_step(&mut data, &mut text)?;
        train_ms.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    let report = PolicyBenchReport {
        n1: config.observation.semantic_tokens,
        n2: config.observation.geometric_tokens,
        layers: config.model.layers,
        cameras: observation.cameras.len(),
        image_size: config.observation.image_size,
        threads: rayon::current_num_threads(),
        prepare_ms: median(&prepare_ms),
        encode_ms: median(&encode_ms),
        infer_ms,
        drs8_steps: drs8,
        train_step_ms: median(&train_ms),
        train_batch: args.train_batch,
    };
    if args.json {
        return super::print_json(&report);
    }
    println!(
        "FlowRAM, N1 {} N2 {}, {} Mamba layers, {} cameras at {} px, {} threads (median of {}):",
        report.n1, report.n2, report.layers, report.cameras, report.image_size, report.threads, args.repeats
    );
    println!(
        "  observation -> tokens (lifting, FPS): {:.1} ms; + image encoder and prefix scan: {:.1} ms",
        report.prepare_ms, report.encode_ms
    );
    for (name, t) in [("DRS", &report.infer_ms.drs), ("global", &report.infer_ms.global)] {
        println!(
            "  end to end, {name:>6}: 2 steps {:.0} ms, 4 {:.0}, 8 {:.0}, 16 {:.0}, 32 {:.0}",
            t.s2, t.s4, t.s8, t.s16, t.s32
        );
    }
    println!(
        "  8 DRS steps after encoding: token selection {:.1} ms, network {:.1} ms",
        report.drs8_steps.selection_ms, report.drs8_steps.network_ms
    );
    println!("  training step, batch {}: {:.0} ms", report.train_batch, report.train_step_ms);
    Ok(())
}

#[derive(Debug, Args)]
pub struct HeldOutArgs {
    /// A run folder or checkpoint folder.
    #[arg(long)]
    checkpoint: PathBuf,
    /// Held-out dataset folders (episodes the model did not train on), comma-separated.
    #[arg(long, value_delimiter = ',', required = true)]
    data: Vec<PathBuf>,
    /// The training dataset folders, for the baseline (their mean keyframe), comma-separated.
    #[arg(long, value_delimiter = ',', required = true)]
    train_data: Vec<PathBuf>,
    /// Euler steps (default: the config's).
    #[arg(long)]
    steps: Option<usize>,
    #[arg(long)]
    json: bool,
}

/// Held-out keyframe errors of a trained model against two trivial baselines: always the
/// training set's mean keyframe, and always the mean keyframe of the same task.
pub fn heldout_cmd(args: HeldOutArgs) -> anyhow::Result<()> {
    let mut policy = Policy::load(&args.checkpoint, TextEncoder::load_installed()?)?;
    let steps = args.steps.unwrap_or(policy.config().flow.sampling_steps);
    let train_set = load_training_data(&args.train_data)?;
    let held_out = load_training_data(&args.data)?;
    let report = heldout_errors(&mut policy, &train_set, &held_out, steps, &mut TaskBar::new("keyframes"))?;
    if args.json {
        return super::print_json(&report);
    }
    println!("{} held-out keyframes of {} episodes, {} Euler steps:", report.keyframes, report.episodes, steps);
    let line = |name: &str, e: &Errors| {
        println!(
            "  {name:>13}: position {:.1} mm mean / {:.1} median, rotation {:.1} deg mean / {:.1} median, gripper {:.0} % right",
            e.position_mm_mean,
            e.position_mm_median,
            e.rotation_deg_mean,
            e.rotation_deg_median,
            e.gripper_accuracy * 100.0
        );
    };
    line("model", &report.model);
    line("training mean", &report.training_mean);
    line("task mean", &report.task_mean);
    let swap = |mm: f64, n: usize| {
        println!(
            "  {:>13}: the first keyframe moves {mm:.1} mm (median of {n}) when told another variation",
            "instruction"
        )
    };
    swap(report.instruction_swap_mm, report.instruction_swaps);
    for t in &report.tasks {
        println!("  {} ({} keyframes):", t.task, t.keyframes);
        line("model", &t.model);
        line("task mean", &t.task_mean);
        swap(t.instruction_swap_mm, t.instruction_swaps);
    }
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

/// `flowram bench success`: closed-loop success rate of a trained policy on held-out seeds.
pub fn success_cmd(args: SuccessBenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.episodes > 0, "--episodes must be at least 1");
    let task_list = args.tasks.iter().map(|name| tasks::by_name(name)).collect::<Result<Vec<_>, _>>()?;
    let mut actor = args.learned.load_actor()?;
    let options = SuccessOptions {
        episodes: args.episodes,
        seed: args.seed,
        max_keyframes: args.learned.max_keyframes,
        cameras: args.learned.cameras.clone(),
    };
    let reports = success_rates(&mut actor, &task_list, &options, &mut TaskBar::new("episodes"))?;
    if args.json {
        return super::print_json(&reports);
    }
    for r in &reports {
        println!(
            "{}: {}/{} successes ({:.0} %, 95 % CI {:.0}-{:.0} %), {:.1} keyframes per episode, {:.0} % reached, inference {:.0} ms (median)",
            r.task,
            r.successes,
            r.episodes,
            100.0 * r.success_rate,
            100.0 * r.success_ci95[0],
            100.0 * r.success_ci95[1],
            r.keyframes,
            100.0 * r.reached,
            r.inference_ms_median
        );
    }
    Ok(())
}
