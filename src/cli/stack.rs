//! Assembling the simulated Panda and its control stack for the control subcommands.
use std::path::Path;

use anyhow::Context;
use flowram::control::backend::RobotBackend;
use flowram::control::osc_config::OscConfig;
use flowram::control::runner::Runner;
use flowram::robot::JointLimits;
use flowram::sim::World;

/// The controller profile: a path, or the shipped `controllers/osc.toml`.
pub fn load_config(path: Option<&Path>) -> anyhow::Result<OscConfig> {
    Ok(match path {
        Some(p) => OscConfig::load(p)?,
        None => OscConfig::default_profile()?,
    })
}

/// World (at `home`) + runner with the given profile.
pub fn simulated_stack(scene: &str, config: OscConfig) -> anyhow::Result<(World, Runner)> {
    let world = World::load_named(scene)?;
    let limits = JointLimits::panda()?;
    let description = world.arm_description()?;
    let runner = Runner::build(&description, limits, config, &world.read_state(), world.timestep())
        .context("building the control stack")?;
    Ok((world, runner))
}
