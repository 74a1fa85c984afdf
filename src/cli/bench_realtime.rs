//! `flowram bench realtime` and `flowram bench faults`: the real-time runtime's figures. MuJoCo is stepped at wall-clock
//! 1 kHz by the control thread while the planner plans and (with `--with-policy`) a FlowRAM
//! model infers continuously on its own threads; the arm moves back and forth between two
//! keyframes the whole time, so ticks include re-plans, motion, settling and holding.
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use flowram::control::keyframe::Keyframe;
use flowram::policy::config::PolicyConfig;
use flowram::policy::inference::{Policy, SamplingOptions};
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::policy::runtime::in_pool;
use flowram::policy::scene::observation::Observation;
use flowram::rollout::collection::demonstration;
use flowram::rollout::learned::DEFAULT_CAMERAS;
use flowram::rollout::stack::{load_controller_config, realtime_stack};
use flowram::runtime::alloc_count;
use flowram::runtime::control::{ControlSettings, MissCauses, Pacing};
use flowram::runtime::messages::{Answer, Request};
use flowram::runtime::pacing::{share_one_core, start_background_pool};
use flowram::runtime::planner::WorkspaceBox;
use flowram::runtime::session::{KeyframeSource, Percentiles, SessionSettings, run_session};
use flowram::sim::{Visuals, World};
use flowram::tasks;
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

#[derive(Debug, Args)]
pub struct RealtimeBenchArgs {
    /// Control ticks (1 ms each).
    #[arg(long, default_value_t = 1_000_000)]
    ticks: u64,
    /// Run a FlowRAM model (random weights of --config) inferring continuously beside the loop.
    #[arg(long)]
    with_policy: bool,
    /// Policy config for --with-policy [default: models/policy/paper.toml, the paper's size].
    #[arg(long)]
    config: Option<PathBuf>,
    /// Do not ask for SCHED_FIFO, mlockall and a pinned core.
    #[arg(long)]
    no_rt: bool,
    /// Run the whole process on the control thread's core: the policy computes only while the
    /// tick sleeps (a shorter compute tail on 2-core VMs, a slower policy; see the README).
    #[arg(long)]
    one_core: bool,
    /// Controller profile [default: controllers/osc.toml].
    #[arg(long)]
    controller: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Serialize)]
struct RealtimeReport {
    ticks: u64,
    deadline_misses: u64,
    /// Each miss by what took its time: the previous tick still running at its release
    /// (`overrun`), a late wake-up, the MuJoCo step, or the tick's compute.
    deadline_miss_causes: MissCauses,
    /// CPU time the hypervisor gave to others while this guest's vCPUs wanted to run, over the
    /// run, summed over the vCPUs (s; `steal` of /proc/stat; null where unreadable).
    host_steal_s: Option<f64>,
    /// The tick without the backend: hand-offs, keyframe execution, controller, limit check.
    compute_us: Percentiles,
    /// The backend's cycle: one MuJoCo step of the Panda scene.
    sim_step_us: Percentiles,
    wake_latency_us: Percentiles,
    policy_inferences: u64,
    waited_on_policy_ticks: u64,
    allocations_in_tick: Option<u64>,
    rt_scheduling: bool,
    rt_notes: Vec<String>,
    /// `--one-core`: the core the whole process ran on.
    one_core: Option<usize>,
    keyframes_done: u64,
    limit_violations: u64,
    qp_fallbacks: u64,
    /// Ticks where OSQP ran; on the others no QP row was active and the cost's unconstrained
    /// minimum was the QP's exact solution.
    qp_solves: u64,
    dropped_records: u64,
    stop: flowram::runtime::control::StopReason,
    wall_s: f64,
}

/// Back and forth between two poses near home; with a policy, one inference per request and
/// continuous inference between requests (the policy's keyframes have random weights, so they
/// are the load, not the target).
struct Shuttle {
    poses: [Keyframe; 2],
    next: usize,
    policy: Option<(Policy, Observation)>,
    inferences: std::sync::Arc<std::sync::atomic::AtomicU64>,
    errors: u64,
}

impl Shuttle {
    fn infer(&mut self) {
        if let Some((policy, observation)) = self.policy.as_mut() {
            let n = self.inferences.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let flow = &policy.config().flow;
            let options = SamplingOptions {
                steps: flow.sampling_steps,
                samples: flow.consensus_samples,
                drs: true,
                seed: n,
                consensus: flow.consensus,
                sharpening: flow.pointer_sharpening,
            };
            if in_pool(|| policy.predict(observation, &options)).is_err() {
                self.errors += 1;
            }
        }
    }
}

impl KeyframeSource for Shuttle {
    fn propose(&mut self, _request: &Request) -> Result<Answer, String> {
        self.infer();
        let k = self.poses[self.next % 2];
        self.next += 1;
        Ok(Answer::Keyframe(k))
    }

    fn idle(&mut self) {
        if self.policy.is_some() {
            self.infer();
        } else {
            std::thread::sleep(std::time::Duration::from_micros(200));
        }
    }
}

pub fn realtime(args: RealtimeBenchArgs) -> anyhow::Result<()> {
    if args.ticks == 0 {
        bail!("--ticks must be at least 1");
    }
    let rt = !args.no_rt;
    // before any thread starts, so the policy's pool is sized for and confined to that core
    let one_core = args
        .one_core
        .then(share_one_core)
        .transpose()
        .context("--one-core: confining the process to the control thread's core")?;
    if rt {
        // The policy's pool threads run at background priority: started before first use.
        start_background_pool();
    }
    let policy = if args.with_policy {
        let path = args.config.clone().unwrap_or_else(|| flowram::deps::models_dir().join("policy/paper.toml"));
        let config = PolicyConfig::from_toml_file(&path)?;
        let mut policy = Policy::random(&config, TextEncoder::load_installed()?)?;
        let task = tasks::by_name("open_drawer")?;
        let episode =
            demonstration(task.as_ref(), 0, 0, &DEFAULT_CAMERAS, config.observation.image_size, Visuals::Full)
                .context("rendering the policy's observation")?;
        let observation = Observation::from_episode(&episode, 0)?;
        policy.prepare(&observation)?;
        Some((policy, observation))
    } else {
        None
    };
    let world = World::load_named("default")?;
    let home = world.arm_state().tcp_in_base;
    let open = world.arm_state().gripper_width > 0.04;
    let a = Translation3::new(0.08, 0.12, -0.06) * home * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.4);
    let b = Translation3::new(0.02, -0.12, 0.04) * home * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -0.3);
    let settings = ControlSettings {
        pacing: Pacing::WallClock,
        max_ticks: args.ticks,
        keyframes: None,
        watchdog_ticks: u64::MAX,
        max_rejections_in_a_row: 3,
        gripper_timeout: 2.0,
        stall_timeout_s: 0.0,
    };
    let config = load_controller_config(args.controller.as_deref())?;
    let (control, planner) = realtime_stack(world, config, settings, WorkspaceBox::TABLE)?;
    let inferences = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let mut source = Shuttle {
        poses: [Keyframe::at(&a, open), Keyframe::at(&b, open)],
        next: 0,
        policy,
        inferences: inferences.clone(),
        errors: 0,
    };
    let counting = alloc_count::is_installed();
    let allocations_before = alloc_count::tick_allocations();
    let steal_before = host_steal_s();
    let t0 = Instant::now();
    let out =
        run_session(control, planner, &mut source, SessionSettings { realtime_scheduling: rt, ..Default::default() })?;
    let wall_s = t0.elapsed().as_secs_f64();
    let host_steal_s = steal_before.zip(host_steal_s()).map(|(before, after)| after - before);
    if source.errors > 0 {
        bail!("{} policy inferences failed", source.errors);
    }
    let s = &out.summary;
    let report = RealtimeReport {
        ticks: s.ticks,
        deadline_misses: s.deadline_misses,
        deadline_miss_causes: s.miss_causes,
        host_steal_s,
        compute_us: out.compute,
        sim_step_us: out.backend,
        wake_latency_us: out.wake_latency,
        policy_inferences: inferences.load(std::sync::atomic::Ordering::Relaxed),
        waited_on_policy_ticks: s.waited_ticks,
        allocations_in_tick: counting.then(|| alloc_count::tick_allocations() - allocations_before),
        rt_scheduling: out.rt.as_ref().is_some_and(|r| r.fifo),
        rt_notes: out.rt.map(|r| r.notes).unwrap_or_default(),
        one_core,
        keyframes_done: s.keyframes_done,
        limit_violations: s.monitor.violations,
        qp_fallbacks: s.qp_fallbacks,
        qp_solves: s.qp_solves,
        dropped_records: s.dropped_records,
        stop: s.stop,
        wall_s,
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        let (c, w) = (&report.compute_us, &report.wake_latency_us);
        println!(
            "{} ticks in {:.1} s: {} deadline misses, {} ticks waited on the policy, {} policy inferences, {} keyframes",
            report.ticks,
            wall_s,
            report.deadline_misses,
            report.waited_on_policy_ticks,
            report.policy_inferences,
            report.keyframes_done
        );
        let causes = &report.deadline_miss_causes;
        println!(
            "misses by cause: {} after an overrun of the previous tick, {} woke late, {} MuJoCo step, {} compute; host steal {}",
            causes.overrun,
            causes.wake,
            causes.backend,
            causes.compute,
            report.host_steal_s.map_or("not readable".into(), |t| format!("{t:.2} s"))
        );
        let m = &report.sim_step_us;
        println!("tick compute us: p50 {:.1}, p99 {:.1}, p99.99 {:.1}, max {:.1}", c.p50, c.p99, c.p9999, c.max);
        println!("MuJoCo step us: p50 {:.1}, p99 {:.1}, p99.99 {:.1}, max {:.1}", m.p50, m.p99, m.p9999, m.max);
        println!("wake latency us: p50 {:.1}, p99 {:.1}, p99.99 {:.1}, max {:.1}", w.p50, w.p99, w.p9999, w.max);
        println!(
            "allocations in ticks: {}; SCHED_FIFO: {}; whole process on one core: {}; limit violations {}, OSQP ran on {} ticks, QP fallbacks {}",
            report.allocations_in_tick.map_or("not counted".into(), |n| n.to_string()),
            report.rt_scheduling,
            report.one_core.map_or("no".into(), |c| format!("core {c}")),
            report.limit_violations,
            report.qp_solves,
            report.qp_fallbacks
        );
        for note in &report.rt_notes {
            println!("note: {note}");
        }
    }
    Ok(())
}

#[derive(Debug, Args)]
pub struct FaultsBenchArgs {
    /// Runs, each with its own fault stream (seeds --seed..--seed + runs).
    #[arg(long, default_value_t = 1000)]
    runs: u64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Controller profile (TOML); default controllers/osc.toml (contact guards on;
    /// controllers/osc-unguarded.toml turns them off).
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    #[arg(long)]
    json: bool,
}

pub fn faults(args: FaultsBenchArgs) -> anyhow::Result<()> {
    if args.runs == 0 {
        bail!("--runs must be at least 1");
    }
    let bar = indicatif::ProgressBar::new(args.runs);
    bar.set_style(
        indicatif::ProgressStyle::with_template("fault runs {bar:30} {pos}/{len} [{elapsed_precise} < {eta_precise}]")
            .expect("a valid progress template"),
    );
    let t0 = Instant::now();
    let report =
        flowram::rollout::faults::fault_runs(args.runs, args.seed, args.config.as_deref(), |n| bar.set_position(n))?;
    bar.finish_and_clear();
    let wall_s = t0.elapsed().as_secs_f64();
    if args.json {
        #[derive(Serialize)]
        struct Out<'a> {
            #[serde(flatten)]
            report: &'a flowram::rollout::faults::FaultReport,
            limit_violations: u64,
            wall_s: f64,
        }
        println!(
            "{}",
            serde_json::to_string_pretty(&Out { report: &report, limit_violations: report.violations(), wall_s })?
        );
        return Ok(());
    }
    let r = &report;
    println!("{} runs, {} ticks ({:.0} s wall)", r.runs, r.ticks, wall_s);
    println!("faults injected: {}", r.faults.iter().map(|(k, n)| format!("{k} {n}")).collect::<Vec<_>>().join(", "));
    println!(
        "limit violations: torque {}, torque rate {}, joint position {}, joint velocity {}; non-finite torques {}; panics {}",
        r.torque_violations,
        r.torque_rate_violations,
        r.position_violations,
        r.velocity_violations,
        r.non_finite_torques,
        r.panics
    );
    println!(
        "holds: {} keyframes refused, {} runs ended by the watchdog, {} motions stopped by the collision reflex; keyframes reached {}/{} commanded; OSQP ran on {} ticks, QP fallback ticks {}",
        r.holds_rejected,
        r.holds_watchdog,
        r.holds_reflex,
        r.keyframes_reached,
        r.keyframes_commanded,
        r.qp_solves,
        r.qp_fallbacks
    );
    println!("runs ended: {}", r.stops.iter().map(|(k, n)| format!("{k} {n}")).collect::<Vec<_>>().join(", "));
    Ok(())
}

/// Steal time of all vCPUs since boot (s): the `steal` column of /proc/stat's `cpu` line, in
/// clock ticks. None where the file or the column is missing (not Linux, or an old kernel).
fn host_steal_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let line = stat.lines().find(|l| l.starts_with("cpu "))?;
    let steal: f64 = line.split_whitespace().nth(8)?.parse().ok()?;
    // SAFETY: sysconf has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    (hz > 0).then(|| steal / hz as f64)
}
