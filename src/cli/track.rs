//! `flowram track`: executes a keyframes file through IK -> ruckig -> OSC at 1 kHz, on the
//! simulated Panda or on a real Franka (`--backend franka`, cargo feature `franka`), in one
//! continuous torque session, and reports each keyframe; optionally logs every tick as CSV.
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use flowram::control::keyframe::KeyframeFile;
use flowram::control::runner::{RunReport, Runner};
use flowram::files::write_atomic;
use flowram::franka::FrankaRobot;

/// Which Franka (`--robot`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum RobotArg {
    /// Franka Emika Panda (FER): FCI v5, controllers/panda_limits.toml.
    Panda,
    /// Franka Research 3: FCI v10, controllers/fr3_limits.toml.
    Fr3,
}

impl From<RobotArg> for FrankaRobot {
    fn from(r: RobotArg) -> Self {
        match r {
            RobotArg::Panda => FrankaRobot::Panda,
            RobotArg::Fr3 => FrankaRobot::Fr3,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Backend {
    /// The MuJoCo-simulated Panda.
    Sim,
    /// A Franka arm (or a Franka-protocol simulator) at --robot-ip.
    Franka,
}

#[derive(Debug, Args)]
pub struct TrackArgs {
    /// Keyframes JSON: {"keyframes":[{"position":[x,y,z],"quat_wxyz":[w,x,y,z],"gripper_open":true}, ...]}
    /// (TCP poses in the robot base frame panda_link0, metres).
    #[arg(long)]
    keyframes: PathBuf,
    /// Write every tick (t, q, dq, tau, TCP pose, reference) to this CSV file.
    #[arg(long)]
    log: Option<PathBuf>,
    /// Controller profile (TOML); default controllers/osc.toml.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Scene of the simulated backend (models/<scene>.xml).
    #[arg(long, default_value = "default")]
    scene: String,
    /// Where the keyframes run.
    #[arg(long, value_enum, default_value = "sim")]
    backend: Backend,
    /// The robot's address for --backend franka: HOST or HOST:PORT (FCI port 1337 by default).
    #[arg(long)]
    robot_ip: Option<String>,
    /// Which Franka (--backend franka): its protocol version and joint limits.
    #[arg(long, value_enum, default_value = "fr3")]
    robot: RobotArg,
    /// Collision thresholds sent to the Franka (TOML); default controllers/franka_collision.toml.
    #[arg(long)]
    collision: Option<PathBuf>,
    /// Do not drive the Franka's hand.
    #[arg(long)]
    no_gripper: bool,
    #[arg(long)]
    json: bool,
}

/// `track --json` output: the run, plus the robot's side of it on a Franka.
#[derive(Debug, serde::Serialize)]
struct TrackReport {
    #[serde(flatten)]
    run: RunReport,
    #[serde(skip_serializing_if = "Option::is_none")]
    franka: Option<FrankaFigures>,
}

#[derive(Debug, serde::Serialize)]
#[cfg_attr(not(feature = "franka"), allow(dead_code))]
struct FrankaFigures {
    robot: FrankaRobot,
    #[cfg(feature = "franka")]
    #[serde(flatten)]
    session: flowram::franka::SessionFigures,
    /// Commands sent to the hand, how many it refused or failed, and failed reads of its state.
    gripper_commands: u64,
    gripper_failures: u64,
    gripper_read_errors: u64,
}

pub fn run(args: TrackArgs) -> anyhow::Result<()> {
    let file = KeyframeFile::read(&args.keyframes)?;
    let config = flowram::rollout::stack::load_controller_config(args.config.as_deref())?;
    if args.backend == Backend::Sim && (args.robot_ip.is_some() || args.collision.is_some() || args.no_gripper) {
        bail!(
            "--robot-ip, --collision and --no-gripper are for --backend franka; the simulated Panda needs none of them"
        );
    }
    let log_seconds = file.keyframes.len() as f64 * 12.0;
    let (report, runner, franka) = match args.backend {
        Backend::Sim => {
            let (mut world, mut runner) = flowram::rollout::stack::simulated_stack(&args.scene, config)?;
            if args.log.is_some() {
                runner.enable_log(log_seconds, world.timestep());
            }
            (runner.run(&mut world, &file.keyframes)?, runner, None)
        }
        Backend::Franka => {
            let Some(address) = args.robot_ip.as_deref() else {
                bail!(
                    "--backend franka needs --robot-ip HOST[:PORT] (the robot's control box, or a franka-sim server)"
                );
            };
            let (report, runner, figures) = run_on_franka(
                address,
                args.robot.into(),
                args.collision.as_deref(),
                !args.no_gripper,
                config,
                &file,
                args.log.is_some(),
                log_seconds,
            )?;
            (report, runner, Some(figures))
        }
    };
    if let Some(path) = &args.log {
        write_atomic(path, runner.log_csv().as_bytes()).with_context(|| format!("writing {}", path.display()))?;
    }
    if args.json {
        return super::print_json(&TrackReport { run: report, franka });
    }
    for (i, k) in report.keyframes.iter().enumerate() {
        match &k.error {
            Some(e) if !k.reached => println!("keyframe {i}: NOT reached: {e}"),
            _ => println!(
                "keyframe {i}: reached, {:.3} mm / {:.3} deg, {:.2} s{}",
                k.pos_err_mm,
                k.rot_err_deg,
                k.time_s,
                k.gripper.map(|g| format!(", gripper {g}")).unwrap_or_default()
            ),
        }
    }
    println!(
        "limit violations: {}, max torque {:.0} % of limit, max torque rate {:.0} % of limit, QP fallbacks: {}",
        report.limit_violations,
        report.max_torque_ratio * 100.0,
        report.max_torque_rate_ratio * 100.0,
        report.qp_fallbacks
    );
    #[cfg(feature = "franka")]
    if let Some(f) = &franka {
        println!(
            "franka: {} cycles, lowest command success rate {:.3}, largest torque step the robot received {:.3} Nm/ms, {} commands changed by the torque guard (at most {:.2e} Nm), hand: {} commands ({} failed)",
            f.session.cycles,
            f.session.min_command_success_rate,
            f.session.max_received_torque_step,
            f.session.guarded_cycles,
            f.session.max_guard_change,
            f.gripper_commands,
            f.gripper_failures
        );
    }
    Ok(())
}

/// The keyframes on a Franka: the stack is built from the Panda model (the FR3 shares its
/// kinematics to within millimetres) with the chosen arm's limits.
#[cfg(feature = "franka")]
#[allow(clippy::too_many_arguments)]
fn run_on_franka(
    address: &str,
    robot: FrankaRobot,
    collision: Option<&std::path::Path>,
    gripper: bool,
    config: flowram::control::osc_config::OscConfig,
    file: &KeyframeFile,
    log: bool,
    log_seconds: f64,
) -> anyhow::Result<(RunReport, Runner, FrankaFigures)> {
    use flowram::control::backend::{BackendError, RobotBackend};
    use flowram::franka::collision::CollisionProfile;
    use flowram::franka::{FrankaBackend, FrankaOptions};
    let collision = match collision {
        Some(p) => CollisionProfile::load(p)?,
        None => CollisionProfile::default_profile()?,
    };
    let description = flowram::sim::World::load_named("default")?.arm_description()?;
    let options = FrankaOptions { address: address.to_string(), robot, collision, gripper };
    let mut backend = FrankaBackend::connect(&options)?;
    let mut runner = Runner::build(&description, robot.limits()?, config, &backend.read_state(), backend.period())?;
    if log {
        runner.enable_log(log_seconds, backend.period());
    }
    let report = match runner.run(&mut backend, &file.keyframes) {
        Ok(report) => report,
        // The robot stopped the motion: clear the error so that it is ready again, and say so.
        Err(e @ (BackendError::Reflex { .. } | BackendError::Communication(_))) => match backend.recover() {
            Ok(_) => bail!("{e}; the robot was then recovered (automatic error recovery) and is ready for a new run"),
            Err(r) => bail!("{e}; automatic error recovery failed as well ({r}): recover the robot from Desk"),
        },
        Err(e) => return Err(e.into()),
    };
    let (gripper_commands, gripper_failures, gripper_read_errors) = backend.gripper_commands();
    let figures =
        FrankaFigures { robot, session: backend.figures(), gripper_commands, gripper_failures, gripper_read_errors };
    Ok((report, runner, figures))
}

#[cfg(not(feature = "franka"))]
#[allow(clippy::too_many_arguments)]
fn run_on_franka(
    _address: &str,
    _robot: FrankaRobot,
    _collision: Option<&std::path::Path>,
    _gripper: bool,
    _config: flowram::control::osc_config::OscConfig,
    _file: &KeyframeFile,
    _log: bool,
    _log_seconds: f64,
) -> anyhow::Result<(RunReport, Runner, FrankaFigures)> {
    bail!(
        "this flowram was built without the Franka backend; rebuild it with `cargo build --release --features franka` (see docs/franka.md)"
    )
}
