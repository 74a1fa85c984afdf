//! The 1 kHz tick does not allocate or wait: a counting global allocator sees no allocation in
//! control ticks (lock-step and in the real-time runtime's control thread); a stalled policy
//! never delays a tick and the arm holds; garbage keyframes are rejected and the arm holds; the
//! simulated-latency mode reproduces bit for bit and applies plans exactly at their due tick.
mod common;

use std::time::Duration;

use flowram::control::backend::{Cycle, RobotBackend};
use flowram::control::keyframe::Keyframe;
use flowram::control::osc_config::OscConfig;
use flowram::policy::inference::{Policy, SamplingOptions};
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::rollout::episode::{Actor, Observer, run_episode};
use flowram::rollout::learned::FlowRamActor;
use flowram::rollout::realtime::{RealtimeActor, RealtimeOptions, run_realtime_episode};
use flowram::rollout::stack::{build_runner, realtime_stack};
use flowram::runtime::alloc_count::{CountingAllocator, TickScope, tick_allocations};
use flowram::runtime::control::{ControlSettings, Pacing, StopReason};
use flowram::runtime::messages::{Answer, Event, Rejection, Request};
use flowram::runtime::planner::WorkspaceBox;
use flowram::runtime::session::{KeyframeSource, SessionOutcome, SessionSettings, run_session};
use flowram::sim::backend::DetachedWorld;
use flowram::sim::{CameraRig, Visuals, World};
use flowram::tasks;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

#[test]
fn control_ticks_do_not_allocate() {
    let mut world = World::load_named("default").unwrap();
    let mut runner = build_runner(&world, OscConfig::default_profile().unwrap()).unwrap();
    let home = world.arm_state().tcp_in_base;
    let target = Translation3::new(0.1, -0.1, -0.05) * home * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3);
    let goal = runner.ik.solve(runner.controller.kinematics_mut(), &target, &world.read_state().q).unwrap().q;
    runner.controller.set_goal(&goal);
    let before = tick_allocations();
    let mut ticks = 0u32;
    world
        .control(|state| {
            ticks += 1;
            if ticks == 700 {
                let mut q = goal;
                q[0] -= 0.2;
                runner.controller.set_goal(&q); // a re-plan mid-motion, too
            }
            if ticks == 1500 {
                // a raw step of the reference: the torque-rate rows become active, so OSQP runs
                // (on the smooth motion before it the cost's minimum meets every row)
                let mut q = state.q;
                q[3] += 0.3;
                runner.controller.jump_reference(&q);
            }
            // from the second tick on (the first sizes the solver's workspaces)
            let _scope = (ticks > 1).then(TickScope::enter);
            let command = runner.controller.tick(state);
            if ticks == 2000 { Cycle::Finish(command) } else { Cycle::Continue(command) }
        })
        .unwrap();
    let stats = runner.controller.osc().stats();
    assert!(stats.ticks >= 2000);
    assert!(stats.qp_solves > 10, "OSQP ran on {} ticks: its path is not under the count", stats.qp_solves);
    assert_eq!(tick_allocations() - before, 0, "heap allocations inside control ticks");
}

/// Keyframes from a list, in order; each answer after `delay` of wall-clock time.
struct Script {
    keyframes: Vec<Keyframe>,
    delay: Duration,
    next: usize,
}

impl KeyframeSource for Script {
    fn propose(&mut self, _request: &Request) -> Result<Answer, String> {
        std::thread::sleep(self.delay);
        let Some(&k) = self.keyframes.get(self.next) else { return Ok(Answer::Finish) };
        self.next += 1;
        Ok(Answer::Keyframe(k))
    }
}

fn home() -> (World, Isometry3<f64>) {
    let world = World::load_named("default").unwrap();
    let tcp = world.arm_state().tcp_in_base;
    (world, tcp)
}

fn settings(pacing: Pacing, max_ticks: u64, keyframes: Option<u64>) -> ControlSettings {
    ControlSettings {
        pacing,
        max_ticks,
        keyframes,
        watchdog_ticks: 1000,
        max_rejections_in_a_row: 4,
        gripper_timeout: 2.0,
        stall_timeout_s: 5.0,
    }
}

fn run(world: World, settings: ControlSettings, source: &mut dyn KeyframeSource) -> SessionOutcome<DetachedWorld> {
    let (control, planner) =
        realtime_stack(world, OscConfig::default_profile().unwrap(), settings, WorkspaceBox::TABLE).unwrap();
    run_session(control, planner, source, SessionSettings::default()).unwrap()
}

fn moves(home: &Isometry3<f64>) -> Vec<Keyframe> {
    let a = Translation3::new(0.08, 0.1, -0.05) * home * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3);
    let b = Translation3::new(0.0, -0.1, 0.03) * home;
    vec![Keyframe::at(&a, true), Keyframe::at(&b, false)]
}

#[test]
fn simulated_latency_applies_plans_at_their_due_tick_and_reproduces_bit_for_bit() {
    let latency = 150;
    let mut finals = Vec::new();
    let mut timelines = Vec::new();
    for delay_ms in [0, 30] {
        // different wall-clock delays of the policy: the simulated timeline must not change
        let (world, tcp) = home();
        let mut source = Script { keyframes: moves(&tcp), delay: Duration::from_millis(delay_ms), next: 0 };
        let out = run(world, settings(Pacing::SimulatedLatency { ticks: latency }, 20_000, Some(2)), &mut source);
        assert_eq!(out.summary.stop, StopReason::KeyframesDone, "{:?}", out.events);
        assert_eq!(out.summary.keyframes_done, 2);
        assert_eq!(out.summary.monitor.violations, 0);
        let mut requested = std::collections::HashMap::new();
        let mut timeline = Vec::new();
        for e in &out.events {
            match *e {
                Event::Requested { request, tick } => {
                    requested.insert(request, tick);
                }
                Event::PlanStarted { request, tick } => {
                    assert_eq!(tick, requested[&request] + latency, "plan {request} applied off its due tick");
                    timeline.push(tick);
                }
                Event::KeyframeDone { tick, outcome, .. } => {
                    assert!(outcome.position_error() < 1e-3, "keyframe settled {} m off", outcome.position_error());
                    timeline.push(tick);
                }
                _ => {}
            }
        }
        timelines.push(timeline);
        let s = out.summary.final_state;
        finals.push((s.q.map(f64::to_bits), s.dq.map(f64::to_bits), s.gripper_width.to_bits(), out.summary.ticks));
    }
    assert_eq!(timelines[0], timelines[1]);
    assert_eq!(finals[0], finals[1], "the simulated-latency mode is not bit-identical across runs");
}

#[test]
fn a_stalled_policy_never_delays_a_tick_and_the_arm_holds() {
    let (world, tcp) = home();
    let q0 = world.arm_state().q;
    // the policy answers after 1.5 s; the watchdog gives up after 1000 ticks (1 s)
    let mut source = Script { keyframes: moves(&tcp), delay: Duration::from_millis(1500), next: 0 };
    let out = run(world, settings(Pacing::WallClock, 5000, None), &mut source);
    let s = &out.summary;
    assert_eq!(s.stop, StopReason::PolicySilent);
    assert!(s.ticks > 1000, "the control loop stopped ticking after {} ticks", s.ticks);
    assert_eq!(s.waited_ticks, 0, "ticks waited on the policy");
    assert_eq!(s.monitor.violations, 0);
    assert!(
        (s.final_state.q - q0).amax() < 1e-3,
        "the arm drifted {} rad while holding",
        (s.final_state.q - q0).amax()
    );
    assert!(matches!(out.events.last(), Some(Event::WatchdogHold { .. })), "{:?}", out.events);
}

#[test]
fn a_stall_inside_a_tick_is_a_compute_miss_and_the_ticks_that_catch_up_are_overruns() {
    let (world, tcp) = home();
    let (mut control, planner) = realtime_stack(
        world,
        OscConfig::default_profile().unwrap(),
        settings(Pacing::WallClock, 400, None),
        WorkspaceBox::TABLE,
    )
    .unwrap();
    // The first request's tap (inside tick 0's compute) stalls the tick for 8 periods: tick 0
    // misses by its compute, and the ticks released during the stall start late.
    control.tap = Some(Box::new(|_, request: &Request| {
        if request.id == 0 {
            std::thread::sleep(Duration::from_millis(8));
        }
    }));
    let mut source = Script { keyframes: moves(&tcp), delay: Duration::ZERO, next: 0 };
    let out = run_session(control, planner, &mut source, SessionSettings::default()).unwrap();
    let (s, causes) = (&out.summary, out.summary.miss_causes);
    assert_eq!(causes.total(), s.deadline_misses, "every miss has one cause: {causes:?}");
    assert!(causes.compute >= 1, "the stalled tick was not counted as a compute miss: {causes:?}");
    assert!(causes.overrun >= 5, "the ticks released during the 8 ms stall were not overruns: {causes:?}");
}

#[test]
fn garbage_keyframes_are_rejected_and_the_arm_holds() {
    let (world, tcp) = home();
    let q0 = world.arm_state().q;
    let good = Keyframe::at(&tcp, true);
    let nan = Keyframe { position: [f64::NAN, 0.0, 0.5], ..good };
    let skewed = Keyframe { quat_wxyz: [0.9, 0.0, 0.0, 0.0], ..good };
    let far = Keyframe { position: [2.0, 0.0, 0.4], ..good };
    let unreachable = Keyframe { position: [0.12, 0.0, 0.0], quat_wxyz: [0.0, 0.0, 0.0, 1.0], ..good };
    let mut source = Script { keyframes: vec![nan, skewed, far, unreachable], delay: Duration::ZERO, next: 0 };
    let out = run(world, settings(Pacing::SimulatedLatency { ticks: 20 }, 5000, None), &mut source);
    assert_eq!(out.summary.stop, StopReason::PolicyGarbage);
    let why: Vec<Rejection> =
        out.events.iter().filter_map(|e| if let Event::Rejected { why, .. } = e { Some(*why) } else { None }).collect();
    assert_eq!(
        why,
        [Rejection::NonFinite, Rejection::NotUnitQuaternion, Rejection::OutsideWorkspace, Rejection::Unreachable]
    );
    assert_eq!(out.summary.monitor.violations, 0);
    assert!((out.summary.final_state.q - q0).amax() < 1e-3, "the arm moved on garbage");
}

#[test]
fn the_control_thread_does_not_allocate() {
    let (world, tcp) = home();
    let mut source = Script { keyframes: moves(&tcp), delay: Duration::ZERO, next: 0 };
    let before = tick_allocations();
    let out = run(world, settings(Pacing::SimulatedLatency { ticks: 5 }, 20_000, Some(2)), &mut source);
    assert_eq!(out.summary.keyframes_done, 2);
    assert!(out.summary.ticks > 1000);
    assert_eq!(tick_allocations() - before, 0, "heap allocations inside control ticks");
}

fn realtime_options(latency_ticks: Option<u64>, max_keyframes: usize) -> RealtimeOptions {
    RealtimeOptions {
        latency_ticks,
        max_keyframes,
        realtime_scheduling: false,
        watchdog_s: 30.0,
        max_seconds: 120.0,
        cameras: vec!["front".into(), "left_shoulder".into()],
        image_size: 48,
    }
}

#[test]
fn the_expert_solves_a_task_on_the_realtime_runtime_at_wall_clock_pace() {
    let task = tasks::by_name("open_drawer").unwrap();
    let (result, figures) =
        run_realtime_episode(task.as_ref(), 0, 3, RealtimeActor::Expert, &realtime_options(None, 100)).unwrap();
    assert!(result.success, "problems: {:?}", result.problems);
    assert_eq!(figures.stop, StopReason::SourceFinished);
    assert_eq!(figures.waited_on_policy_ticks, 0);
    assert_eq!(figures.limit_violations, 0);
    assert_eq!(result.keyframes, result.actions.len());
    // The keyframes lock-step reaches, reached alike. (With the contact guards, the drawer's end
    // stop holds keyframe 2 of this seed 1.02 mm short of its 1 mm tolerance in both.)
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    let lock = run_episode(task.as_ref(), &mut world, 0, 3, Actor::Expert, None).unwrap();
    assert!(lock.success);
    assert!(lock.reached + 1 >= lock.keyframes, "lock-step reaches all but one: {:?}", lock.problems);
    assert_eq!((result.keyframes, result.reached), (lock.keyframes, lock.reached), "problems: {:?}", result.problems);
}

#[test]
fn a_policy_on_the_realtime_runtime_sees_and_does_what_it_does_in_lock_step() {
    let config = common::tiny_policy_config();
    let options = SamplingOptions::new(2, 1, 5);
    let actor = || FlowRamActor::new(Policy::random(&config, TextEncoder::load_installed().unwrap()).unwrap(), options);
    let task = tasks::by_name("slide_block").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    let mut rig = CameraRig::new(&world, 48, Visuals::Full).unwrap();
    let cameras = vec![rig.camera_index("front").unwrap(), rig.camera_index("left_shoulder").unwrap()];
    let mut observer = Observer { rig: &mut rig, cameras };
    let mut lock_actor = actor();
    let lock = run_episode(
        task.as_ref(),
        &mut world,
        0,
        1,
        Actor::Policy { policy: &mut lock_actor, max_keyframes: 2 },
        Some(&mut observer),
    )
    .unwrap();
    let mut rt_actor = actor();
    let (rt, figures) = run_realtime_episode(
        task.as_ref(),
        0,
        1,
        RealtimeActor::Policy(&mut rt_actor),
        &realtime_options(Some(120), 2),
    )
    .unwrap();
    // The first observation is the settled scene in both, so the same view and keyframe up to
    // rounding: lock-step renders the stepped world, whose body poses MuJoCo computed before the
    // step's integration (1 ms old, the arm at rest); the policy's copy recomputes them from the
    // copied joint state. (Later observations differ: the real-time arm holds 120 ms first.)
    let (a, b) = (&rt.observations[0], &lock.observations[0]);
    let close =
        |x: &[f32], y: &[f32], tol: f32| x.len() == y.len() && x.iter().zip(y).all(|(u, v)| (u - v).abs() <= tol);
    assert!(close(&a.proprio, &b.proprio, 1e-6), "{:?} vs {:?}", a.proprio, b.proprio);
    assert_eq!(a.frames.len(), 2);
    for (fa, fb) in a.frames.iter().zip(&b.frames) {
        let same = fa.rgb.iter().zip(&fb.rgb).filter(|(u, v)| u == v).count();
        assert!(
            same as f64 >= 0.999 * fb.rgb.len() as f64,
            "camera {}: {same}/{} bytes equal",
            fa.camera,
            fb.rgb.len()
        );
        assert!(close(&fa.depth, &fb.depth, 1e-4), "camera {} depth differs", fa.camera);
    }
    assert!(close(&rt.actions[0], &lock.actions[0], 1e-3), "{:?} vs {:?}", rt.actions[0], lock.actions[0]);
    assert_eq!(rt_actor.inference_ms.len(), 2);
    assert_eq!(figures.policy_inferences, 2);
    assert!(
        matches!(figures.stop, StopReason::KeyframesDone | StopReason::PolicyGarbage | StopReason::SourceFinished),
        "{:?}",
        figures.stop
    );
}

struct Crashing;

impl KeyframeSource for Crashing {
    fn propose(&mut self, _request: &Request) -> Result<Answer, String> {
        panic!("the policy crashed");
    }
}

#[test]
fn a_panicking_policy_ends_the_run_instead_of_hanging_it() {
    let (world, _) = home();
    // ten minutes of ticks and no watchdog: only the panic can end this run quickly
    let mut s = settings(Pacing::WallClock, 600_000, None);
    s.watchdog_ticks = u64::MAX;
    let started = std::time::Instant::now();
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(world, s, &mut Crashing)));
    assert!(outcome.is_err(), "the policy's panic must reach the caller");
    assert!(started.elapsed() < Duration::from_secs(60), "the run went on after the policy died");
}

/// The cores a thread may run on.
fn allowed_cores(tid: libc::pid_t) -> Vec<usize> {
    // SAFETY: a zeroed set is valid; the call fills it.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        assert_eq!(libc::sched_getaffinity(tid, std::mem::size_of::<libc::cpu_set_t>(), &raw mut set), 0);
        (0..libc::CPU_SETSIZE as usize).filter(|&c| libc::CPU_ISSET(c, &set)).collect()
    }
}

#[test]
fn one_core_confines_the_threads_started_after_it_to_the_control_core() {
    use flowram::runtime::pacing::{control_core, share_one_core};
    let harness = allowed_cores(0);
    // on a thread of its own: affinity is per thread, and the harness's threads stay as they are
    std::thread::spawn(|| {
        let before = allowed_cores(0);
        let core = control_core();
        assert_eq!(Some(&core), before.last(), "the control core is the last the process may use");
        assert_eq!(share_one_core().unwrap(), core);
        // a thread started afterwards (a pool worker, the planner) inherits the one core
        let child = std::thread::spawn(|| (allowed_cores(0), control_core())).join().unwrap();
        assert_eq!(child, (vec![core], core));
        assert_eq!(allowed_cores(0), vec![core]);
    })
    .join()
    .unwrap();
    assert_eq!(allowed_cores(0), harness, "only the confined thread and its children moved");
}
