//! `flowram bench ...`: the performance figures the issues ask for, measured here and printed
//! (median over repeats; the machines are shared, so single runs are noisy).
use std::time::Instant;

use clap::{Args, Subcommand};
use flowram::sim::{CameraRig, JointVector, Visuals, World};
use serde::Serialize;

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Physics steps per second of the Panda scene (arm holding still under zero torque).
    Sim(SimArgs),
    /// RGB-D frames per second for one camera.
    Render(RenderBenchArgs),
}

#[derive(Debug, Args)]
pub struct SimArgs {
    #[arg(long, default_value = "default")]
    scene: String,
    /// Steps per repeat.
    #[arg(long, default_value_t = 20_000)]
    steps: usize,
    #[arg(long, default_value_t = 5)]
    repeats: usize,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
pub struct RenderBenchArgs {
    #[arg(long, default_value = "default")]
    scene: String,
    #[arg(long, default_value = "front")]
    camera: String,
    #[arg(long, default_value_t = flowram::sim::camera::DEFAULT_IMAGE_SIZE)]
    size: usize,
    /// Frames per repeat.
    #[arg(long, default_value_t = 100)]
    frames: usize,
    #[arg(long, default_value_t = 5)]
    repeats: usize,
    #[arg(long, value_enum, default_value_t = Visuals::Full)]
    visuals: Visuals,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct SimReport {
    steps_per_s: f64,
    realtime_factor: f64,
    timestep_s: f64,
    steps: usize,
    repeats: usize,
    steps_per_s_runs: Vec<f64>,
}

#[derive(Serialize)]
struct RenderReport {
    size: usize,
    cameras: usize,
    camera: String,
    visuals: Visuals,
    frames_per_s: f64,
    frames: usize,
    repeats: usize,
    frames_per_s_runs: Vec<f64>,
}

pub fn run(cmd: BenchCommand) -> anyhow::Result<()> {
    match cmd {
        BenchCommand::Sim(args) => sim(args),
        BenchCommand::Render(args) => render(args),
    }
}

fn check_counts(per_repeat: usize, repeats: usize, what: &str) -> anyhow::Result<()> {
    anyhow::ensure!(per_repeat > 0 && repeats > 0, "--{what} and --repeats must be at least 1");
    Ok(())
}

fn sim(args: SimArgs) -> anyhow::Result<()> {
    check_counts(args.steps, args.repeats, "steps")?;
    let mut world = World::load_named(&args.scene)?;
    let mut runs = Vec::with_capacity(args.repeats);
    for _ in 0..args.repeats {
        world.reset_to("home")?;
        world.apply_torques(&JointVector::zeros())?;
        let start = Instant::now();
        for _ in 0..args.steps {
            world.step();
        }
        runs.push(args.steps as f64 / start.elapsed().as_secs_f64());
    }
    let steps_per_s = median(&runs);
    let report = SimReport {
        steps_per_s,
        realtime_factor: steps_per_s * world.timestep(),
        timestep_s: world.timestep(),
        steps: args.steps,
        repeats: args.repeats,
        steps_per_s_runs: runs,
    };
    if args.json {
        super::print_json(&report)
    } else {
        println!("{:.0} steps/s, {:.1}x real time (dt = {} s)", report.steps_per_s, report.realtime_factor, report.timestep_s);
        Ok(())
    }
}

fn render(args: RenderBenchArgs) -> anyhow::Result<()> {
    check_counts(args.frames, args.repeats, "frames")?;
    let mut world = World::load_named(&args.scene)?;
    let mut rig = CameraRig::new(&world, args.size, args.visuals)?;
    let index = rig.camera_index(&args.camera)?;
    let mut frame = rig.render(&mut world, index)?; // warm-up, and the buffers reused below
    let mut runs = Vec::with_capacity(args.repeats);
    for _ in 0..args.repeats {
        let start = Instant::now();
        for _ in 0..args.frames {
            rig.render_into(&mut world, index, &mut frame)?;
        }
        runs.push(args.frames as f64 / start.elapsed().as_secs_f64());
    }
    let report = RenderReport {
        size: args.size,
        cameras: 1,
        camera: args.camera,
        visuals: args.visuals,
        frames_per_s: median(&runs),
        frames: args.frames,
        repeats: args.repeats,
        frames_per_s_runs: runs,
    };
    if args.json {
        super::print_json(&report)
    } else {
        println!("{:.1} RGB-D frames/s at {}x{} ({:?} visuals, camera {})", report.frames_per_s, report.size, report.size, report.visuals, report.camera);
        Ok(())
    }
}

fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}
