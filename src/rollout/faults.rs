//! Faults injected into the real stack (MuJoCo, IK, ruckig, the OSC QP, the real-time runtime in
//! its simulated-latency mode), run after run, to count what must never happen: a limit
//! violation (torque, torque rate, joint position, joint velocity), a non-finite torque, a
//! panic. Each run draws its own fault stream from its seed:
//! - keyframes: reachable ones, unreachable ones, NaN/inf values, non-unit quaternions,
//!   positions outside the workspace box, poses 4 cm inside the table (a blocked TCP);
//! - the policy: failures, and stalls (120 ms of wall clock against a 50 ms stall time-out);
//! - the QP: a solver time limit of 5-30 us, so that OSQP runs out of time on some ticks;
//! - the backend: dropped cycles (the robot keeps the previous command) and late ones (two
//!   physics steps of one command);
//! - the latency between request and plan, 0 to 300 ticks.
//!
//! The stall and QP time-limit faults are measured in wall-clock time, so a run's counts can
//! differ slightly between machines and loads (the refusals, violations and panics it checks
//! for do not depend on it).
use std::collections::BTreeMap;
use std::time::Duration;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::RolloutError;
use super::stack::{load_controller_config, realtime_stack};
use crate::control::backend::{BackendError, Command, RobotBackend, RobotState};
use crate::control::keyframe::Keyframe;
use crate::runtime::control::{ControlSettings, Pacing, StopReason};
use crate::runtime::messages::{Answer, Event, Request};
use crate::runtime::planner::WorkspaceBox;
use crate::runtime::session::{KeyframeSource, SessionSettings, run_session};
use crate::sim::World;

/// What `fault_runs` counted.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct FaultReport {
    pub runs: u64,
    /// Faults injected, by kind.
    pub faults: BTreeMap<&'static str, u64>,
    /// Ticks over a limit, by kind, and ticks with a non-finite torque.
    pub torque_violations: u64,
    pub torque_rate_violations: u64,
    pub position_violations: u64,
    pub velocity_violations: u64,
    pub non_finite_torques: u64,
    /// Runs with any limit violation, and those of them without a `blocked_tcp` fault.
    pub runs_with_violations: u64,
    pub runs_with_violations_without_blocked_tcp: u64,
    pub panics: u64,
    /// Keyframes refused (the arm held), runs the watchdog ended (the arm held), and motions
    /// the collision reflex stopped (the arm stopped where it was).
    pub holds_rejected: u64,
    pub holds_watchdog: u64,
    pub holds_reflex: u64,
    /// Plans started, and keyframes the arm reached to tolerance.
    pub keyframes_commanded: u64,
    pub keyframes_reached: u64,
    /// Ticks where the QP failed or ran out of time and the damping torque was used.
    pub qp_fallbacks: u64,
    /// Ticks where OSQP ran (a QP row was active: contacts, limits, re-targeting).
    pub qp_solves: u64,
    pub ticks: u64,
    /// How the runs ended.
    pub stops: BTreeMap<&'static str, u64>,
}

impl FaultReport {
    pub fn violations(&self) -> u64 {
        self.torque_violations + self.torque_rate_violations + self.position_violations + self.velocity_violations
    }

    fn count(&mut self, kind: &'static str, n: u64) {
        *self.faults.entry(kind).or_default() += n;
    }
}

/// A backend that drops and delays cycles.
struct FaultyBackend<B> {
    inner: B,
    rng: StdRng,
    drop_p: f64,
    late_p: f64,
    last: Option<Command>,
    dropped: u64,
    late: u64,
}

impl<B: RobotBackend> RobotBackend for FaultyBackend<B> {
    fn period(&self) -> f64 {
        self.inner.period()
    }

    fn read_state(&self) -> RobotState {
        self.inner.read_state()
    }

    fn cycle(&mut self, command: &Command) -> Result<RobotState, BackendError> {
        let r: f64 = self.rng.random();
        if r < self.drop_p
            && let Some(previous) = self.last
        {
            self.dropped += 1;
            return self.inner.cycle(&previous);
        }
        self.last = Some(*command);
        if r < self.drop_p + self.late_p {
            self.late += 1;
            self.inner.cycle(command)?;
        }
        self.inner.cycle(command)
    }
}

/// A policy that misbehaves.
struct FaultySource {
    rng: StdRng,
    home: Isometry3<f64>,
    stall: Duration,
    injected: BTreeMap<&'static str, u64>,
}

impl FaultySource {
    fn reachable(&mut self) -> Keyframe {
        let r = &mut self.rng;
        let t = Translation3::new(r.random_range(-0.15..0.15), r.random_range(-0.2..0.2), r.random_range(-0.15..0.1));
        let turn = UnitQuaternion::from_euler_angles(
            r.random_range(-0.3..0.3),
            r.random_range(-0.3..0.3),
            r.random_range(-0.8..0.8),
        );
        Keyframe::at(&(t * self.home * turn), r.random_bool(0.5))
    }
}

impl KeyframeSource for FaultySource {
    fn propose(&mut self, _request: &Request) -> Result<Answer, String> {
        let good = self.reachable();
        let pick: f64 = self.rng.random();
        let (kind, answer) = match pick {
            p if p < 0.08 => {
                // beyond the arm's reach, inside the workspace box
                ("unreachable", Answer::Keyframe(Keyframe { position: [0.88, 0.55, 0.75], ..good }))
            }
            p if p < 0.16 => {
                let mut k = good;
                let bad = [f64::NAN, f64::INFINITY, f64::NEG_INFINITY][self.rng.random_range(0..3)];
                if self.rng.random_bool(0.5) {
                    k.position[self.rng.random_range(0..3)] = bad;
                } else {
                    k.quat_wxyz[self.rng.random_range(0..4)] = bad;
                }
                ("non_finite", Answer::Keyframe(k))
            }
            p if p < 0.24 => {
                let s = if self.rng.random_bool(0.5) {
                    self.rng.random_range(0.2..0.99)
                } else {
                    self.rng.random_range(1.01..3.0)
                };
                ("non_unit_quaternion", Answer::Keyframe(Keyframe { quat_wxyz: good.quat_wxyz.map(|v| v * s), ..good }))
            }
            p if p < 0.32 => {
                let mut k = good;
                k.position[self.rng.random_range(0..3)] += if self.rng.random_bool(0.5) { 1.5 } else { -1.5 };
                ("outside_workspace", Answer::Keyframe(k))
            }
            p if p < 0.42 => {
                // 4 cm into the table, fingers down: the arm pushes on the table
                let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
                let pose = Isometry3::from_parts(
                    Translation3::new(self.rng.random_range(0.35..0.6), self.rng.random_range(-0.2..0.2), -0.04),
                    down,
                );
                ("blocked_tcp", Answer::Keyframe(Keyframe::at(&pose, good.gripper_open)))
            }
            p if p < 0.52 => ("policy_failure", Answer::Failed),
            p if p < 0.55 => {
                std::thread::sleep(self.stall);
                ("policy_stall", Answer::Keyframe(good))
            }
            _ => ("reachable", Answer::Keyframe(good)),
        };
        *self.injected.entry(kind).or_default() += 1;
        if matches!(answer, Answer::Failed) {
            return Err("injected policy failure".into());
        }
        Ok(answer)
    }
}

/// One fault run from `seed`; adds its counts to `report`.
fn fault_run(seed: u64, config: Option<&std::path::Path>, report: &mut FaultReport) -> Result<(), RolloutError> {
    let mut rng = StdRng::seed_from_u64(seed);
    let world = World::load_named("default")?;
    let home = world.arm_state().tcp_in_base;
    let mut config = load_controller_config(config)?;
    let qp_timeout = rng.random_bool(0.2);
    if qp_timeout {
        config.time_limit = rng.random_range(5e-6..30e-6);
        report.count("qp_time_limit_runs", 1);
    }
    let settings = ControlSettings {
        pacing: Pacing::SimulatedLatency { ticks: rng.random_range(0..300) },
        max_ticks: 15_000,
        keyframes: Some(rng.random_range(2..6)),
        watchdog_ticks: 2_000,
        max_rejections_in_a_row: 4,
        gripper_timeout: 2.0,
        stall_timeout_s: 0.05,
    };
    let (control, planner) = realtime_stack(world, config, settings, WorkspaceBox::TABLE)?;
    let faulty_cycles = rng.random_bool(0.5);
    let (drop_p, late_p) =
        if faulty_cycles { (rng.random_range(0.0..0.05), rng.random_range(0.0..0.05)) } else { (0.0, 0.0) };
    let control = crate::runtime::control::ControlLoop {
        backend: FaultyBackend {
            inner: control.backend,
            rng: StdRng::seed_from_u64(seed ^ 0x5eed),
            drop_p,
            late_p,
            last: None,
            dropped: 0,
            late: 0,
        },
        tap: None,
        controller: control.controller,
        gripper: control.gripper,
        monitor: control.monitor,
        settings: control.settings,
    };
    let mut source = FaultySource {
        rng: StdRng::seed_from_u64(seed ^ 0xfa17),
        home,
        stall: Duration::from_millis(120),
        injected: BTreeMap::new(),
    };
    let out = run_session(control, planner, &mut source, SessionSettings::default())
        .map_err(|e| RolloutError::Thread(e.to_string()))?;
    let m = &out.summary.monitor;
    if m.violations > 0 {
        report.runs_with_violations += 1;
        report.runs_with_violations_without_blocked_tcp += u64::from(!source.injected.contains_key("blocked_tcp"));
    }
    for (kind, n) in source.injected {
        report.count(kind, n);
    }
    report.count("dropped_cycles", out.control.backend.dropped);
    report.count("late_cycles", out.control.backend.late);
    report.torque_violations += m.torque_violations;
    report.torque_rate_violations += m.torque_rate_violations;
    report.position_violations += m.position_violations;
    report.velocity_violations += m.velocity_violations;
    report.non_finite_torques += m.non_finite_torques;
    report.qp_fallbacks += out.summary.qp_fallbacks;
    report.qp_solves += out.summary.qp_solves;
    report.ticks += out.summary.ticks;
    let c = *out.control.controller.osc().config();
    for e in &out.events {
        match e {
            Event::Rejected { .. } => report.holds_rejected += 1,
            Event::WatchdogHold { .. } => report.holds_watchdog += 1,
            Event::PlanStarted { .. } => report.keyframes_commanded += 1,
            Event::KeyframeDone { outcome, .. } => {
                report.keyframes_reached += u64::from(outcome.reached(&c));
                report.holds_reflex += u64::from(outcome.reflex.is_some());
            }
            Event::Requested { .. } => {}
        }
    }
    *report.stops.entry(stop_name(out.summary.stop)).or_default() += 1;
    Ok(())
}

fn stop_name(stop: StopReason) -> &'static str {
    match stop {
        StopReason::TickLimit => "tick_limit",
        StopReason::KeyframesDone => "keyframes_done",
        StopReason::PolicySilent => "policy_silent",
        StopReason::PolicyGarbage => "policy_garbage",
        StopReason::BackendError => "backend_error",
        StopReason::SourceFinished => "source_finished",
        StopReason::Stopped => "stopped",
    }
}

/// `runs` fault runs, seeds `seed..seed + runs`; `progress` is called after each run. A panic
/// inside a run is caught and counted.
pub fn fault_runs(
    runs: u64,
    seed: u64,
    config: Option<&std::path::Path>,
    mut progress: impl FnMut(u64),
) -> Result<FaultReport, RolloutError> {
    let mut report = FaultReport::default();
    for i in 0..runs {
        let mut partial = report.clone();
        match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| fault_run(seed + i, config, &mut partial))) {
            Ok(result) => {
                result?;
                report = partial;
            }
            Err(_) => report.panics += 1,
        }
        report.runs += 1;
        progress(i + 1);
    }
    Ok(report)
}
