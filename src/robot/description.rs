//! A simulator-neutral description of a 7-DoF serial arm: link placements, joint axes,
//! inertias, the TCP and gravity. The simulator exports it from the model it steps, so that
//! Pinocchio and MuJoCo describe exactly the same robot.
use nalgebra::{Isometry3, Matrix3, Vector3};

/// Mass properties of a rigid body in its own frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodyInertia {
    /// kg
    pub mass: f64,
    /// Centre of mass (m).
    pub com: Vector3<f64>,
    /// Rotational inertia about the centre of mass (kg m^2).
    pub inertia: Matrix3<f64>,
}

impl BodyInertia {
    pub const ZERO: BodyInertia = BodyInertia {
        mass: 0.0,
        com: Vector3::new(0.0, 0.0, 0.0),
        inertia: Matrix3::new(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    };

    /// The same body expressed in a parent frame where the body's frame sits at `pose`.
    pub fn transformed(&self, pose: &Isometry3<f64>) -> Self {
        let r = pose.rotation.to_rotation_matrix();
        Self {
            mass: self.mass,
            com: (pose * nalgebra::Point3::from(self.com)).coords,
            inertia: r * self.inertia * r.transpose(),
        }
    }

    /// Two bodies rigidly joined (same frame), by the parallel-axis theorem.
    pub fn combined(&self, other: &Self) -> Self {
        let mass = self.mass + other.mass;
        if mass <= 0.0 {
            return Self::ZERO;
        }
        let com = (self.com * self.mass + other.com * other.mass) / mass;
        let shift = |b: &Self| {
            let d = b.com - com;
            (Matrix3::identity() * d.norm_squared() - d * d.transpose()) * b.mass
        };
        Self { mass, com, inertia: self.inertia + shift(self) + other.inertia + shift(other) }
    }
}

/// One link of the chain: its frame in the previous link's frame (the base frame for link 1),
/// the revolute joint at its origin, and its mass properties.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkDescription {
    pub placement: Isometry3<f64>,
    /// Joint axis in the link frame (unit).
    pub axis: Vector3<f64>,
    pub inertia: BodyInertia,
    /// Rotor inertia added to the mass-matrix diagonal (kg m^2).
    pub armature: f64,
    /// Dry (Coulomb) friction of the joint (Nm) and viscous damping (Nm s/rad).
    pub friction: f64,
    pub damping: f64,
}

/// The arm from its base frame to the TCP.
#[derive(Debug, Clone, PartialEq)]
pub struct ArmDescription {
    pub links: [LinkDescription; 7],
    /// TCP frame in the last link's frame.
    pub tcp: Isometry3<f64>,
    /// Gravity in the base frame (m/s^2).
    pub gravity: Vector3<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn two_point_masses_combine_by_the_parallel_axis_theorem() {
        let point = |x: f64| BodyInertia { mass: 1.0, com: Vector3::new(x, 0.0, 0.0), inertia: Matrix3::zeros() };
        let c = point(1.0).combined(&point(-1.0));
        assert_eq!(c.mass, 2.0);
        assert!(c.com.norm() < 1e-15);
        // About the centre: I_yy = I_zz = sum m x^2 = 2, I_xx = 0.
        assert!((c.inertia - Matrix3::from_diagonal(&Vector3::new(0.0, 2.0, 2.0))).norm() < 1e-12);
    }

    #[test]
    fn transforming_moves_the_centre_of_mass_and_rotates_the_inertia() {
        let body = BodyInertia {
            mass: 2.0,
            com: Vector3::new(1.0, 0.0, 0.0),
            inertia: Matrix3::from_diagonal(&Vector3::new(1.0, 2.0, 3.0)),
        };
        let pose = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 5.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2),
        );
        let t = body.transformed(&pose);
        assert!((t.com - Vector3::new(0.0, 1.0, 5.0)).norm() < 1e-12);
        assert!((t.inertia - Matrix3::from_diagonal(&Vector3::new(2.0, 1.0, 3.0))).norm() < 1e-12);
    }
}
