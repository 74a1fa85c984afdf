//! Collision thresholds of a real Franka (libfranka's `set_collision_behavior`), from a TOML
//! profile (`controllers/franka_collision.toml`, format documented there): between `lower` and
//! `upper` the robot flags a contact, above `upper` it stops with a reflex.
use std::path::Path;

use crate::unit_config::{ConfigError, ConfigFile, Quantity, Sign};

/// Thresholds for one motion phase (accelerating or at constant velocity).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Thresholds {
    /// External torque per joint (Nm).
    pub torque: [f64; 7],
    /// External force (N) then moment (Nm) at the end effector: x y z, then about x y z.
    pub wrench: [f64; 6],
}

/// A collision-behaviour profile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CollisionProfile {
    pub lower_acceleration: Thresholds,
    pub upper_acceleration: Thresholds,
    pub lower_nominal: Thresholds,
    pub upper_nominal: Thresholds,
}

impl CollisionProfile {
    /// The profile shipped in `controllers/`.
    pub fn default_profile() -> Result<Self, ConfigError> {
        Self::load(&crate::deps::controllers_dir().join("franka_collision.toml"))
    }

    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        Self::from_config(ConfigFile::open(path)?)
    }

    pub fn from_config(mut f: ConfigFile) -> Result<Self, ConfigError> {
        let mut phase = |name: &str| -> Result<Thresholds, ConfigError> {
            let torque: [f64; 7] = f.quantities(&format!("torque.{name}"), Quantity::Torque, Sign::Positive)?;
            let force: [f64; 3] = f.quantities(&format!("force.{name}"), Quantity::Force, Sign::Positive)?;
            let moment: [f64; 3] = f.quantities(&format!("moment.{name}"), Quantity::Torque, Sign::Positive)?;
            let mut wrench = [0.0; 6];
            wrench[..3].copy_from_slice(&force);
            wrench[3..].copy_from_slice(&moment);
            Ok(Thresholds { torque, wrench })
        };
        let profile = Self {
            lower_acceleration: phase("lower_acceleration")?,
            upper_acceleration: phase("upper_acceleration")?,
            lower_nominal: phase("lower_nominal")?,
            upper_nominal: phase("upper_nominal")?,
        };
        for (lower, upper, phase) in [
            (&profile.lower_acceleration, &profile.upper_acceleration, "acceleration"),
            (&profile.lower_nominal, &profile.upper_nominal, "nominal"),
        ] {
            let torque = (0..7).find(|&i| lower.torque[i] > upper.torque[i]);
            if let Some(i) = torque {
                return Err(f.error(
                    &format!("torque.lower_{phase}"),
                    format!("joint {}: the lower threshold is above the upper one", i + 1),
                ));
            }
            if let Some(i) = (0..6).find(|&i| lower.wrench[i] > upper.wrench[i]) {
                let (table, axis) = if i < 3 { ("force", i) } else { ("moment", i - 3) };
                return Err(f.error(
                    &format!("{table}.lower_{phase}"),
                    format!("axis {}: the lower threshold is above the upper one", ["x", "y", "z"][axis]),
                ));
            }
        }
        f.finish()?;
        Ok(profile)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_profile_loads() {
        let p = CollisionProfile::default_profile().unwrap();
        assert_eq!(p.upper_nominal.torque[0], 20.0);
        assert_eq!(p.lower_acceleration.wrench, [20.0, 20.0, 20.0, 25.0, 25.0, 25.0]);
    }

    #[test]
    fn lower_above_upper_is_refused_naming_the_field() {
        let text =
            std::fs::read_to_string(crate::deps::controllers_dir().join("franka_collision.toml")).unwrap().replacen(
                "lower_nominal = { values = [20.0, 20.0, 18.0",
                "lower_nominal = { values = [30.0, 20.0, 18.0",
                1,
            );
        let e = CollisionProfile::from_config(ConfigFile::parse(Path::new("c.toml"), &text).unwrap()).unwrap_err();
        assert_eq!(e.field, "torque.lower_nominal");
        assert!(e.to_string().contains("joint 1"), "{e}");
    }

    #[test]
    fn a_missing_unit_is_refused() {
        let text = "[torque]\nlower_acceleration = [1, 2, 3, 4, 5, 6, 7]\n";
        let e = CollisionProfile::from_config(ConfigFile::parse(Path::new("c.toml"), text).unwrap()).unwrap_err();
        assert!(e.field.starts_with("torque."), "{e}");
    }
}
