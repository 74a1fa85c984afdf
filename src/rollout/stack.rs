//! The simulated Panda with its control stack (IK -> ruckig -> OSC at 1 kHz), assembled for a
//! world: what `flowram track`, `tune`, `bench control` and every episode run on.
use std::path::Path;

use super::RolloutError;
use crate::control::backend::RobotBackend;
use crate::control::gripper::Gripper;
use crate::control::osc_config::OscConfig;
use crate::control::runner::{Runner, StackError};
use crate::robot::{JointLimits, Kinematics};
use crate::runtime::control::{ControlLoop, ControlSettings};
use crate::runtime::planner::{Planner, WorkspaceBox};
use crate::sim::World;
use crate::sim::backend::DetachedWorld;

/// The controller profile at `path`, or the shipped `controllers/osc.toml`.
pub fn load_controller_config(path: Option<&Path>) -> Result<OscConfig, RolloutError> {
    Ok(match path {
        Some(p) => OscConfig::load(p)?,
        None => OscConfig::default_profile()?,
    })
}

/// The control stack for the Panda of `world` with the profile `config` (the Panda's rated
/// limits), holding the arm where it is.
pub fn build_runner(world: &World, config: OscConfig) -> Result<Runner, RolloutError> {
    let limits = JointLimits::panda()?;
    let description = world.arm_description()?;
    Ok(Runner::build(&description, limits, config, &world.read_state(), world.timestep())?)
}

/// The world of scene `scene` (at `home`) and its control stack with the profile `config`.
pub fn simulated_stack(scene: &str, config: OscConfig) -> Result<(World, Runner), RolloutError> {
    let world = World::load_named(scene)?;
    let runner = build_runner(&world, config)?;
    Ok((world, runner))
}

/// The control loop of the real-time runtime for `world` with the profile `config` (the Panda's
/// rated limits), and its planner (own kinematics, the same IK settings, keyframes checked
/// against `workspace`), holding the arm where it is.
pub fn realtime_stack(
    world: World,
    config: OscConfig,
    settings: ControlSettings,
    workspace: WorkspaceBox,
) -> Result<(ControlLoop<DetachedWorld>, Planner), RolloutError> {
    let runner = build_runner(&world, config)?;
    let kinematics = Kinematics::new(&world.arm_description()?).map_err(StackError::from)?;
    let open = world.read_state().gripper_width > 0.04;
    let planner = Planner { ik: runner.ik, kinematics, workspace };
    let control = ControlLoop {
        backend: world.detach()?,
        tap: None,
        controller: runner.controller,
        gripper: Gripper::new(open),
        monitor: runner.monitor,
        settings,
    };
    Ok((control, planner))
}
