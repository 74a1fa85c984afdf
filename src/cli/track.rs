//! `flowram track`: executes a keyframes file on the simulated Panda through IK -> ruckig ->
//! OSC at 1 kHz and reports each keyframe; optionally logs every tick as CSV.
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use flowram::control::keyframe::KeyframeFile;
use flowram::files::write_atomic;

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
    #[arg(long, default_value = "default")]
    scene: String,
    #[arg(long)]
    json: bool,
}

pub fn run(args: TrackArgs) -> anyhow::Result<()> {
    let file = KeyframeFile::read(&args.keyframes)?;
    let config = flowram::rollout::stack::load_controller_config(args.config.as_deref())?;
    let (mut world, mut runner) = flowram::rollout::stack::simulated_stack(&args.scene, config)?;
    if args.log.is_some() {
        runner.enable_log(file.keyframes.len() as f64 * 12.0, world.timestep());
    }
    let report = runner.run(&mut world, &file.keyframes)?;
    if let Some(path) = &args.log {
        write_atomic(path, runner.log_csv().as_bytes()).with_context(|| format!("writing {}", path.display()))?;
    }
    if args.json {
        return super::print_json(&report);
    }
    for (i, k) in report.keyframes.iter().enumerate() {
        match &k.error {
            Some(e) if !k.reached => println!("keyframe {i}: NOT reached: {e}"),
            _ => println!(
                "keyframe {i}: reached, {:.3} mm / {:.3} deg, {:.2} s{}",
                k.pos_err_mm,
                k.rot_err_deg,
                k.time_s,
                k.gripper.as_deref().map(|g| format!(", gripper {g}")).unwrap_or_default()
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
    Ok(())
}
