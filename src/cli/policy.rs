//! `flowram train`, `flowram predict` and `flowram bench policy`.
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use flowram::deps::Deps;
use flowram::policy::config::PolicyConfig;
use flowram::policy::inference::{Policy, SampleProfile, SamplingOptions};
use flowram::policy::scene::observation::Observation;
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::policy::training::data::TrainingData;
use flowram::policy::training::trainer::{StepLoss, TrainProgress, Trainer, train};
use serde::Serialize;

use super::bench::median;

pub fn text_encoder() -> anyhow::Result<TextEncoder> {
    let dir = Deps::locate().minilm_dir()?;
    Ok(TextEncoder::load(&dir)?)
}

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Dataset folders (from `flowram collect`), comma-separated.
    #[arg(long, value_delimiter = ',', required = true)]
    data: Vec<PathBuf>,
    /// Run folder: checkpoints/, metrics.csv, loss.png.
    #[arg(long)]
    out: PathBuf,
    /// Policy config (TOML); default models/policy/cpu.toml. Ignored with --resume (the run's own).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Total optimiser steps (overrides the config's train.steps).
    #[arg(long)]
    steps: Option<usize>,
    /// Batch size (overrides the config's train.batch; not with --resume).
    #[arg(long)]
    batch: Option<usize>,
    /// Continue the run in --out from its latest checkpoint, exactly.
    #[arg(long)]
    resume: bool,
}

struct Bar(indicatif::ProgressBar);

impl TrainProgress for Bar {
    fn step(&mut self, step: u64, total: u64, loss: &StepLoss) {
        self.0.set_length(total);
        self.0.set_position(step);
        self.0.set_message(format!("loss {:.4} (cfm {:.4}, open {:.4})", loss.total, loss.cfm, loss.bce));
    }
}

pub fn train_cmd(args: TrainArgs) -> anyhow::Result<()> {
    let config = if args.resume {
        if args.config.is_some() || args.batch.is_some() {
            bail!("--resume continues the run with its own config: leave out --config and --batch");
        }
        None
    } else {
        let mut c = match &args.config {
            Some(p) => PolicyConfig::from_toml_file(p)?,
            None => PolicyConfig::cpu_default()?,
        };
        if let Some(b) = args.batch {
            c.train.batch = b;
        }
        c.validate()?;
        Some(c)
    };
    let mut data = TrainingData::load(&args.data)?;
    eprintln!("training on {} episodes, {} keyframe samples", data.episodes().len(), data.samples());
    let mut text = text_encoder()?;
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} [{bar:30}] step {pos}/{len} {msg}, {elapsed_precise} (eta {eta})",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let trainer =
        train(&args.out, config.as_ref(), &mut data, &mut text, args.resume, args.steps, &mut Bar(bar.clone()))?;
    bar.finish();
    eprintln!(
        "trained to step {} in {:.0} s; checkpoints in {}, metrics.csv and loss.png beside them",
        trainer.step,
        trainer.elapsed_seconds,
        args.out.join("checkpoints").display()
    );
    Ok(())
}

#[derive(Debug, Args)]
pub struct PredictArgs {
    /// A run folder (runs/NAME: its latest checkpoint) or a checkpoint folder.
    #[arg(long)]
    checkpoint: PathBuf,
    /// An episode file of a dataset (episode_*.safetensors).
    #[arg(long)]
    episode: PathBuf,
    #[arg(long)]
    keyframe: usize,
    /// Euler steps (default: the config's flow.sampling_steps).
    #[arg(long)]
    steps: Option<usize>,
    #[arg(long, default_value_t = 1)]
    samples: usize,
    /// The w/o-DRS ablation: geometric tokens sampled globally at every step.
    #[arg(long)]
    no_drs: bool,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct Prediction {
    keyframe: flowram::policy::scene::observation::KeyframePose,
    position_error_mm: f32,
    rotation_error_deg: f32,
    gripper_correct: bool,
}

#[derive(Serialize)]
struct PredictReport {
    episode: PathBuf,
    keyframe: usize,
    instruction: String,
    steps: usize,
    drs: bool,
    recorded: flowram::policy::scene::observation::KeyframePose,
    predictions: Vec<Prediction>,
    seconds: f64,
}

pub fn predict_cmd(args: PredictArgs) -> anyhow::Result<()> {
    let mut policy = Policy::load(&args.checkpoint, text_encoder()?)?;
    let episode = flowram::data::read_episode(&args.episode)?;
    let observation = Observation::from_episode(&episode, args.keyframe)?;
    let recorded = Observation::episode_action(&episode, args.keyframe);
    let steps = args.steps.unwrap_or(policy.config().flow.sampling_steps);
    let started = Instant::now();
    let keyframes = policy
        .predict(&observation, &SamplingOptions { steps, samples: args.samples, drs: !args.no_drs, seed: args.seed })?;
    let seconds = started.elapsed().as_secs_f64();
    let predictions: Vec<Prediction> = keyframes
        .into_iter()
        .map(|k| {
            let (p, r) = k.error_to(&recorded);
            Prediction {
                keyframe: k,
                position_error_mm: p * 1e3,
                rotation_error_deg: r.to_degrees(),
                gripper_correct: k.gripper_open == recorded.gripper_open,
            }
        })
        .collect();
    let report = PredictReport {
        episode: args.episode.clone(),
        keyframe: args.keyframe,
        instruction: observation.instruction.clone(),
        steps,
        drs: !args.no_drs,
        recorded,
        predictions,
        seconds,
    };
    if args.json {
        return super::print_json(&report);
    }
    println!(
        "{} keyframe {}: \"{}\" ({} Euler steps, DRS {})",
        report.episode.display(),
        report.keyframe,
        report.instruction,
        steps,
        if report.drs { "on" } else { "off" }
    );
    let show = |k: &flowram::policy::scene::observation::KeyframePose| {
        format!(
            "position [{:.4}, {:.4}, {:.4}] m, quat wxyz [{:.3}, {:.3}, {:.3}, {:.3}], {}",
            k.position[0],
            k.position[1],
            k.position[2],
            k.quat_wxyz[0],
            k.quat_wxyz[1],
            k.quat_wxyz[2],
            k.quat_wxyz[3],
            if k.gripper_open { "open" } else { "closed" }
        )
    };
    println!("  recorded:  {}", show(&report.recorded));
    for (i, p) in report.predictions.iter().enumerate() {
        println!(
            "  sample {i}: {}\n             error {:.1} mm, {:.1} deg, gripper {}",
            show(&p.keyframe),
            p.position_error_mm,
            p.rotation_error_deg,
            if p.gripper_correct { "right" } else { "wrong" }
        );
    }
    println!("  {:.0} ms", seconds * 1e3);
    Ok(())
}

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
    let text = text_encoder()?;
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
    let episode = demonstration(config.observation.image_size).context("rendering the benchmark's observation")?;
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
    let mut text = text_encoder()?;
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

/// One expert demonstration of open_drawer with all four cameras at `size` pixels.
fn demonstration(size: usize) -> anyhow::Result<flowram::data::Episode> {
    use flowram::sim::{CameraRig, Visuals};
    use flowram::tasks::{
        self,
        episode::{Actor, Observer, run_episode},
    };
    let task = tasks::by_name("open_drawer")?;
    let mut world = tasks::load_world(task.as_ref())?;
    let mut rig = CameraRig::new(&world, size, Visuals::Full)?;
    let cameras = ["front", "left_shoulder", "right_shoulder", "wrist"]
        .iter()
        .map(|c| rig.camera_index(c))
        .collect::<Result<Vec<_>, _>>()?;
    let mut observer = Observer { rig: &mut rig, cameras };
    let result = run_episode(task.as_ref(), &mut world, 0, 0, Actor::Expert, Some(&mut observer))?;
    result.to_dataset_episode().context("the demonstration has no images")
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

#[derive(Serialize, Default)]
struct Errors {
    position_mm_mean: f64,
    position_mm_median: f64,
    rotation_deg_mean: f64,
    rotation_deg_median: f64,
    gripper_accuracy: f64,
}

#[derive(Serialize)]
struct HeldOutErrors {
    /// The task's name, or "all".
    task: String,
    keyframes: usize,
    model: Errors,
    /// Always the training set's mean keyframe.
    training_mean: Errors,
    /// Always the mean keyframe of the training episodes of the same task (the instruction names
    /// the task, so this is what a model that ignores the scene could reach).
    task_mean: Errors,
}

#[derive(Serialize)]
struct HeldOutReport {
    keyframes: usize,
    episodes: usize,
    steps: usize,
    model: Errors,
    training_mean: Errors,
    task_mean: Errors,
    /// The same per task.
    tasks: Vec<HeldOutErrors>,
    seconds: f64,
}

fn summarise(rows: &[(f32, f32, bool)]) -> Errors {
    let n = rows.len().max(1) as f64;
    let pos: Vec<f64> = rows.iter().map(|r| f64::from(r.0) * 1e3).collect();
    let rot: Vec<f64> = rows.iter().map(|r| f64::from(r.1).to_degrees()).collect();
    Errors {
        position_mm_mean: pos.iter().sum::<f64>() / n,
        position_mm_median: median(&pos),
        rotation_deg_mean: rot.iter().sum::<f64>() / n,
        rotation_deg_median: median(&rot),
        gripper_accuracy: rows.iter().filter(|r| r.2).count() as f64 / n,
    }
}

/// The mean keyframe of `episodes` (mean position, chordal-mean rotation, majority gripper).
fn mean_keyframe<'a>(
    episodes: impl Iterator<Item = &'a flowram::data::Episode>,
) -> anyhow::Result<flowram::policy::scene::observation::KeyframePose> {
    let mut sum = [0f64; 9];
    let (mut count, mut open) = (0usize, 0usize);
    for e in episodes {
        for k in 0..e.keyframes() {
            let a = Observation::episode_action(e, k);
            let r = flowram::policy::scene::rotation::quaternion_to_6d(a.quat_wxyz)?;
            for i in 0..3 {
                sum[i] += f64::from(a.position[i]);
            }
            for i in 0..6 {
                sum[3 + i] += f64::from(r[i]);
            }
            count += 1;
            open += usize::from(a.gripper_open);
        }
    }
    anyhow::ensure!(count > 0, "the training datasets hold no keyframes");
    let mean = |i: usize| (sum[i] / count as f64) as f32;
    Ok(flowram::policy::scene::observation::KeyframePose {
        position: [mean(0), mean(1), mean(2)],
        quat_wxyz: flowram::policy::scene::rotation::quaternion_from_6d(std::array::from_fn(|i| mean(3 + i))),
        gripper_open: 2 * open >= count,
    })
}

/// Held-out keyframe errors of a trained model against two trivial baselines: always the
/// training set's mean keyframe, and always the mean keyframe of the same task.
pub fn heldout_cmd(args: HeldOutArgs) -> anyhow::Result<()> {
    let mut policy = Policy::load(&args.checkpoint, text_encoder()?)?;
    let steps = args.steps.unwrap_or(policy.config().flow.sampling_steps);
    let train_set = TrainingData::load(&args.train_data)?;
    let baseline = mean_keyframe(train_set.episodes().iter())?;
    let held_out = TrainingData::load(&args.data)?;
    let mut task_names: Vec<String> = held_out.episodes().iter().map(|e| e.task.clone()).collect();
    task_names.sort();
    task_names.dedup();
    let started = Instant::now();
    // per held-out keyframe: task index, (model, training mean, task mean) errors
    let mut rows: Vec<(usize, [(f32, f32, bool); 3])> = Vec::new();
    for (ti, task) in task_names.iter().enumerate() {
        let task_baseline = mean_keyframe(train_set.episodes().iter().filter(|e| &e.task == task))
            .with_context(|| format!("no training episodes of task {task} for its baseline"))?;
        for e in held_out.episodes().iter().filter(|e| &e.task == task) {
            for k in 0..e.keyframes() {
                let observation = Observation::from_episode(e, k)?;
                let target = Observation::episode_action(e, k);
                let predicted =
                    policy.predict(&observation, &SamplingOptions { steps, samples: 1, drs: true, seed: k as u64 })?[0];
                let row = |p: &flowram::policy::scene::observation::KeyframePose| {
                    let (d, r) = p.error_to(&target);
                    (d, r, p.gripper_open == target.gripper_open)
                };
                rows.push((ti, [row(&predicted), row(&baseline), row(&task_baseline)]));
            }
        }
    }
    let errors = |name: &str, filter: &dyn Fn(usize) -> bool| {
        let pick = |j: usize| rows.iter().filter(|r| filter(r.0)).map(|r| r.1[j]).collect::<Vec<_>>();
        HeldOutErrors {
            task: name.to_string(),
            keyframes: rows.iter().filter(|r| filter(r.0)).count(),
            model: summarise(&pick(0)),
            training_mean: summarise(&pick(1)),
            task_mean: summarise(&pick(2)),
        }
    };
    let all = errors("all", &|_| true);
    let tasks = task_names.iter().enumerate().map(|(ti, name)| errors(name, &|t| t == ti)).collect();
    let report = HeldOutReport {
        keyframes: all.keyframes,
        episodes: held_out.episodes().len(),
        steps,
        model: all.model,
        training_mean: all.training_mean,
        task_mean: all.task_mean,
        tasks,
        seconds: started.elapsed().as_secs_f64(),
    };
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
    for t in &report.tasks {
        println!("  {} ({} keyframes):", t.task, t.keyframes);
        line("model", &t.model);
        line("task mean", &t.task_mean);
    }
    Ok(())
}
