//! The runner: a list of keyframes (TCP pose + gripper) executed through IK -> ruckig -> OSC on
//! a robot backend at 1 kHz. Joint goals are solved before the control loop (each seeded from
//! the previous goal), so the tick never waits for IK. Per keyframe: move, settle to tolerance,
//! then open or close the gripper. Every tick is checked against the arm's limits and can be
//! logged (t, q, dq, tau, TCP pose, reference) for CSV. The keyframe format is in `keyframe`,
//! the limit monitor and log rows in `monitor`, the straight-line waypoints in `waypoints`.
use nalgebra::Isometry3;
use serde::Serialize;

use super::backend::{BackendError, Command, Cycle, RobotBackend, RobotState};
use super::controller::ArmController;
use super::execution::{Execution, ExecutionOutcome, MotionPlan};
use super::gripper::{GraspState, Gripper};
use super::ik::{InverseKinematics, target_pose};
use super::keyframe::Keyframe;
use super::monitor::{LimitMonitor, LogRow, pose7};
use super::waypoints::straight_line_goals;
use crate::robot::JointLimits;

/// How one keyframe went.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct KeyframeReport {
    pub reached: bool,
    /// TCP error after settling (before the gripper moved).
    pub pos_err_mm: f64,
    pub rot_err_deg: f64,
    /// From the start of the motion to the end of the gripper action.
    pub time_s: f64,
    pub error: Option<String>,
    /// What the gripper did (open, grasped, empty, blocked) if it was actuated; in JSON its
    /// description (`"closed on nothing"`, `"grasped (30.0 mm)"`).
    #[serde(serialize_with = "describe")]
    pub gripper: Option<GraspState>,
    /// Wall-clock time IK took for this keyframe (ms).
    pub ik_ms: f64,
}

impl KeyframeReport {
    /// A keyframe that was never executed (no plan).
    fn failed(error: String, ik_ms: f64) -> Self {
        Self {
            reached: false,
            pos_err_mm: f64::NAN,
            rot_err_deg: f64::NAN,
            time_s: 0.0,
            error: Some(error),
            gripper: None,
            ik_ms,
        }
    }
}

/// How the whole run went.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunReport {
    pub keyframes: Vec<KeyframeReport>,
    /// Ticks where a torque, torque-rate, joint-position or joint-velocity limit was exceeded.
    pub limit_violations: u64,
    /// Largest |value| / limit over the run.
    pub max_torque_ratio: f64,
    pub max_torque_rate_ratio: f64,
    pub max_velocity_ratio: f64,
    /// Ticks where the QP failed and the damping torque was used.
    pub qp_fallbacks: u64,
    pub ticks: u64,
    pub sim_time_s: f64,
}

/// Executes keyframes on a backend.
pub struct Runner {
    pub controller: ArmController,
    pub ik: InverseKinematics,
    pub monitor: LimitMonitor,
    gripper: Gripper,
    log: Option<Vec<LogRow>>,
    timings: Option<Vec<super::controller::TickTiming>>,
    /// Longest time the gripper may take to open or close (s).
    pub gripper_timeout: f64,
}

/// Why the control stack could not be assembled.
#[derive(Debug, thiserror::Error)]
pub enum StackError {
    #[error(transparent)]
    Model(#[from] crate::robot::ModelError),
    #[error(transparent)]
    Osc(#[from] super::osc::OscSetupError),
}

impl Runner {
    /// The whole stack for an arm described by `description`, holding it at `state`.
    pub fn build(
        description: &crate::robot::ArmDescription,
        limits: JointLimits,
        config: super::osc_config::OscConfig,
        state: &RobotState,
        dt: f64,
    ) -> Result<Self, StackError> {
        let kinematics = crate::robot::Kinematics::new(description)?;
        let controller = ArmController::new(kinematics, limits, config, dt, state)?;
        let ik = InverseKinematics::new(super::ik::IkConfig::default(), limits);
        Ok(Self::new(controller, ik, limits, dt, state.gripper_width > 0.04))
    }

    pub fn new(
        controller: ArmController,
        ik: InverseKinematics,
        limits: JointLimits,
        dt: f64,
        gripper_open: bool,
    ) -> Self {
        Self {
            controller,
            ik,
            monitor: LimitMonitor::new(limits, dt),
            gripper: Gripper::new(gripper_open),
            log: None,
            timings: None,
            gripper_timeout: 2.0,
        }
    }

    /// Keep a log of every tick, with room reserved for `seconds` of run at `dt`.
    pub fn enable_log(&mut self, seconds: f64, dt: f64) {
        self.log = Some(Vec::with_capacity((seconds / dt) as usize));
    }

    /// Keep each tick's compute time (room for `ticks` ticks).
    pub fn enable_timing(&mut self, ticks: usize) {
        self.timings = Some(Vec::with_capacity(ticks));
    }

    pub fn timings(&self) -> Option<&[super::controller::TickTiming]> {
        self.timings.as_deref()
    }

    pub fn log(&self) -> Option<&[LogRow]> {
        self.log.as_deref()
    }

    /// The log as CSV text (header + one line per tick).
    pub fn log_csv(&self) -> String {
        let rows = self.log.as_deref().unwrap_or_default();
        let mut out = String::with_capacity(64 + rows.len() * 400);
        out.push_str(LogRow::CSV_HEADER);
        out.push('\n');
        for r in rows {
            r.csv_line(&mut out);
        }
        out
    }

    /// Runs all keyframes in one continuous control session; an unreachable keyframe is
    /// reported and skipped. Every keyframe is planned first (each seeded from the previous
    /// goal), so the torque stream never pauses between keyframes: on a robot that aborts after
    /// a few missed cycles, one session must carry the whole run.
    pub fn run<B: RobotBackend>(&mut self, backend: &mut B, keyframes: &[Keyframe]) -> Result<RunReport, BackendError> {
        let start_ticks = self.monitor_ticks();
        let t_start = backend.read_state().time;
        let mut reports: Vec<Option<KeyframeReport>> = vec![None; keyframes.len()];
        // (keyframe index, plan, IK time in ms)
        let mut plans: Vec<(usize, MotionPlan, f64)> = Vec::with_capacity(keyframes.len());
        let mut seed = backend.read_state().q;
        for (i, keyframe) in keyframes.iter().enumerate() {
            let ik_start = std::time::Instant::now();
            let from = self.controller.kinematics_mut().tcp(&seed).unwrap_or_else(|_| Isometry3::identity());
            let goal = target_pose(keyframe.position, keyframe.quat_wxyz).and_then(|target| {
                let goals = straight_line_goals(&self.ik, self.controller.kinematics_mut(), &from, &target, &seed)?;
                Ok((target, goals))
            });
            let ik_ms = ik_start.elapsed().as_secs_f64() * 1e3;
            let planned = goal.map_err(|e| e.to_string()).and_then(|(target, goals)| {
                let plan = MotionPlan::new(target, &goals, keyframe.gripper_open).map_err(|e| e.to_string())?;
                Ok((plan, *goals.last().unwrap_or(&seed)))
            });
            match planned {
                Ok((plan, last)) => {
                    seed = last;
                    plans.push((i, plan, ik_ms));
                }
                Err(e) => reports[i] = Some(KeyframeReport::failed(e, ik_ms)),
            }
        }
        // (keyframe index, outcome, start and end time of its execution)
        let mut done: Vec<(usize, ExecutionOutcome, f64, f64)> = Vec::with_capacity(plans.len());
        if !plans.is_empty() {
            let period = backend.period();
            let mut next = 0;
            let mut current: Option<(usize, Execution, f64)> = None;
            backend.control(|state| {
                let (i, execution, t0) = current.get_or_insert_with(|| {
                    let (i, plan, _) = plans[next];
                    next += 1;
                    (i, Execution::start(plan, &self.gripper, self.gripper_timeout), state.time)
                });
                execution.before_tick(&mut self.controller, &mut self.gripper, state);
                let command = self.tick(state);
                if !execution.after_tick(&self.controller, &mut self.gripper, state) {
                    return Cycle::Continue(command);
                }
                // The command is applied for one more period: the execution ends then.
                done.push((*i, execution.outcome(), *t0, state.time + period));
                current = None;
                if next == plans.len() { Cycle::Finish(command) } else { Cycle::Continue(command) }
            })?;
        }
        for (i, outcome, t0, t1) in done {
            let (ep, er) = (outcome.position_error(), outcome.rotation_error());
            let c = self.controller.osc().config();
            let ik_ms = plans.iter().find(|p| p.0 == i).map_or(0.0, |p| p.2);
            reports[i] = Some(KeyframeReport {
                reached: outcome.reached(c),
                pos_err_mm: ep * 1e3,
                rot_err_deg: er.to_degrees(),
                time_s: t1 - t0,
                error: outcome.problem(c),
                gripper: outcome.gripper,
                ik_ms,
            });
        }
        let reports = reports
            .into_iter()
            .map(|r| r.unwrap_or_else(|| KeyframeReport::failed("the control session ended before it".into(), 0.0)))
            .collect();
        let m = &self.monitor;
        Ok(RunReport {
            keyframes: reports,
            limit_violations: m.violations,
            max_torque_ratio: m.max_torque_ratio,
            max_torque_rate_ratio: m.max_torque_rate_ratio,
            max_velocity_ratio: m.max_velocity_ratio,
            qp_fallbacks: self.controller.osc().stats().fallbacks,
            ticks: self.monitor_ticks() - start_ticks,
            sim_time_s: backend.read_state().time - t_start,
        })
    }

    /// The limits the run is checked against.
    pub fn monitor_limits(&self) -> &JointLimits {
        &self.monitor.limits
    }

    fn monitor_ticks(&self) -> u64 {
        self.controller.osc().stats().ticks
    }

    /// One control tick with limit checks and logging.
    fn tick(&mut self, state: &RobotState) -> Command {
        let command = self.controller.tick(state);
        if let Some(t) = self.timings.as_mut()
            && t.len() < t.capacity()
        {
            t.push(self.controller.timing());
        }
        self.monitor.check(state, &command.tau);
        if let Some(log) = self.log.as_mut()
            && log.len() < log.capacity()
        {
            let reference = self.controller.task_reference().map_or([f64::NAN; 7], |r| pose7(&r.pose));
            log.push(LogRow {
                t: state.time,
                q: state.q,
                dq: state.dq,
                tau: command.tau,
                tcp: pose7(self.controller.tcp()),
                reference,
                q_ref: self.controller.reference().q,
            });
        }
        command
    }
}

fn describe<S: serde::Serializer>(g: &Option<GraspState>, serializer: S) -> Result<S::Ok, S::Error> {
    match g {
        Some(g) => serializer.collect_str(g),
        None => serializer.serialize_none(),
    }
}
