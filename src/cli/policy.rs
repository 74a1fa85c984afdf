//! `flowram train` and `flowram predict`.
use std::path::PathBuf;
use std::time::Instant;

use anyhow::bail;
use clap::Args;
use flowram::policy::PolicyError;
use flowram::policy::config::{Consensus, PolicyConfig};
use flowram::policy::inference::{PointerReadout, Policy, Samples, SamplingOptions, consensus};
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::policy::scene::observation::{KeyframePose, Observation};
use flowram::policy::training::data::TrainingData;
use flowram::policy::training::trainer::train;
use flowram::rollout::collection::stale_expert;
use serde::Serialize;

use super::learned::SharpeningArgs;
use super::progress::TrainBar;

/// Loads training datasets, reporting the episode files it had to skip and the datasets
/// collected with an older version of their task's expert.
pub fn load_training_data(dirs: &[PathBuf]) -> anyhow::Result<TrainingData> {
    for dir in dirs {
        if let Some(warning) = stale_expert(dir)? {
            eprintln!("warning: {warning}");
        }
    }
    let read = TrainingData::read_datasets(dirs)?;
    for (path, reason) in &read.skipped {
        eprintln!("warning: skipping {}: {reason}", path.display());
    }
    Ok(TrainingData::from_episodes(read.episodes)?)
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
    let mut data = load_training_data(&args.data)?;
    eprintln!("training on {} episodes, {} keyframe samples", data.episodes().len(), data.samples());
    let mut text = TextEncoder::load_installed()?;
    let mut bar = TrainBar::new();
    let trainer = match train(&args.out, config.as_ref(), &mut data, &mut text, args.resume, args.steps, &mut bar) {
        Ok(trainer) => trainer,
        Err(e @ PolicyError::RunHasCheckpoints { .. }) => {
            bail!("{e}: pass --resume to continue it, or choose another --out")
        }
        Err(e @ PolicyError::NoCheckpoint { .. }) => bail!("{e}: start the run without --resume"),
        Err(e) => return Err(e.into()),
    };
    bar.0.finish();
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
    #[arg(long, value_parser = super::at_least_one)]
    steps: Option<usize>,
    /// Keyframe samples to draw (all are printed, their consensus marked).
    #[arg(long, default_value_t = 1, value_parser = super::at_least_one)]
    samples: usize,
    /// Which sample is executed: medoid or mode (default: the checkpoint's flow.consensus).
    #[arg(long, value_parser = super::consensus_rule)]
    consensus: Option<Consensus>,
    #[command(flatten)]
    sharpening: SharpeningArgs,
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
    keyframe: KeyframePose,
    position_error_mm: f32,
    rotation_error_deg: f32,
    gripper_correct: bool,
    /// The sample's pointers at its last Euler step (world frame, m); absent without
    /// `model.position_pointer`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pointer: Option<PointerReadout>,
}

#[derive(Serialize)]
struct PredictReport {
    episode: PathBuf,
    keyframe: usize,
    instruction: String,
    steps: usize,
    drs: bool,
    consensus: &'static str,
    pointer_temperature: f64,
    pointer_posterior: bool,
    /// m (0: candidates are points).
    pointer_posterior_width: f64,
    /// The instruction's guidance of the pointer (1: as trained).
    pointer_guidance: f64,
    /// The index in `predictions` of the sample a closed-loop run executes (their consensus).
    executed: usize,
    recorded: KeyframePose,
    predictions: Vec<Prediction>,
    seconds: f64,
}

pub fn predict_cmd(args: PredictArgs) -> anyhow::Result<()> {
    let mut policy = Policy::load(&args.checkpoint, TextEncoder::load_installed()?)?;
    let episode = flowram::data::read_episode(&args.episode)?;
    let observation = Observation::from_episode(&episode, args.keyframe)?;
    let recorded = Observation::episode_action(&episode, args.keyframe);
    let steps = args.steps.unwrap_or(policy.config().flow.sampling_steps);
    let started = Instant::now();
    let options = SamplingOptions {
        steps,
        samples: args.samples,
        drs: !args.no_drs,
        seed: args.seed,
        consensus: args.consensus.unwrap_or(policy.config().flow.consensus),
        sharpening: args.sharpening.over(policy.config()),
    };
    let Samples { poses: keyframes, pointers } = policy.predict_explained(&observation, &options)?;
    let seconds = started.elapsed().as_secs_f64();
    let chosen = consensus(&keyframes, options.consensus);
    let executed = keyframes.iter().position(|k| Some(*k) == chosen).unwrap_or(0);
    let predictions: Vec<Prediction> = keyframes
        .into_iter()
        .enumerate()
        .map(|(i, k)| {
            let (p, r) = k.error_to(&recorded);
            Prediction {
                keyframe: k,
                position_error_mm: p * 1e3,
                rotation_error_deg: r.to_degrees(),
                gripper_correct: k.gripper_open == recorded.gripper_open,
                pointer: pointers.get(i).copied(),
            }
        })
        .collect();
    let report = PredictReport {
        episode: args.episode.clone(),
        keyframe: args.keyframe,
        instruction: observation.instruction.clone(),
        steps,
        drs: options.samples_with_drs(policy.config().radius_schedule),
        consensus: options.consensus.name(),
        pointer_temperature: options.sharpening.temperature,
        pointer_posterior: options.sharpening.posterior,
        pointer_posterior_width: options.sharpening.posterior_width,
        pointer_guidance: options.sharpening.guidance,
        executed,
        recorded,
        predictions,
        seconds,
    };
    if args.json {
        return super::print_json(&report);
    }
    println!(
        "{} keyframe {}: \"{}\" ({} Euler steps, DRS {}, pointer temperature {}, consensus {})",
        report.episode.display(),
        report.keyframe,
        report.instruction,
        steps,
        if report.drs { "on" } else { "off" },
        report.pointer_temperature,
        report.consensus
    );
    let show = |k: &KeyframePose| {
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
            "  sample {i}: {}{}\n             error {:.1} mm, {:.1} deg, gripper {}",
            show(&p.keyframe),
            if i == report.executed && report.predictions.len() > 1 { " (executed)" } else { "" },
            p.position_error_mm,
            p.rotation_error_deg,
            if p.gripper_correct { "right" } else { "wrong" }
        );
        if let Some(r) = &p.pointer {
            let v = |x: [f32; 3]| format!("[{:.4}, {:.4}, {:.4}]", x[0], x[1], x[2]);
            let relation = match (r.goal, r.beta) {
                (Some(g), Some(b)) => format!(", instruction pointer {} m, beta {b:.3}", v(g)),
                _ => String::new(),
            };
            println!("             position pointer {} m{relation}", v(r.pointed));
        }
    }
    println!("  {:.0} ms", seconds * 1e3);
    Ok(())
}
