//! Subcommands: parse arguments, call the library, print (text, or one JSON object with --json).
mod bench;
mod bench_policy;
mod bench_realtime;
mod episodes;
mod learned;
mod merge;
mod policy;
mod progress;
mod render;
mod track;
mod tune;

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use flowram::policy::config::Consensus;

#[derive(Debug, Parser)]
#[command(
    name = "flowram",
    version,
    about = "FlowRAM keyframe policy and real-time control stack for a MuJoCo Franka Panda"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Render every camera of a scene: RGB PNG, 16-bit depth PNG (mm), world-frame PLY cloud.
    Render(render::RenderArgs),
    /// Execute keyframes on the simulated Panda (IK -> ruckig -> OSC at 1 kHz) and report each.
    Track(track::TrackArgs),
    /// Step response of a controller profile: rise time, overshoot, settling, plot.
    Tune(tune::TuneArgs),
    /// One closed-loop episode of a task (expert or idle), optionally as an animated GIF.
    Run(episodes::RunArgs),
    /// Collect successful expert demonstrations of a task into a dataset (safetensors).
    Collect(episodes::CollectArgs),
    /// Train the FlowRAM policy on datasets (progress bar, metrics.csv, loss.png, checkpoints).
    Train(policy::TrainArgs),
    /// Predict the next keyframe of a dataset episode with a trained policy.
    Predict(policy::PredictArgs),
    /// Benchmarks that print the project's performance figures.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Combine the outputs of the shards of one `collect` (dataset folders) or one
    /// `bench success` (results files) into one dataset or one success table.
    Merge(merge::MergeArgs),
}

pub fn run() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Render(args) => render::run(args),
        Command::Track(args) => track::run(args),
        Command::Tune(args) => tune::run(args),
        Command::Run(args) => episodes::run(args),
        Command::Collect(args) => episodes::collect(args),
        Command::Train(args) => policy::train_cmd(args),
        Command::Predict(args) => policy::predict_cmd(args),
        Command::Bench(cmd) => bench::run(cmd),
        Command::Merge(args) => merge::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// `--visuals`: what the renderer draws for the robot (see `flowram::sim::Visuals`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum VisualsArg {
    /// The Panda's full visual meshes (about 135k faces): what the paper's images look like.
    Full,
    /// Collision meshes as their convex hulls (a few hundred faces per link): several times
    /// faster on a software renderer, coarser arm silhouettes, identical everything else.
    Fast,
}

impl From<VisualsArg> for flowram::sim::Visuals {
    fn from(v: VisualsArg) -> Self {
        match v {
            VisualsArg::Full => Self::Full,
            VisualsArg::Fast => Self::Fast,
        }
    }
}

/// Which shard of a collection or evaluation this process runs (see `docs/scale-out.md`).
#[derive(Debug, clap::Args)]
struct ShardArgs {
    /// This process's shard, 0-based [default: SLURM_ARRAY_TASK_ID (minus SLURM_ARRAY_TASK_MIN)
    /// or JOB_COMPLETION_INDEX when set, else the whole run]. Shard i runs episodes k with
    /// k mod count = i.
    #[arg(long)]
    shard_index: Option<usize>,
    /// Shards in all [default: SLURM_ARRAY_TASK_COUNT when set, else 1].
    #[arg(long)]
    shard_count: Option<usize>,
}

impl ShardArgs {
    fn resolve(&self) -> anyhow::Result<flowram::rollout::shard::Shard> {
        Ok(flowram::rollout::shard::Shard::resolve(self.shard_index, self.shard_count, &|k| std::env::var(k).ok())?)
    }
}

/// Prints a serializable value as one line of JSON.
fn print_json(value: &impl serde::Serialize) -> anyhow::Result<()> {
    println!("{}", serde_json::to_string(value)?);
    Ok(())
}

/// `--consensus`: which of several keyframe samples is executed.
fn consensus_rule(text: &str) -> Result<Consensus, String> {
    match text {
        "medoid" => Ok(Consensus::Medoid),
        "mode" => Ok(Consensus::Mode),
        _ => Err(format!("expected `medoid` or `mode`, got `{text}`")),
    }
}

/// clap parser for a finite number above 0 (`--pointer-temperature`).
fn positive_number(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("expected a number above 0, got `{text}`")),
    }
}

/// clap parser for a finite number at least 0 (`--pointer-posterior-width`).
fn non_negative_number(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("expected a number at least 0, got `{text}`")),
    }
}

/// clap parser for counts that must be at least 1 (`--samples`, `--steps`): 0 is refused at the
/// command line, with what was expected, instead of deep inside the sampler.
fn at_least_one(text: &str) -> Result<usize, String> {
    match text.parse::<usize>() {
        Ok(0) => Err("expected a whole number of at least 1, got 0".into()),
        Ok(n) => Ok(n),
        Err(_) => Err(format!("expected a whole number of at least 1, got `{text}`")),
    }
}
