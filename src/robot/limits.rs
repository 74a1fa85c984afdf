//! The Panda's joint limits (position, velocity, acceleration, jerk, torque, torque rate),
//! read from `controllers/panda_limits.toml` and validated.
use std::path::Path;

use crate::robot::JointVector;
use crate::unit_config::{ConfigError, ConfigFile, Quantity, Sign};

/// Joint-space limits of a 7-DoF arm, SI units; velocity and above are symmetric magnitudes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointLimits {
    pub position_min: JointVector,
    pub position_max: JointVector,
    pub velocity: JointVector,
    pub acceleration: JointVector,
    pub jerk: JointVector,
    pub torque: JointVector,
    pub torque_rate: JointVector,
}

impl JointLimits {
    /// The limits file shipped in `controllers/`.
    pub fn panda() -> Result<Self, ConfigError> {
        Self::load(&crate::deps::controllers_dir().join("panda_limits.toml"))
    }

    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        Self::from_config(ConfigFile::open(path)?)
    }

    pub fn from_config(mut f: ConfigFile) -> Result<Self, ConfigError> {
        let v = |a: [f64; 7]| JointVector::from_column_slice(&a);
        let limits = Self {
            position_min: v(f.quantities("joint.position_min", Quantity::Angle, Sign::Any)?),
            position_max: v(f.quantities("joint.position_max", Quantity::Angle, Sign::Any)?),
            velocity: v(f.quantities("joint.velocity", Quantity::AngularVelocity, Sign::Positive)?),
            acceleration: v(f.quantities("joint.acceleration", Quantity::AngularAcceleration, Sign::Positive)?),
            jerk: v(f.quantities("joint.jerk", Quantity::AngularJerk, Sign::Positive)?),
            torque: v(f.quantities("joint.torque", Quantity::Torque, Sign::Positive)?),
            torque_rate: v(f.quantities("joint.torque_rate", Quantity::TorqueRate, Sign::Positive)?),
        };
        if let Some(i) = (0..7).find(|&i| limits.position_min[i] >= limits.position_max[i]) {
            return Err(f.error("joint.position_min", format!("joint {} has position_min >= position_max", i + 1)));
        }
        f.finish()?;
        Ok(limits)
    }

    /// Whether `q` lies within the position limits shrunk by `margin` (rad).
    pub fn contains(&self, q: &JointVector, margin: f64) -> bool {
        (0..7).all(|i| q[i] >= self.position_min[i] + margin && q[i] <= self.position_max[i] - margin)
    }

    /// `q` clamped into the position limits shrunk by `margin`.
    pub fn clamp(&self, q: &JointVector, margin: f64) -> JointVector {
        JointVector::from_fn(|i, _| q[i].clamp(self.position_min[i] + margin, self.position_max[i] - margin))
    }

    /// Middle of each joint's range.
    pub fn mid(&self) -> JointVector {
        (self.position_min + self.position_max) * 0.5
    }
}
