//! `flowram bench ...`: the performance figures the issues ask for, measured here and printed
//! (median over repeats; the machines are shared, so single runs are noisy).
use std::time::Instant;

use clap::{Args, Subcommand};
use flowram::sim::{CameraRig, JointVector, Visuals, World};
use flowram::stats::median;
use serde::Serialize;

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Physics steps per second of the Panda scene (arm holding still under zero torque).
    Sim(SimArgs),
    /// RGB-D frames per second for one camera.
    Render(RenderBenchArgs),
    /// Per-tick compute time of the control stack over a long tracking run, and IK time.
    Control(ControlBenchArgs),
    /// FlowRAM latency from observation to keyframe (Table C grid) and training-step time.
    Policy(super::bench_policy::PolicyBenchArgs),
    /// Held-out keyframe errors of a trained policy against the training-mean baseline.
    Heldout(super::bench_policy::HeldOutArgs),
    /// Closed-loop success rate of a trained policy on held-out seeds of tasks.
    Success(super::bench_policy::SuccessBenchArgs),
    /// Two results files of `bench success --out` on the same tasks and seeds, paired: both
    /// success tables and the seeds only one of them solved (exact McNemar p), per task and over
    /// all.
    Compare(super::bench_policy::CompareArgs),
    /// The Table C analogue from results files of `bench success --steps N [--no-drs] --out`:
    /// success (95 % Wilson interval) and median inference latency per arm and Euler steps, as a
    /// table and a PNG plot.
    Grid(super::bench_policy::GridArgs),
    /// Expert success, keyframes per episode and episodes per minute (no cameras) of tasks over
    /// seeded episodes.
    Experts(ExpertsBenchArgs),
    /// Wall clock of one collection run whole, then split into shards running side by side on
    /// this machine and merged (checks that the merge equals the whole run).
    Shards(ShardsBenchArgs),
    /// The real-time runtime: deadline misses, tick compute and wake-up latency percentiles,
    /// ticks that waited on the policy and allocations in ticks, over a long wall-clock run.
    Realtime(super::bench_realtime::RealtimeBenchArgs),
    /// Fault streams injected into the real stack (bad keyframes, policy stalls and failures, QP
    /// time-outs, dropped and late cycles, a blocked TCP): limit violations, non-finite
    /// torques, panics, holds.
    Faults(super::bench_realtime::FaultsBenchArgs),
}

#[derive(Debug, Args)]
pub struct ExpertsBenchArgs {
    /// Tasks, comma-separated [default: every task].
    #[arg(long, value_delimiter = ',')]
    tasks: Vec<String>,
    /// Episodes per task: seeds from --seed, variation = seed modulo the task's variations.
    #[arg(long, default_value_t = 100)]
    episodes: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct ExpertReport {
    task: String,
    episodes: usize,
    successes: usize,
    success_ci95: [f64; 2],
    keyframes_mean: f64,
    episodes_per_minute: f64,
    /// Seeds the expert failed.
    failed_seeds: Vec<u64>,
}

#[derive(Debug, Args)]
pub struct ShardsBenchArgs {
    #[arg(long, default_value = "slide_block")]
    task: String,
    #[arg(long, default_value_t = 30)]
    episodes: usize,
    /// Shards, run as parallel processes.
    #[arg(long, default_value_t = 3)]
    count: usize,
    #[arg(long, value_delimiter = ',', default_values_t = flowram::rollout::learned::DEFAULT_CAMERAS.map(String::from))]
    cameras: Vec<String>,
    #[arg(long, default_value_t = flowram::sim::camera::DEFAULT_IMAGE_SIZE)]
    size: usize,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct ShardsReport {
    task: String,
    episodes: usize,
    shards: usize,
    cores: usize,
    unsharded_s: f64,
    /// The shards side by side, until the last finished.
    sharded_s: f64,
    merge_s: f64,
    /// unsharded_s / (sharded_s + merge_s).
    speedup: f64,
    merged_equals_unsharded: bool,
}

#[derive(Debug, Args)]
pub struct ControlBenchArgs {
    #[arg(long, default_value = "default")]
    scene: String,
    /// Controller profile (TOML); default controllers/osc.toml.
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    /// Keyframes in the tour (each a move of 10-20 cm and up to 0.4 rad from the home pose).
    #[arg(long, default_value_t = 24)]
    keyframes: usize,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct ControlReport {
    tick_us_p50: f64,
    tick_us_p99: f64,
    tick_us_max: f64,
    osc_us_p99: f64,
    trajectory_us_p99: f64,
    kinematics_us_p99: f64,
    ik_ms_median: f64,
    realtime_factor: f64,
    ticks: usize,
    keyframes: usize,
    keyframes_reached: usize,
    qp_fallbacks: u64,
    /// Share of the ticks where OSQP ran (on the others no row was active and the cost's
    /// unconstrained minimum was the QP's solution).
    qp_share: f64,
    limit_violations: u64,
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
    #[arg(long, value_enum, default_value_t = super::VisualsArg::Full)]
    visuals: super::VisualsArg,
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
        BenchCommand::Control(args) => control(args),
        BenchCommand::Policy(args) => super::bench_policy::bench_cmd(args),
        BenchCommand::Heldout(args) => super::bench_policy::heldout_cmd(args),
        BenchCommand::Success(args) => super::bench_policy::success_cmd(args),
        BenchCommand::Compare(args) => super::bench_policy::compare_cmd(args),
        BenchCommand::Grid(args) => super::bench_policy::grid_cmd(args),
        BenchCommand::Experts(args) => experts(args),
        BenchCommand::Shards(args) => shards(args),
        BenchCommand::Realtime(args) => super::bench_realtime::realtime(args),
        BenchCommand::Faults(args) => super::bench_realtime::faults(args),
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
        println!(
            "{:.0} steps/s, {:.1}x real time (dt = {} s)",
            report.steps_per_s, report.realtime_factor, report.timestep_s
        );
        Ok(())
    }
}

fn render(args: RenderBenchArgs) -> anyhow::Result<()> {
    check_counts(args.frames, args.repeats, "frames")?;
    let mut world = World::load_named(&args.scene)?;
    let mut rig = CameraRig::new(&world, args.size, args.visuals.into())?;
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
        visuals: args.visuals.into(),
        frames_per_s: median(&runs),
        frames: args.frames,
        repeats: args.repeats,
        frames_per_s_runs: runs,
    };
    if args.json {
        super::print_json(&report)
    } else {
        println!(
            "{:.1} RGB-D frames/s at {}x{} ({:?} visuals, camera {})",
            report.frames_per_s, report.size, report.size, report.visuals, report.camera
        );
        Ok(())
    }
}

/// A deterministic tour around the home pose: translations of 10-20 cm and rotations up to
/// 0.4 rad, returning home at the end.
fn tour(home: &nalgebra::Isometry3<f64>, n: usize) -> Vec<flowram::control::keyframe::Keyframe> {
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    let offsets = [
        (Vector3::new(0.12, 0.1, -0.05), Vector3::new(0.0, 0.0, 0.3)),
        (Vector3::new(0.05, -0.15, -0.1), Vector3::new(0.2, 0.0, -0.2)),
        (Vector3::new(-0.1, 0.05, 0.1), Vector3::new(0.0, -0.25, 0.0)),
        (Vector3::new(0.15, 0.0, -0.12), Vector3::new(-0.2, 0.1, 0.4)),
        (Vector3::new(0.0, 0.18, 0.05), Vector3::new(0.1, 0.2, -0.3)),
        (Vector3::new(0.08, -0.08, 0.12), Vector3::new(0.0, 0.0, 0.0)),
    ];
    (0..n)
        .map(|i| {
            let (d, r) = if i + 1 == n { (Vector3::zeros(), Vector3::zeros()) } else { offsets[i % offsets.len()] };
            let pose = Translation3::from(d) * home * UnitQuaternion::from_scaled_axis(r);
            flowram::control::keyframe::Keyframe::at(&pose, true)
        })
        .collect()
}

fn control(args: ControlBenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.keyframes > 0, "--keyframes must be at least 1");
    let config = flowram::rollout::stack::load_controller_config(args.config.as_deref())?;
    let (mut world, mut runner) = flowram::rollout::stack::simulated_stack(&args.scene, config)?;
    let keyframes = tour(&world.arm_state().tcp_in_base, args.keyframes);
    runner.enable_timing(args.keyframes * 10_000);
    let start = Instant::now();
    let report = runner.run(&mut world, &keyframes)?;
    let wall = start.elapsed().as_secs_f64();
    let timings = runner.timings().unwrap_or_default();
    anyhow::ensure!(!timings.is_empty(), "no control ticks ran");
    let micros = |f: fn(&flowram::control::controller::TickTiming) -> std::time::Duration| {
        let mut v: Vec<f64> = timings.iter().map(|t| f(t).as_secs_f64() * 1e6).collect();
        v.sort_by(f64::total_cmp);
        v
    };
    let pct = flowram::stats::percentile_sorted;
    let total = micros(|t| t.total);
    let ik: Vec<f64> = report.keyframes.iter().map(|k| k.ik_ms).collect();
    let out = ControlReport {
        tick_us_p50: pct(&total, 0.5),
        tick_us_p99: pct(&total, 0.99),
        tick_us_max: *total.last().unwrap_or(&0.0),
        osc_us_p99: pct(&micros(|t| t.osc), 0.99),
        trajectory_us_p99: pct(&micros(|t| t.trajectory), 0.99),
        kinematics_us_p99: pct(&micros(|t| t.kinematics), 0.99),
        ik_ms_median: median(&ik),
        realtime_factor: report.sim_time_s / wall,
        ticks: timings.len(),
        keyframes: report.keyframes.len(),
        keyframes_reached: report.keyframes.iter().filter(|k| k.reached).count(),
        qp_fallbacks: report.qp_fallbacks,
        qp_share: {
            let stats = runner.controller.osc().stats();
            stats.qp_solves as f64 / stats.ticks.max(1) as f64
        },
        limit_violations: report.limit_violations,
    };
    if args.json {
        super::print_json(&out)
    } else {
        println!(
            "tick: p50 {:.1} us, p99 {:.1} us, max {:.1} us (OSC p99 {:.1}, trajectory p99 {:.2}, kinematics p99 {:.1}); IK median {:.2} ms; {:.1}x real time (sim + control); {}/{} keyframes reached, OSQP on {:.1} % of ticks, {} QP fallbacks, {} limit violations",
            out.tick_us_p50,
            out.tick_us_p99,
            out.tick_us_max,
            out.osc_us_p99,
            out.trajectory_us_p99,
            out.kinematics_us_p99,
            out.ik_ms_median,
            out.realtime_factor,
            out.keyframes_reached,
            out.keyframes,
            out.qp_share * 100.0,
            out.qp_fallbacks,
            out.limit_violations
        );
        Ok(())
    }
}

fn shards(args: ShardsBenchArgs) -> anyhow::Result<()> {
    use anyhow::Context;
    anyhow::ensure!(args.episodes > 0 && args.count > 0, "--episodes and --count must be at least 1");
    let exe = std::env::current_exe().context("locating the flowram binary")?;
    let dir = std::env::temp_dir().join(format!("flowram-bench-shards-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let collect = |out: &std::path::Path, shard: Option<usize>| {
        let mut c = std::process::Command::new(&exe);
        c.args(["collect", "--task", &args.task, "--episodes", &args.episodes.to_string(), "--json"]);
        c.args(["--cameras", &args.cameras.join(","), "--size", &args.size.to_string(), "--out"]).arg(out);
        if let Some(i) = shard {
            c.args(["--shard-index", &i.to_string(), "--shard-count", &args.count.to_string()]);
        }
        c.env_remove("SLURM_ARRAY_TASK_ID").env_remove("JOB_COMPLETION_INDEX");
        c.stdout(std::process::Stdio::null()).stderr(std::process::Stdio::piped());
        c
    };
    let check = |out: std::process::Output, what: &str| {
        anyhow::ensure!(out.status.success(), "{what} failed: {}", String::from_utf8_lossy(&out.stderr));
        Ok(())
    };
    let result = (|| -> anyhow::Result<ShardsReport> {
        let whole = dir.join("whole");
        let start = Instant::now();
        check(collect(&whole, None).output()?, "the unsharded collection")?;
        let unsharded_s = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let children = (0..args.count)
            .map(|i| collect(&dir.join(format!("shard{i}")), Some(i)).spawn())
            .collect::<Result<Vec<_>, _>>()?;
        for (i, child) in children.into_iter().enumerate() {
            check(child.wait_with_output()?, &format!("shard {i}"))?;
        }
        let sharded_s = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let parts: Vec<std::path::PathBuf> = (0..args.count).map(|i| dir.join(format!("shard{i}"))).collect();
        let merged = dir.join("merged");
        flowram::rollout::collection::merge_collections(&parts, &merged)?;
        let merge_s = start.elapsed().as_secs_f64();
        let same = flowram::data::read_index(&merged)? == flowram::data::read_index(&whole)?;
        Ok(ShardsReport {
            task: args.task.clone(),
            episodes: args.episodes,
            shards: args.count,
            cores: std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
            unsharded_s,
            sharded_s,
            merge_s,
            speedup: unsharded_s / (sharded_s + merge_s),
            merged_equals_unsharded: same,
        })
    })();
    let _ = std::fs::remove_dir_all(&dir);
    let report = result?;
    if args.json {
        return super::print_json(&report);
    }
    println!(
        "{} x {} episodes on {} cores: unsharded {:.1} s; {} shards side by side {:.1} s + merge {:.2} s = {:.2}x; merged index {} the unsharded one",
        report.task,
        report.episodes,
        report.cores,
        report.unsharded_s,
        report.shards,
        report.sharded_s,
        report.merge_s,
        report.speedup,
        if report.merged_equals_unsharded { "equals" } else { "DIFFERS from" }
    );
    Ok(())
}

fn experts(args: ExpertsBenchArgs) -> anyhow::Result<()> {
    use flowram::rollout::episode::{Actor, run_episode};
    anyhow::ensure!(args.episodes > 0, "--episodes must be at least 1");
    let task_list = if args.tasks.is_empty() {
        flowram::tasks::all()
    } else {
        args.tasks.iter().map(|t| flowram::tasks::by_name(t)).collect::<Result<Vec<_>, _>>()?
    };
    let mut reports = Vec::with_capacity(task_list.len());
    for task in &task_list {
        let mut world = flowram::tasks::load_world(task.as_ref())?;
        let mut bar = super::progress::TaskBar::new("episodes");
        flowram::rollout::evaluation::EvaluationProgress::started(&mut bar, task.name(), args.episodes);
        let start = Instant::now();
        let (mut successes, mut keyframes, mut failed_seeds) = (0, 0, Vec::new());
        for i in 0..args.episodes {
            let seed = args.seed + i as u64;
            let variation = seed as usize % task.variation_count();
            let result = run_episode(task.as_ref(), &mut world, variation, seed, Actor::Expert, None)?;
            keyframes += result.keyframes;
            if result.success {
                successes += 1;
            } else {
                failed_seeds.push(seed);
            }
            flowram::rollout::evaluation::EvaluationProgress::advanced(&mut bar, i + 1);
        }
        bar.finish();
        reports.push(ExpertReport {
            task: task.name().into(),
            episodes: args.episodes,
            successes,
            success_ci95: flowram::stats::wilson_interval(successes, args.episodes),
            keyframes_mean: keyframes as f64 / args.episodes as f64,
            episodes_per_minute: args.episodes as f64 / start.elapsed().as_secs_f64() * 60.0,
            failed_seeds,
        });
    }
    if args.json {
        return super::print_json(&reports);
    }
    for r in &reports {
        println!(
            "{}: expert {}/{} (95 % CI {:.0}-{:.0} %), {:.1} keyframes per episode, {:.0} episodes/min without cameras{}",
            r.task,
            r.successes,
            r.episodes,
            100.0 * r.success_ci95[0],
            100.0 * r.success_ci95[1],
            r.keyframes_mean,
            r.episodes_per_minute,
            if r.failed_seeds.is_empty() { String::new() } else { format!("; failed seeds {:?}", r.failed_seeds) }
        );
    }
    Ok(())
}
