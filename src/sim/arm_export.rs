//! The arm exported for the controller's Pinocchio model: [`World::arm_description`] reads the
//! Panda as MuJoCo models it (link placements, joint axes, inertias, armature, friction, TCP,
//! gravity), and [`World::arm_dynamics_reference`] gives MuJoCo's own mass matrix, TCP Jacobian
//! and bias forces, to check the Pinocchio model against the simulator's.
use mujoco_rs::wrappers::mj_model::{MjtJoint, MjtObjBase};
use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};

use super::scene::ARM_JOINTS;
use super::world::pose_from;
use super::{SimError, World};
use crate::robot::{ArmDescription, BodyInertia, JointVector, LinkDescription};

/// MuJoCo's view of the arm's kinematics and dynamics (see [`World::arm_dynamics_reference`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmDynamicsReference {
    pub tcp_in_base: Isometry3<f64>,
    /// 6x7, linear rows then angular, base-frame axes.
    pub jacobian: crate::robot::Jacobian,
    /// The arm's 7x7 block of MuJoCo's joint-space inertia.
    pub mass: crate::robot::JointMatrix,
    /// Coriolis, centrifugal and gravity torques (`qfrc_bias`).
    pub bias: JointVector,
    /// The gravity compensation MuJoCo applies (`qfrc_gravcomp`; bodies have gravcomp = 1).
    pub gravity_compensation: JointVector,
}

impl World {
    /// The arm as the simulator models it (link placements, joint axes, inertias, armature, TCP,
    /// gravity), in the base frame, for building the controller's kinematic model. The hand and
    /// fingers are lumped into link 7 at their current opening.
    pub fn arm_description(&self) -> Result<ArmDescription, SimError> {
        let m = self.data.model();
        let mismatch = |detail: String| SimError::InvalidInput { what: "arm model", detail };
        let inertia_of = |b: usize| {
            let rot = quat_wxyz(&m.body_iquat()[b]).to_rotation_matrix();
            let d = m.body_inertia()[b];
            BodyInertia {
                mass: m.body_mass()[b],
                com: Vector3::from(m.body_ipos()[b]),
                inertia: rot * Matrix3::from_diagonal(&Vector3::from(d)) * rot.transpose(),
            }
        };
        let mut bodies = [0usize; 7];
        let mut links = [LinkDescription {
            placement: Isometry3::identity(),
            axis: Vector3::z(),
            inertia: BodyInertia::ZERO,
            armature: 0.0,
            friction: 0.0,
            damping: 0.0,
        }; 7];
        let mut parent = self.arm.base_body;
        for (i, name) in ARM_JOINTS.iter().enumerate() {
            let j = m.name_to_id(MjtObjBase::mjOBJ_JOINT, name).ok_or_else(|| mismatch(format!("no joint {name}")))?;
            let b = m.jnt_bodyid()[j] as usize;
            if m.body_parentid()[b] as usize != parent {
                return Err(mismatch(format!("{name} is not on a child of the previous link")));
            }
            if m.jnt_type()[j] != MjtJoint::mjJNT_HINGE || Vector3::from(m.jnt_pos()[j]).norm() > 1e-12 {
                return Err(mismatch(format!("{name} must be a hinge at its body's origin")));
            }
            let p = m.body_pos()[b];
            links[i] = LinkDescription {
                placement: Isometry3::from_parts(Translation3::new(p[0], p[1], p[2]), quat_wxyz(&m.body_quat()[b])),
                axis: Vector3::from(m.jnt_axis()[j]).normalize(),
                inertia: inertia_of(b),
                armature: m.dof_armature()[m.jnt_dofadr()[j] as usize],
                friction: m.dof_frictionloss()[m.jnt_dofadr()[j] as usize],
                damping: m.dof_damping()[m.jnt_dofadr()[j] as usize],
            };
            bodies[i] = b;
            parent = b;
        }
        // Everything below link 7 (flange, hand, fingers) rides on link 7.
        let last = bodies[6];
        let world_to_last = self.body_frame(last).inverse();
        for b in 0..m.ffi().nbody as usize {
            let mut a = m.body_parentid()[b] as usize;
            while a != 0 && a != last {
                a = m.body_parentid()[a] as usize;
            }
            if a == last && b != last {
                let in_last = world_to_last * self.body_frame(b);
                links[6].inertia = links[6].inertia.combined(&inertia_of(b).transformed(&in_last));
            }
        }
        let base = self.base_pose();
        let g = Vector3::from(m.ffi().opt.gravity);
        Ok(ArmDescription { links, tcp: world_to_last * self.tcp_pose(), gravity: base.rotation.inverse() * g })
    }

    fn body_frame(&self, b: usize) -> Isometry3<f64> {
        pose_from(&self.data.xpos()[b], &self.data.xmat()[b])
    }

    /// MuJoCo's own mass matrix, Jacobian of the TCP and bias forces of the arm at the current
    /// state (base frame), for checking the controller's model against the simulator's.
    pub fn arm_dynamics_reference(&mut self) -> ArmDynamicsReference {
        self.data.forward();
        let nv = self.model().ffi().nv as usize;
        let mut full = vec![0.0; nv * nv];
        self.data.full_m(&mut full).expect("buffer sized nv*nv");
        let (jacp, jacr) = self.data.jac_site(true, true, self.arm.tcp_site);
        let r_base = self.base_pose().rotation.inverse().to_rotation_matrix();
        let mut jacobian = crate::robot::Jacobian::zeros();
        let mut mass = crate::robot::JointMatrix::zeros();
        for (c, &dc) in self.arm.dof.iter().enumerate() {
            let lin = r_base * Vector3::new(jacp[dc], jacp[nv + dc], jacp[2 * nv + dc]);
            let ang = r_base * Vector3::new(jacr[dc], jacr[nv + dc], jacr[2 * nv + dc]);
            jacobian.fixed_view_mut::<3, 1>(0, c).copy_from(&lin);
            jacobian.fixed_view_mut::<3, 1>(3, c).copy_from(&ang);
            for (r, &dr) in self.arm.dof.iter().enumerate() {
                mass[(r, c)] = full[dr * nv + dc];
            }
        }
        let bias = self.data.qfrc_bias();
        let gravcomp = self.data.qfrc_gravcomp();
        ArmDynamicsReference {
            tcp_in_base: self.base_pose().inverse() * self.tcp_pose(),
            jacobian,
            mass,
            bias: JointVector::from_fn(|i, _| bias[self.arm.dof[i]]),
            gravity_compensation: JointVector::from_fn(|i, _| gravcomp[self.arm.dof[i]]),
        }
    }
}

/// A unit quaternion from MuJoCo's w, x, y, z order.
fn quat_wxyz(q: &[f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]))
}
