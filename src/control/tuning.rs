//! Step responses for controller tuning: the reference jumps (or moves through ruckig) by a
//! Cartesian step from the current pose, and the TCP's response is measured: rise time (10 to
//! 90 %), overshoot, 2 % settling time, steady-state error, peak torque.
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use super::backend::{BackendError, Cycle, RobotBackend};
use super::ik::IkError;
use super::pose_error::rotation_error;
use super::runner::Runner;

/// A step of the TCP reference: translation (m) and rotation vector (rad), base-frame axes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Step {
    pub translation: Vector3<f64>,
    pub rotation: Vector3<f64>,
}

impl std::str::FromStr for Step {
    type Err = String;

    /// `dx,dy,dz` or `dx,dy,dz,rx,ry,rz` (metres, radians).
    fn from_str(s: &str) -> Result<Self, String> {
        let values: Vec<f64> = s
            .split(',')
            .map(|v| v.trim().parse::<f64>().map_err(|_| format!("`{v}` is not a number")))
            .collect::<Result<_, _>>()?;
        if !(values.len() == 3 || values.len() == 6) {
            return Err(format!("expected dx,dy,dz[,rx,ry,rz] (metres, radians), got {} values", values.len()));
        }
        if values.iter().any(|v| !v.is_finite()) {
            return Err("step values must be finite".into());
        }
        let r = if values.len() == 6 { Vector3::new(values[3], values[4], values[5]) } else { Vector3::zeros() };
        let step = Self { translation: Vector3::new(values[0], values[1], values[2]), rotation: r };
        if step.translation.norm() == 0.0 && step.rotation.norm() == 0.0 {
            return Err("the step is zero; give a translation or a rotation".into());
        }
        Ok(step)
    }
}

/// The measured response.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StepMetrics {
    pub rise_time_s: Option<f64>,
    pub overshoot_pct: f64,
    pub settling_time_s: Option<f64>,
    pub steady_state_error_mm: f64,
    pub steady_state_error_deg: f64,
    pub peak_torque_ratio: f64,
    pub qp_fallbacks: u64,
}

/// Time series of a step run: TCP and reference as [x, y, z (m), rx, ry, rz (rad)] relative to
/// the start pose (rotation vectors of R R0^T).
#[derive(Debug, Clone, PartialEq)]
pub struct StepRun {
    pub t: Vec<f64>,
    pub reference: Vec<[f64; 6]>,
    pub response: Vec<[f64; 6]>,
    pub metrics: StepMetrics,
    pub smooth: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum TuneError {
    #[error("the stepped pose is not reachable: {0}")]
    Unreachable(#[from] IkError),
    #[error(transparent)]
    Backend(#[from] BackendError),
}

fn relative(pose: &Isometry3<f64>, start: &Isometry3<f64>) -> [f64; 6] {
    let d = pose.translation.vector - start.translation.vector;
    let r = rotation_error(&pose.rotation, &start.rotation);
    [d.x, d.y, d.z, r.x, r.y, r.z]
}

/// Applies `step` to the reference from the current pose and records `duration` seconds.
pub fn step_response<B: RobotBackend>(
    backend: &mut B,
    runner: &mut Runner,
    step: &Step,
    smooth: bool,
    duration: f64,
) -> Result<StepRun, TuneError> {
    let q0 = backend.read_state().q;
    let kin = runner.controller.kinematics_mut();
    let start = kin.tcp(&q0).map_err(IkError::from)?;
    let target = Isometry3::from_parts(
        Translation3::from(start.translation.vector + step.translation),
        UnitQuaternion::from_scaled_axis(step.rotation) * start.rotation,
    );
    let goal = runner.ik.solve(kin, &target, &q0)?.q;
    if smooth {
        runner.controller.set_goal(&goal);
    } else {
        runner.controller.jump_reference(&goal);
    }
    let ticks = (duration / backend.period()).ceil() as usize;
    let (mut t, mut reference, mut response) =
        (Vec::with_capacity(ticks), Vec::with_capacity(ticks), Vec::with_capacity(ticks));
    let t0 = backend.read_state().time;
    let mut peak: f64 = 0.0;
    let torque_limit = runner.monitor_limits().torque;
    backend.control(|state| {
        let command = runner.controller.tick(state);
        for i in 0..7 {
            peak = peak.max(command.tau[i].abs() / torque_limit[i]);
        }
        t.push(state.time - t0);
        reference.push(runner.controller.task_reference().map_or([0.0; 6], |r| relative(&r.pose, &start)));
        response.push(relative(runner.controller.tcp(), &start));
        if t.len() >= ticks { Cycle::Finish(command) } else { Cycle::Continue(command) }
    })?;
    let final_pose = {
        let q = backend.read_state().q;
        runner.controller.kinematics_mut().tcp(&q).map_err(IkError::from)?
    };
    let mut metrics = analyze(&t, &response, step, &target, &final_pose);
    metrics.peak_torque_ratio = peak;
    metrics.qp_fallbacks = runner.controller.osc().stats().fallbacks;
    Ok(StepRun { t, reference, response, metrics, smooth })
}

/// Progress along the step (0 at the start, 1 at the target): the translation's projection
/// when the step translates, else the rotation's.
fn progress(sample: &[f64; 6], step: &Step) -> f64 {
    let (d, r) = (step.translation, step.rotation);
    if d.norm() > 0.0 {
        Vector3::new(sample[0], sample[1], sample[2]).dot(&d) / d.norm_squared()
    } else {
        Vector3::new(sample[3], sample[4], sample[5]).dot(&r) / r.norm_squared()
    }
}

fn analyze(
    t: &[f64],
    response: &[[f64; 6]],
    step: &Step,
    target: &Isometry3<f64>,
    final_pose: &Isometry3<f64>,
) -> StepMetrics {
    let s: Vec<f64> = response.iter().map(|x| progress(x, step)).collect();
    let first = |level: f64| s.iter().position(|&v| v >= level).map(|i| t[i]);
    let rise_time_s = match (first(0.1), first(0.9)) {
        (Some(a), Some(b)) => Some(b - a),
        _ => None,
    };
    let peak = s.iter().cloned().fold(f64::MIN, f64::max);
    let overshoot_pct = ((peak - 1.0) * 100.0).max(0.0);
    // Settled once the progress stays within 2 % of the step.
    let last_outside = s.iter().rposition(|&v| (v - 1.0).abs() > 0.02);
    let settling_time_s = match last_outside {
        None => Some(0.0),
        Some(i) if i + 1 < t.len() => Some(t[i + 1]),
        Some(_) => None,
    };
    StepMetrics {
        rise_time_s,
        overshoot_pct,
        settling_time_s,
        steady_state_error_mm: (final_pose.translation.vector - target.translation.vector).norm() * 1e3,
        steady_state_error_deg: rotation_error(&target.rotation, &final_pose.rotation).norm().to_degrees(),
        peak_torque_ratio: 0.0,
        qp_fallbacks: 0,
    }
}
