//! [`FrankaBackend`]: `franka-rs`'s torque control mapped onto [`RobotBackend`].
use ::franka::{FciVersion, FrankaError, RealtimeConfig, Robot, RobotOptions, Torques, VersionPolicy};

use super::FrankaRobot;
use super::collision::CollisionProfile;
use super::gripper::GripperWorker;
use super::guard::TorqueGuard;
use crate::control::backend::{BackendError, Command, Cycle, RobotBackend, RobotMode, RobotState};
use crate::robot::JointVector;
use crate::runtime::pacing::SchedulingRestore;

/// The robot echoes the command it received in float32: agreement within a few float32 steps
/// of the torque means it got the command last sent.
fn echo_agrees(sent: &JointVector, echo: &JointVector) -> bool {
    (0..7).all(|i| (sent[i] - echo[i]).abs() <= 4.0 * f64::from(f32::EPSILON) * sent[i].abs().max(1.0))
}

/// How to reach the robot.
#[derive(Debug, Clone)]
pub struct FrankaOptions {
    /// `host` or `host:port` of the robot's control box (FCI command port 1337 by default).
    pub address: String,
    pub robot: FrankaRobot,
    pub collision: CollisionProfile,
    /// Drive the hand (its service on port 1338 of the same host).
    pub gripper: bool,
}

/// A Franka arm under torque control.
pub struct FrankaBackend {
    robot: Robot,
    gripper: Option<GripperWorker>,
    guard: TorqueGuard,
    /// The robot's clock (s) at the first state read: `RobotState::time` counts from it.
    clock_origin: f64,
    state: RobotState,
    figures: SessionFigures,
}

/// What the robot's side saw over the backend's control sessions.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct SessionFigures {
    /// Control cycles run.
    pub cycles: u64,
    /// Cycles whose command the torque guard had to change (by more than rounding), and the
    /// largest change it made (Nm).
    pub guarded_cycles: u64,
    pub max_guard_change: f64,
    /// Lowest command success rate the robot reported (after each session's first 100 cycles,
    /// its averaging window).
    pub min_command_success_rate: f64,
    /// Largest change between consecutive torques the robot received (Nm per 1 ms cycle,
    /// from its `tau_J_d` echo): the torque rate on the robot's side.
    pub max_received_torque_step: f64,
}

impl std::fmt::Debug for FrankaBackend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrankaBackend").field("state", &self.state).finish_non_exhaustive()
    }
}

fn host_of(address: &str) -> &str {
    address.rsplit_once(':').map_or(address, |(host, _)| host)
}

fn connect_error(address: &str, e: &FrankaError) -> BackendError {
    BackendError::Connect { address: address.to_string(), detail: e.to_string() }
}

/// A `franka-rs` error as the backend's: reflexes (with their flags named) and communication
/// aborts are told apart from the rest.
fn backend_error(e: FrankaError) -> BackendError {
    match e {
        FrankaError::Control(c) => {
            let errors = c.last_motion_errors.names();
            if errors.contains(&"communication_constraints_violation") {
                BackendError::Communication(c.message)
            } else {
                let errors = if errors.is_empty() { "no error flag set".to_string() } else { errors.join(", ") };
                BackendError::Reflex { errors, detail: c.message }
            }
        }
        FrankaError::Network(m) => BackendError::Communication(m),
        FrankaError::InvalidArgument(m) | FrankaError::InvalidOperation(m) | FrankaError::Command(m) => {
            BackendError::Rejected(m)
        }
        other => BackendError::Rejected(other.to_string()),
    }
}

fn mode(m: ::franka::RobotMode) -> RobotMode {
    match m {
        ::franka::RobotMode::Move => RobotMode::Move,
        ::franka::RobotMode::Idle => RobotMode::Idle,
        ::franka::RobotMode::Reflex => RobotMode::Reflex,
        ::franka::RobotMode::UserStopped => RobotMode::UserStopped,
        ::franka::RobotMode::AutomaticErrorRecovery => RobotMode::AutomaticErrorRecovery,
        _ => RobotMode::Other,
    }
}

/// The robot's state as the controller's. Allocation-free (runs in the control callback).
fn convert(s: &::franka::RobotState, clock_origin: f64, gripper: Option<&GripperWorker>, open: bool) -> RobotState {
    let v = |a: &[f64; 7]| JointVector::from_column_slice(a);
    // Without a hand the fingers are reported where they were told to go.
    let (gripper_width, gripper_speed) =
        gripper.map_or((if open { 0.08 } else { 0.0 }, 0.0), GripperWorker::width_and_speed);
    let errors = s.current_errors.0.iter().enumerate().fold(0u64, |bits, (i, &set)| bits | (u64::from(set) << i));
    RobotState {
        time: s.time.as_secs_f64() - clock_origin,
        q: v(&s.q),
        dq: v(&s.dq),
        tau: v(&s.tau_J),
        gripper_width,
        gripper_speed,
        tau_commanded: v(&s.tau_J_d),
        tau_ext: v(&s.tau_ext_hat_filtered),
        command_success_rate: s.control_command_success_rate,
        mode: mode(s.robot_mode),
        errors,
    }
}

impl FrankaBackend {
    /// Connects (the protocol version of `options.robot`), sets the collision thresholds and
    /// starts the hand's workers. The calling thread's scheduling is left as it was (the
    /// client library raises it).
    pub fn connect(options: &FrankaOptions) -> Result<Self, BackendError> {
        let version = match options.robot {
            FrankaRobot::Panda => FciVersion::V5,
            FrankaRobot::Fr3 => FciVersion::V10,
        };
        let robot = {
            let _restore = SchedulingRestore::save();
            Robot::with_options(
                &options.address,
                RobotOptions::new(RealtimeConfig::Ignore).with_version(VersionPolicy::Exact(version)),
            )
            .map_err(|e| connect_error(&options.address, &e))?
        };
        let c = &options.collision;
        robot
            .set_collision_behavior(
                c.lower_acceleration.torque,
                c.upper_acceleration.torque,
                c.lower_nominal.torque,
                c.upper_nominal.torque,
                c.lower_acceleration.wrench,
                c.upper_acceleration.wrench,
                c.lower_nominal.wrench,
                c.upper_nominal.wrench,
            )
            .map_err(backend_error)?;
        let gripper = if options.gripper { Some(GripperWorker::start(host_of(&options.address))?) } else { None };
        let limits = options.robot.limits().map_err(|e| BackendError::Rejected(e.to_string()))?;
        let first = robot.read_once().map_err(backend_error)?;
        let clock_origin = first.time.as_secs_f64();
        let state = convert(&first, clock_origin, gripper.as_ref(), true);
        let figures = SessionFigures { min_command_success_rate: 1.0, ..SessionFigures::default() };
        Ok(Self { robot, gripper, guard: TorqueGuard::new(&limits, 0.001), clock_origin, state, figures })
    }

    /// Reads a fresh state (outside a control session).
    pub fn refresh(&mut self) -> Result<RobotState, BackendError> {
        let s = self.robot.read_once().map_err(backend_error)?;
        self.state = convert(&s, self.clock_origin, self.gripper.as_ref(), self.state.gripper_width > 0.04);
        Ok(self.state)
    }

    /// Clears a reflex (automatic error recovery) so that a new session can start.
    pub fn recover(&mut self) -> Result<RobotState, BackendError> {
        self.robot.automatic_error_recovery().map_err(backend_error)?;
        self.refresh()
    }

    /// What the robot's side saw so far.
    pub fn figures(&self) -> SessionFigures {
        self.figures
    }

    /// Commands sent to the hand, how many it refused or failed, and its failed state reads.
    pub fn gripper_commands(&self) -> (u64, u64, u64) {
        self.gripper.as_ref().map_or((0, 0, 0), GripperWorker::commands)
    }
}

impl RobotBackend for FrankaBackend {
    fn period(&self) -> f64 {
        0.001
    }

    fn read_state(&self) -> RobotState {
        self.state
    }

    /// A Franka runs whole sessions paced by its packets ([`RobotBackend::control`]); single
    /// cycles would stop the torque stream between calls.
    fn cycle(&mut self, _command: &Command) -> Result<RobotState, BackendError> {
        Err(BackendError::Unsupported(
            "the Franka backend runs whole control sessions (RobotBackend::control), not single cycles",
        ))
    }

    /// One torque session, paced by the robot's packets, on the calling thread at SCHED_FIFO
    /// where permitted. Every command passes the torque guard; a non-finite one ends the
    /// session with [`BackendError::NonFiniteTorque`].
    fn control<F>(&mut self, mut callback: F) -> Result<RobotState, BackendError>
    where
        F: FnMut(&RobotState) -> Cycle,
    {
        let (_restore, _fifo) = SchedulingRestore::raise_to_fifo();
        let clock_origin = self.clock_origin;
        let guard = self.guard;
        let mut gripper = self.gripper.as_mut();
        let mut open = self.state.gripper_width > 0.04;
        let mut failure = None;
        let mut figures = self.figures;
        let mut session_cycles = 0u64;
        let mut last = self.state;
        let mut received: Option<JointVector> = None;
        let mut sent: Option<JointVector> = None;
        let result = self.robot.control_torques(
            |s, _dt| {
                let state = convert(s, clock_origin, gripper.as_deref(), open);
                last = state;
                session_cycles += 1;
                figures.cycles += 1;
                if session_cycles > 100 {
                    figures.min_command_success_rate = figures.min_command_success_rate.min(state.command_success_rate);
                }
                if let Some(before) = received {
                    let step = (state.tau_commanded - before).amax();
                    figures.max_received_torque_step = figures.max_received_torque_step.max(step);
                }
                received = Some(state.tau_commanded);
                let (command, finish) = match callback(&state) {
                    Cycle::Continue(c) => (c, false),
                    Cycle::Finish(c) => (c, true),
                };
                open = command.gripper_open;
                if let Some(g) = gripper.as_mut() {
                    g.command(open);
                }
                // Against the command last sent, exact, while the robot's float32 echo of it
                // agrees; against the echo when it does not (a command the robot never got).
                let reference = match sent {
                    Some(sent) if echo_agrees(&sent, &state.tau_commanded) => sent,
                    _ => state.tau_commanded,
                };
                let out = guard.apply(&command.tau, &reference);
                sent = Some(out.tau);
                figures.guarded_cycles += u64::from(out.clamped);
                if out.non_finite.is_none() {
                    figures.max_guard_change = figures.max_guard_change.max((out.tau - command.tau).amax());
                }
                if let Some(joint) = out.non_finite {
                    failure.get_or_insert(BackendError::NonFiniteTorque { joint });
                }
                let mut tau_j = [0.0; 7];
                tau_j.copy_from_slice(out.tau.as_slice());
                Torques { tau_J: tau_j, motion_finished: finish || failure.is_some() }
            },
            false,
            ::franka::lowpass_filter::MAX_CUTOFF_FREQUENCY,
        );
        self.figures = figures;
        self.state = last;
        result.map_err(backend_error)?;
        if let Some(e) = failure {
            return Err(e);
        }
        self.refresh()
    }
}
