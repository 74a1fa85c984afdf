//! The simulated Panda with its control stack (IK -> ruckig -> OSC at 1 kHz), assembled for a
//! world: what `flowram track`, `tune`, `bench control` and every episode run on.
use std::path::Path;

use super::RolloutError;
use crate::control::backend::RobotBackend;
use crate::control::osc_config::OscConfig;
use crate::control::runner::Runner;
use crate::robot::JointLimits;
use crate::sim::World;

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
