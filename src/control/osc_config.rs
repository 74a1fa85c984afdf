//! The controller profile (`controllers/osc.toml`): OSC gains, QP settings, fallback damping,
//! trajectory limits and the "keyframe reached" tolerances, validated on load.
use std::path::Path;

use nalgebra::Vector3;

use crate::robot::JointVector;
use crate::unit_config::{ConfigError, ConfigFile, Quantity, Sign};

/// Gains of one 3-D part of the task (position or orientation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisGains {
    /// 1/s^2 (natural frequency squared).
    pub stiffness: Vector3<f64>,
    pub damping_ratio: Vector3<f64>,
    /// 1/s^3.
    pub integral: Vector3<f64>,
    /// The integral runs only while the error is below this (m or rad).
    pub integral_zone: f64,
    /// Bound on the integral's acceleration (m/s^2 or rad/s^2).
    pub integral_limit: f64,
    /// Fastest the error is closed (m/s or rad/s), on top of the reference's own velocity.
    pub max_speed: f64,
    /// Largest feedback acceleration (m/s^2 or rad/s^2): bounds the force in contact.
    pub max_acceleration: f64,
}

impl AxisGains {
    /// Damping gain 2 * zeta * sqrt(k) (1/s).
    pub fn damping(&self) -> Vector3<f64> {
        self.stiffness.zip_map(&self.damping_ratio, |k, z| 2.0 * z * k.sqrt())
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OscConfig {
    pub position: AxisGains,
    pub orientation: AxisGains,
    pub nullspace_stiffness: f64,
    pub nullspace_damping_ratio: f64,
    pub position_weight: f64,
    pub orientation_weight: f64,
    pub posture_weight: f64,
    pub regularization: f64,
    /// Weight of the slack on the joint-limit acceleration rows (large: nearly hard).
    pub slack_weight: f64,
    pub limit_horizon: f64,
    pub limit_margin: f64,
    pub max_iterations: u32,
    /// OSQP's data scaling (Ruiz equilibration) iterations, redone at every tick's update; 0 =
    /// no scaling.
    pub scaling_iterations: u32,
    /// Wall-clock limit of one solve (s); 0 = none (deterministic lock-step simulation).
    pub time_limit: f64,
    pub fallback_damping: JointVector,
    /// Fraction of the arm model's joint friction compensated (0 = none, 1 = all).
    pub friction_compensation: f64,
    /// Velocity below which the dry-friction compensation fades (tanh), rad/s.
    pub friction_smoothing: f64,
    /// The compensation pushes toward dq_ref + gain * (q_ref - q); gain in 1/s.
    pub friction_direction_gain: f64,
    pub velocity_scale: f64,
    pub acceleration_scale: f64,
    pub jerk_scale: f64,
    pub reached_position: f64,
    pub reached_orientation: f64,
    pub settle_timeout: f64,
    /// The collision reflex (`[reflex] enabled`): an external torque above
    /// `reflex_external_torque` on any joint (Nm) stops the motion and backs the arm off.
    pub reflex_enabled: bool,
    pub reflex_external_torque: JointVector,
    /// The joint-limit rows bound the acceleration the joints will have including the measured
    /// external torque (`[qp] external_torque_in_limits`).
    pub external_torque_in_limits: bool,
}

impl OscConfig {
    /// `controllers/osc.toml`.
    pub fn default_profile() -> Result<Self, ConfigError> {
        Self::load(&crate::deps::controllers_dir().join("osc.toml"))
    }

    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        Self::from_config(ConfigFile::open(path)?)
    }

    pub fn from_config(mut f: ConfigFile) -> Result<Self, ConfigError> {
        let position = axis(&mut f, "task.position", Quantity::Length, Quantity::Acceleration, Quantity::Velocity)?;
        let orientation = axis(
            &mut f,
            "task.orientation",
            Quantity::Angle,
            Quantity::AngularAcceleration,
            Quantity::AngularVelocity,
        )?;
        let fraction = |f: &mut ConfigFile, field: &str| -> Result<f64, ConfigError> {
            let x = f.number_field(field, Sign::Positive)?;
            if x > 1.0 {
                return Err(f.error(field, format!("{x} is a fraction of the arm's limit and must be in (0, 1]")));
            }
            Ok(x)
        };
        let max_iterations = f.number_field("qp.max_iterations", Sign::Positive)?;
        if max_iterations.fract() != 0.0 || max_iterations > 1e6 {
            return Err(f.error("qp.max_iterations", "expected a whole number of iterations up to 1000000"));
        }
        let scaling_iterations = f.number_field("qp.scaling_iterations", Sign::NonNegative)?;
        if scaling_iterations.fract() != 0.0 || scaling_iterations > 100.0 {
            return Err(f.error(
                "qp.scaling_iterations",
                "expected a whole number of scaling iterations from 0 (no scaling) to 100",
            ));
        }
        let config = Self {
            position,
            orientation,
            nullspace_stiffness: f.quantity("nullspace.stiffness", Quantity::PerSecondSquared, Sign::NonNegative)?,
            nullspace_damping_ratio: f.number_field("nullspace.damping_ratio", Sign::NonNegative)?,
            position_weight: f.number_field("qp.position_weight", Sign::Positive)?,
            orientation_weight: f.number_field("qp.orientation_weight", Sign::Positive)?,
            posture_weight: f.number_field("qp.posture_weight", Sign::NonNegative)?,
            regularization: f.number_field("qp.regularization", Sign::Positive)?,
            slack_weight: f.number_field("qp.slack_weight", Sign::Positive)?,
            limit_horizon: f.quantity("qp.limit_horizon", Quantity::Time, Sign::Positive)?,
            limit_margin: f.quantity("qp.limit_margin", Quantity::Angle, Sign::NonNegative)?,
            max_iterations: max_iterations as u32,
            scaling_iterations: scaling_iterations as u32,
            time_limit: f.quantity("qp.time_limit", Quantity::Time, Sign::NonNegative)?,
            fallback_damping: JointVector::from_column_slice(&f.quantities::<7>(
                "fallback.damping",
                Quantity::JointDamping,
                Sign::NonNegative,
            )?),
            friction_compensation: {
                let x = f.number_field("friction.compensation", Sign::NonNegative)?;
                if x > 1.0 {
                    return Err(f.error("friction.compensation", format!("{x} must be a fraction in [0, 1]")));
                }
                x
            },
            friction_smoothing: f.quantity("friction.smoothing_velocity", Quantity::AngularVelocity, Sign::Positive)?,
            friction_direction_gain: f.quantity("friction.direction_gain", Quantity::PerSecond, Sign::NonNegative)?,
            velocity_scale: fraction(&mut f, "motion.velocity_scale")?,
            acceleration_scale: fraction(&mut f, "motion.acceleration_scale")?,
            jerk_scale: fraction(&mut f, "motion.jerk_scale")?,
            reached_position: f.quantity("reached.position", Quantity::Length, Sign::Positive)?,
            reached_orientation: f.quantity("reached.orientation", Quantity::Angle, Sign::Positive)?,
            settle_timeout: f.quantity("reached.settle_timeout", Quantity::Time, Sign::Positive)?,
            reflex_enabled: f.flag("reflex.enabled")?,
            external_torque_in_limits: f.flag("qp.external_torque_in_limits")?,
            reflex_external_torque: JointVector::from_column_slice(&f.quantities::<7>(
                "reflex.external_torque",
                Quantity::Torque,
                Sign::Positive,
            )?),
        };
        f.finish()?;
        Ok(config)
    }
}

fn axis(
    f: &mut ConfigFile,
    section: &str,
    zone: Quantity,
    limit: Quantity,
    speed: Quantity,
) -> Result<AxisGains, ConfigError> {
    let v3 = |a: [f64; 3]| Vector3::from(a);
    Ok(AxisGains {
        stiffness: v3(f.quantities(&format!("{section}.stiffness"), Quantity::PerSecondSquared, Sign::NonNegative)?),
        damping_ratio: v3(f.numbers(&format!("{section}.damping_ratio"), Sign::NonNegative)?),
        integral: v3(f.quantities(&format!("{section}.integral"), Quantity::PerSecondCubed, Sign::NonNegative)?),
        integral_zone: f.quantity(&format!("{section}.integral_zone"), zone, Sign::NonNegative)?,
        integral_limit: f.quantity(&format!("{section}.integral_limit"), limit, Sign::NonNegative)?,
        max_speed: f.quantity(&format!("{section}.max_speed"), speed, Sign::Positive)?,
        max_acceleration: f.quantity(&format!("{section}.max_acceleration"), limit, Sign::Positive)?,
    })
}
