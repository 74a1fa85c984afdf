//! `flowram bench policy` (latency and training-step time), `bench heldout` (held-out keyframe
//! errors against trivial baselines) and `bench success` (closed-loop success rates).
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use flowram::data::Episode;
use flowram::policy::config::{Consensus, PolicyConfig};
use flowram::policy::inference::{Policy, SampleProfile, SamplingOptions};
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::policy::runtime::in_pool;
use flowram::policy::scene::observation::Observation;
use flowram::policy::training::data::TrainingData;
use flowram::policy::training::trainer::Trainer;
use flowram::rollout::collection::demonstration;
use flowram::rollout::evaluation::{Errors, SuccessOptions, SuccessRecord, TaskSuccess, heldout_errors, success_rates};
use flowram::rollout::learned::DEFAULT_CAMERAS;
use flowram::rollout::steps_grid::{plot_steps_grid, steps_grid};
use flowram::sim::Visuals;
use flowram::stats::{mcnemar_exact_p, median, wilson_interval};
use flowram::tasks;
use serde::Serialize;

use super::learned::{LearnedArgs, SharpeningArgs};
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
    /// Observations per second of that training step (x `train.flow_samples` flow samples).
    train_samples_per_s: f64,
    /// The shipped CPU config (models/policy/cpu.toml) at its own batch: step time, observations/s.
    cpu_config_train_step_ms: f64,
    cpu_config_train_batch: usize,
    cpu_config_train_samples_per_s: f64,
    /// The machine's single-precision GEMM peak on the policy's threads (1024^3 f32 matmul, best
    /// of the repeats), and what the 8 DRS steps end to end achieve against it.
    gemm_peak_gflops: f64,
    keyframe_gflop: f64,
    achieved_gflops: f64,
}

/// Best single-precision GEMM rate (GFLOP/s) of `repeats` 1024^3 products on the policy's pool.
fn gemm_peak_gflops(repeats: usize) -> anyhow::Result<f64> {
    const N: usize = 1024;
    let device = flowram::policy::network::model::device();
    let a = candle_core::Tensor::randn(0f32, 1.0, (N, N), &device)?;
    let b = candle_core::Tensor::randn(0f32, 1.0, (N, N), &device)?;
    in_pool(|| -> anyhow::Result<f64> {
        a.matmul(&b)?; // warm-up
        let mut best = f64::INFINITY;
        for _ in 0..repeats.max(5) {
            let t0 = Instant::now();
            let c = a.matmul(&b)?;
            best = best.min(t0.elapsed().as_secs_f64());
            drop(c);
        }
        Ok(2.0 * (N * N * N) as f64 / best / 1e9)
    })
}

/// Median training-step time (ms) of `config` at its batch on one demonstration.
fn time_training_step(config: &PolicyConfig, episode: &Episode, repeats: usize) -> anyhow::Result<f64> {
    let mut trainer = Trainer::new(config)?;
    let mut data = TrainingData::from_episodes(vec![episode.clone()])?;
    let mut text = TextEncoder::load_installed()?;
    trainer.train_step(&mut data, &mut text)?; // prepares the observations once
    let mut train_ms = Vec::new();
    for _ in 0..repeats {
        let t0 = Instant::now();
        trainer.train_step(&mut data, &mut text)?;
        train_ms.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    Ok(median(&train_ms))
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
                policy.predict(&observation, &SamplingOptions { drs, ..SamplingOptions::new(steps, 1, r as u64) })?;
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
        policy.sample_profiled(&prepared, &encoded, &SamplingOptions::new(8, 1, r as u64), &mut profile)?;
        profiles.push(profile);
    }
    let drs8 = SampleProfile {
        selection_ms: median(&profiles.iter().map(|p| p.selection_ms).collect::<Vec<_>>()),
        network_ms: median(&profiles.iter().map(|p| p.network_ms).collect::<Vec<_>>()),
    };
    // Training step at the requested batch size, on the rendered demonstration, and the shipped
    // CPU config's at its own.
    let mut train_config = config.clone();
    train_config.train.batch = args.train_batch;
    train_config.validate()?;
    let train_step_ms = time_training_step(&train_config, &episode, args.repeats)?;
    let cpu_config = PolicyConfig::cpu_default()?;
    let cpu_step_ms = time_training_step(&cpu_config, &episode, args.repeats)?;
    let cameras = if config.observation.cameras.is_empty() {
        observation.cameras.len()
    } else {
        config.observation.cameras.len()
    };
    let keyframe_flops = policy.model.keyframe_flops(cameras, 8);
    let gemm_peak = gemm_peak_gflops(args.repeats)?;
    let drs8_ms = infer_ms.drs.s8;
    let report = PolicyBenchReport {
        n1: config.observation.semantic_tokens,
        n2: config.observation.geometric_tokens,
        layers: config.model.layers,
        cameras,
        image_size: config.observation.image_size,
        threads: rayon::current_num_threads(),
        prepare_ms: median(&prepare_ms),
        encode_ms: median(&encode_ms),
        infer_ms,
        drs8_steps: drs8,
        train_step_ms,
        train_batch: args.train_batch,
        train_samples_per_s: args.train_batch as f64 / (train_step_ms / 1e3),
        cpu_config_train_step_ms: cpu_step_ms,
        cpu_config_train_batch: cpu_config.train.batch,
        cpu_config_train_samples_per_s: cpu_config.train.batch as f64 / (cpu_step_ms / 1e3),
        gemm_peak_gflops: gemm_peak,
        keyframe_gflop: keyframe_flops / 1e9,
        achieved_gflops: keyframe_flops / 1e9 / (drs8_ms / 1e3),
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
    println!(
        "  8 DRS steps: {:.2} GFLOP per keyframe, {:.1} GFLOP/s achieved = {:.0} % of this machine's GEMM peak ({:.1} GFLOP/s, {} threads)",
        report.keyframe_gflop,
        report.achieved_gflops,
        100.0 * report.achieved_gflops / report.gemm_peak_gflops,
        report.gemm_peak_gflops,
        report.threads
    );
    println!(
        "  training step, batch {}: {:.0} ms ({:.1} observations/s)",
        report.train_batch, report.train_step_ms, report.train_samples_per_s
    );
    println!(
        "  shipped CPU config (models/policy/cpu.toml) training step, batch {}: {:.0} ms ({:.1} observations/s)",
        report.cpu_config_train_batch, report.cpu_config_train_step_ms, report.cpu_config_train_samples_per_s
    );
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
    #[arg(long, value_parser = super::at_least_one)]
    steps: Option<usize>,
    /// Keyframe samples per observation, scored their consensus (default: the config's
    /// flow.consensus_samples).
    #[arg(long, value_parser = super::at_least_one)]
    samples: Option<usize>,
    /// Which sample is scored: medoid or mode (default: the config's flow.consensus).
    #[arg(long, value_parser = super::consensus_rule)]
    consensus: Option<Consensus>,
    #[command(flatten)]
    sharpening: SharpeningArgs,
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
    let samples = args.samples.unwrap_or(policy.config().flow.consensus_samples);
    let consensus = args.consensus.unwrap_or(policy.config().flow.consensus);
    let sharpening = args.sharpening.over(policy.config());
    let options = SamplingOptions { steps, samples, drs: true, seed: 0, consensus, sharpening };
    let report = heldout_errors(&mut policy, &train_set, &held_out, &options, &mut TaskBar::new("keyframes"))?;
    if args.json {
        return super::print_json(&report);
    }
    println!(
        "{} held-out keyframes of {} episodes, {} Euler steps, consensus ({}) of {} samples, pointer temperature {}:",
        report.keyframes,
        report.episodes,
        steps,
        consensus.name(),
        samples,
        report.pointer_temperature
    );
    let line = |name: &str, e: &Errors| {
        println!(
            "  {name:>13}: position {:.1} mm mean / {:.1} median (bias x {:+.1} y {:+.1} z {:+.1}), rotation {:.1} deg mean / {:.1} median, gripper {:.0} % right",
            e.position_mm_mean,
            e.position_mm_median,
            e.position_bias_mm[0],
            e.position_bias_mm[1],
            e.position_bias_mm[2],
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
    let target = |accuracy: f64, n: usize| {
        println!(
            "  {:>13}: the instructed target is the nearest in {:.0} % of {n} keyframes the instruction decides",
            "target",
            100.0 * accuracy
        )
    };
    swap(report.instruction_swap_mm, report.instruction_swaps);
    target(report.target_accuracy, report.target_choices);
    for t in &report.tasks {
        println!("  {} ({} keyframes):", t.task, t.keyframes);
        line("model", &t.model);
        line("task mean", &t.task_mean);
        swap(t.instruction_swap_mm, t.instruction_swaps);
        target(t.target_accuracy, t.target_choices);
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
    /// A second checkpoint, run on the same seeds with the same sampling options: both success
    /// tables are printed, with the paired comparison (seeds only one of them solved, exact
    /// McNemar p-value) per task and over all tasks.
    #[arg(long)]
    baseline: Option<PathBuf>,
    /// Results file: every episode's outcome is written to it as it finishes, with a manifest
    /// (revision, checkpoint digest, options, shard); a re-run with the same arguments skips the
    /// episodes it holds. Required with more than one shard (`flowram merge` combines them).
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    shard: super::ShardArgs,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
pub struct CompareArgs {
    /// The results file of the arm under test (`bench success --out`, whole or merged).
    results: PathBuf,
    /// The results file it is compared with: the same tasks, seeds and episodes.
    baseline: PathBuf,
    #[arg(long)]
    json: bool,
}

/// `flowram bench compare`: two recorded evaluations paired on their seeds.
pub fn compare_cmd(args: CompareArgs) -> anyhow::Result<()> {
    let read = |path: &Path| -> anyhow::Result<SuccessRecord> {
        let mut record = SuccessRecord::read(path)?.ok_or_else(|| {
            anyhow::anyhow!("{}: no such results file (write one with `bench success --out`)", path.display())
        })?;
        anyhow::ensure!(
            record.shard.is_whole() && record.complete(),
            "{}: an incomplete or single-shard results file; finish it (re-run the same `bench success`) or `flowram \
             merge` its shards first",
            path.display()
        );
        record.outcomes.sort_by_key(|o| (o.task, o.outcome.seed));
        Ok(record)
    };
    let (a, b) = (read(&args.results)?, read(&args.baseline)?);
    anyhow::ensure!(
        (&a.tasks, a.seed, a.episodes) == (&b.tasks, b.seed, b.episodes),
        "{} and {} are not on the same episodes: tasks {:?}, seeds {}+{} against tasks {:?}, seeds {}+{}",
        args.results.display(),
        args.baseline.display(),
        a.tasks,
        a.seed,
        a.episodes,
        b.tasks,
        b.seed,
        b.episodes
    );
    if !a.expert_versions.is_empty() && !b.expert_versions.is_empty() {
        anyhow::ensure!(
            a.expert_versions == b.expert_versions,
            "{} and {} are not on the same scenes: expert versions {} against {} (a task's new expert version \
             changes what its seeds show; evaluate both checkpoints with this build)",
            args.results.display(),
            args.baseline.display(),
            a.expert_versions_text(),
            b.expert_versions_text()
        );
    } else {
        for (path, r) in [(&args.results, &a), (&args.baseline, &b)] {
            if r.expert_versions.is_empty() {
                eprintln!(
                    "warning: {} predates recorded expert versions; a task whose expert changed since it was made \
                     (push_buttons: version 2 on 2026-12-07) shows other scenes at the same seeds",
                    path.display()
                );
            }
        }
    }
    if !args.json {
        // Arms of one checkpoint differ only here (MODE and SHARP in docs/experiments.md).
        let sampling = |r: &SuccessRecord| {
            format!(
                "weights {}, {} steps, {} samples ({}), pointer temperature {}{}{}{}, DRS {}",
                r.checkpoint_digest,
                r.steps,
                r.samples,
                r.consensus.name(),
                r.pointer_temperature,
                if r.pointer_posterior { ", pointer posterior" } else { "" },
                if r.pointer_posterior_width > 0.0 {
                    format!(" (width {} m)", r.pointer_posterior_width)
                } else {
                    String::new()
                },
                if r.pointer_guidance != 1.0 { format!(", guidance {}", r.pointer_guidance) } else { String::new() },
                r.drs
            )
        };
        println!("checkpoint: {}\nbaseline:   {}", sampling(&a), sampling(&b));
    }
    let (reports, baseline_reports) = (a.table(), b.table());
    let comparison = paired_comparison(&reports, &baseline_reports);
    print_comparison(&args.baseline, &reports, &baseline_reports, &comparison, args.json)
}

#[derive(Debug, Args)]
pub struct GridArgs {
    /// Results files of `bench success --out` (whole or merged), one per cell: the same tasks,
    /// seeds, keyframe limit, cameras, samples, consensus and pointer temperature, differing in
    /// checkpoint, --steps and --no-drs.
    #[arg(required = true)]
    results: Vec<PathBuf>,
    /// Draw the grid to this PNG: success and latency against Euler steps, one line per arm.
    #[arg(long)]
    plot: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

/// `flowram bench grid`: success and latency against Euler steps and DRS (Table C).
pub fn grid_cmd(args: GridArgs) -> anyhow::Result<()> {
    let mut records = Vec::with_capacity(args.results.len());
    for path in &args.results {
        let record = SuccessRecord::read(path)?.ok_or_else(|| {
            anyhow::anyhow!("{}: no such results file (write one with `bench success --out`)", path.display())
        })?;
        records.push((path.clone(), record));
    }
    let cells = steps_grid(&records)?;
    if let Some(plot) = &args.plot {
        plot_steps_grid(&cells, plot, 1200, 450)?;
    }
    if args.json {
        return super::print_json(&cells);
    }
    let tasks: Vec<&str> = cells[0].tasks.iter().map(|t| t.task.as_str()).collect();
    println!("{} episodes per cell ({}):", cells[0].episodes, tasks.join(", "));
    for c in &cells {
        let per_task: Vec<String> = c.tasks.iter().map(|t| format!("{}/{}", t.successes, t.episodes)).collect();
        println!(
            "  {} | {:>2} steps: {}/{} ({:.0} %, 95 % CI {:.0}-{:.0} %) [{}], inference {:.0} ms (median)",
            c.arm,
            c.steps,
            c.successes,
            c.episodes,
            100.0 * c.success_rate,
            100.0 * c.success_ci95[0],
            100.0 * c.success_ci95[1],
            per_task.join(" "),
            c.inference_ms_median
        );
    }
    if let Some(plot) = &args.plot {
        println!("plot: {}", plot.display());
    }
    Ok(())
}

/// One task's (or all tasks', `task = "all"`) paired comparison of two checkpoints.
#[derive(Debug, Serialize)]
struct PairedComparison {
    task: String,
    /// Seeds the checkpoint solved and the baseline did not.
    only_checkpoint: usize,
    /// Seeds the baseline solved and the checkpoint did not.
    only_baseline: usize,
    /// Exact McNemar test of "equally good".
    p_value: f64,
}

/// `flowram bench success`: closed-loop success rate of a trained policy on held-out seeds.
pub fn success_cmd(args: SuccessBenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.episodes > 0, "--episodes must be at least 1");
    let task_list = args.tasks.iter().map(|name| tasks::by_name(name)).collect::<Result<Vec<_>, _>>()?;
    let shard = args.shard.resolve()?;
    anyhow::ensure!(
        shard.is_whole() || args.out.is_some(),
        "shard {} of {} needs --out FILE: each shard writes its own results file, and `flowram merge` combines them",
        shard.index,
        shard.count
    );
    anyhow::ensure!(
        args.baseline.is_none() || (shard.is_whole() && args.out.is_none()),
        "--baseline runs both checkpoints in one process: leave out --out and the shard flags, or evaluate each \
         checkpoint into its own --out files"
    );
    let options = SuccessOptions {
        episodes: args.episodes,
        seed: args.seed,
        max_keyframes: args.learned.max_keyframes,
        cameras: args.learned.cameras.clone(),
        shard,
    };
    let mut actor = args.learned.load_actor(&args.tasks.iter().map(String::as_str).collect::<Vec<_>>())?;
    // Loaded before any episode runs, so that a bad --baseline fails at once.
    let mut baseline_actor = args.baseline.as_deref().map(|path| args.learned.load_actor_from(path)).transpose()?;
    let mut record = SuccessRecord::new(&actor, &task_list, &options)?;
    if let Some(out) = &args.out {
        record.resume_from(out)?;
        record.write(out)?;
    }
    let out = args.out.clone();
    let mut save = |r: &SuccessRecord| match &out {
        Some(path) => r.write(path),
        None => Ok(()),
    };
    let reports =
        success_rates(&mut actor, &task_list, &options, &mut record, &mut save, &mut TaskBar::new("episodes"))?;
    drop(actor);
    let (Some(baseline), Some(baseline_actor)) = (&args.baseline, baseline_actor.as_mut()) else {
        if args.json {
            return super::print_json(&reports);
        }
        if !shard.is_whole() {
            println!("shard {} of {} (merge all shards' --out files with `flowram merge`):", shard.index, shard.count);
        }
        print_success_table(&reports);
        return Ok(());
    };
    let mut baseline_record = SuccessRecord::new(baseline_actor, &task_list, &options)?;
    let baseline_reports = success_rates(
        baseline_actor,
        &task_list,
        &options,
        &mut baseline_record,
        &mut |_| Ok(()),
        &mut TaskBar::new("baseline"),
    )?;
    let comparison = paired_comparison(&reports, &baseline_reports);
    print_comparison(baseline, &reports, &baseline_reports, &comparison, args.json)
}

/// Both success tables and their paired comparison (`bench success --baseline`, `bench compare`).
fn print_comparison(
    baseline: &Path,
    reports: &[TaskSuccess],
    baseline_reports: &[TaskSuccess],
    comparison: &[PairedComparison],
    json: bool,
) -> anyhow::Result<()> {
    if json {
        #[derive(Serialize)]
        struct Compared<'a> {
            checkpoint: &'a [TaskSuccess],
            baseline: &'a [TaskSuccess],
            comparison: &'a [PairedComparison],
        }
        return super::print_json(&Compared { checkpoint: reports, baseline: baseline_reports, comparison });
    }
    println!("checkpoint:");
    print_success_table(reports);
    println!("baseline ({}):", baseline.display());
    print_success_table(baseline_reports);
    println!("paired on the same seeds:");
    for c in comparison {
        println!(
            "  {}: {} seeds solved only by the checkpoint, {} only by the baseline (exact McNemar p = {:.3})",
            c.task, c.only_checkpoint, c.only_baseline, c.p_value
        );
    }
    Ok(())
}

pub(super) fn print_success_table(reports: &[TaskSuccess]) {
    for r in reports {
        println!(
            "  {}: {}/{} successes ({:.0} %, 95 % CI {:.0}-{:.0} %), {:.1} keyframes per episode, {:.0} % reached, inference {:.0} ms (median)",
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
    if reports.len() > 1 {
        let successes: usize = reports.iter().map(|r| r.successes).sum();
        let episodes: usize = reports.iter().map(|r| r.episodes).sum();
        let ci = wilson_interval(successes, episodes);
        let task_mean = reports.iter().map(|r| r.success_rate).sum::<f64>() / reports.len() as f64;
        let worst = reports.iter().map(|r| r.success_rate).fold(f64::INFINITY, f64::min);
        println!(
            "  all: {successes}/{episodes} successes ({:.0} %, 95 % CI {:.0}-{:.0} %), task mean {:.0} %, worst task {:.0} %",
            100.0 * successes as f64 / episodes as f64,
            100.0 * ci[0],
            100.0 * ci[1],
            100.0 * task_mean,
            100.0 * worst
        );
    }
}

/// Seeds solved by only one of the two (same tasks and seeds, in the same order).
fn paired_comparison(checkpoint: &[TaskSuccess], baseline: &[TaskSuccess]) -> Vec<PairedComparison> {
    let mut rows = Vec::with_capacity(checkpoint.len() + 1);
    let (mut all_a, mut all_b) = (0, 0);
    for (a, b) in checkpoint.iter().zip(baseline) {
        let pairs = a.outcomes.iter().zip(&b.outcomes);
        let only_a = pairs.clone().filter(|(x, y)| x.success && !y.success).count();
        let only_b = pairs.filter(|(x, y)| !x.success && y.success).count();
        (all_a, all_b) = (all_a + only_a, all_b + only_b);
        rows.push(PairedComparison {
            task: a.task.clone(),
            only_checkpoint: only_a,
            only_baseline: only_b,
            p_value: mcnemar_exact_p(only_a, only_b),
        });
    }
    if checkpoint.len() > 1 {
        rows.push(PairedComparison {
            task: "all".into(),
            only_checkpoint: all_a,
            only_baseline: all_b,
            p_value: mcnemar_exact_p(all_a, all_b),
        });
    }
    rows
}
