//! Safe Rust over the C++ shim (`shim/`) around Pinocchio 4.1: a 7-DoF serial arm built from an
//! [`ArmDescription`], with allocation-free kinematics and dynamics per call (about 2.5 us for
//! everything, 0.4 us for FK + Jacobian on these machines).
use std::ffi::{c_char, c_int};
use std::marker::{PhantomData, PhantomPinned};
use std::ptr::NonNull;

use nalgebra::{Isometry3, Matrix3, Rotation3, SMatrix, Translation3, UnitQuaternion, Vector3, Vector6};

use super::{ArmDescription, JointVector};

/// 6x7 TCP Jacobian: rows 0..3 linear velocity of the TCP point, rows 3..6 angular velocity,
/// both in base-frame axes (Pinocchio's LOCAL_WORLD_ALIGNED).
pub type Jacobian = SMatrix<f64, 6, 7>;
/// 7x7 joint-space matrix.
pub type JointMatrix = SMatrix<f64, 7, 7>;

#[repr(C)]
struct FrPinArm {
    _data: [u8; 0],
    _marker: PhantomData<(*mut u8, PhantomPinned)>,
}

unsafe extern "C" {
    fn fr_pin_arm_new(
        parent_pos: *const f64,
        parent_quat_wxyz: *const f64,
        axis: *const f64,
        mass: *const f64,
        com: *const f64,
        inertia: *const f64,
        armature: *const f64,
        tcp_pos: *const f64,
        tcp_quat_wxyz: *const f64,
        gravity: *const f64,
        err: *mut c_char,
        err_len: c_int,
    ) -> *mut FrPinArm;
    fn fr_pin_arm_free(arm: *mut FrPinArm);
    fn fr_pin_arm_compute(
        arm: *mut FrPinArm,
        q: *const f64,
        dq: *const f64,
        tcp_pos: *mut f64,
        tcp_rot: *mut f64,
        jac: *mut f64,
        jdot_qdot: *mut f64,
        mass: *mut f64,
        coriolis: *mut f64,
        gravity: *mut f64,
    ) -> c_int;
    fn fr_pin_arm_task(
        arm: *mut FrPinArm,
        q: *const f64,
        dq: *const f64,
        tcp_pos: *mut f64,
        tcp_rot: *mut f64,
        jac: *mut f64,
        jdot_qdot: *mut f64,
    ) -> c_int;
    fn fr_pin_arm_fk_jac(
        arm: *mut FrPinArm,
        q: *const f64,
        tcp_pos: *mut f64,
        tcp_rot: *mut f64,
        jac: *mut f64,
    ) -> c_int;
}

/// Kinematics and dynamics of the arm at one state; everything in the base frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dynamics {
    pub tcp: Isometry3<f64>,
    pub jacobian: Jacobian,
    /// Classical TCP acceleration at zero joint acceleration (J̇ q̇), rows as the Jacobian's.
    pub jdot_qdot: Vector6<f64>,
    /// Joint-space inertia M(q), symmetric, armature included.
    pub mass: JointMatrix,
    /// Coriolis and centrifugal torques C(q, q̇) q̇.
    pub coriolis: JointVector,
    /// Gravity torques g(q): tau = M q̈ + coriolis + gravity.
    pub gravity: JointVector,
}

/// The TCP's pose, Jacobian and J̇q̇ at one state (base frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TaskKinematics {
    pub tcp: Isometry3<f64>,
    pub jacobian: Jacobian,
    pub jdot_qdot: Vector6<f64>,
}

/// A per-call failure (no allocation on this path).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum KinematicsError {
    #[error("joint positions or velocities are not finite")]
    NonFiniteInput,
    #[error("the Pinocchio shim failed (code {0})")]
    Internal(i32),
}

/// The model could not be built from the description.
#[derive(Debug, Clone, thiserror::Error)]
#[error("cannot build the Pinocchio model: {0}")]
pub struct ModelError(pub String);

fn check(rc: c_int) -> Result<(), KinematicsError> {
    match rc {
        0 => Ok(()),
        2 => Err(KinematicsError::NonFiniteInput),
        c => Err(KinematicsError::Internal(c)),
    }
}

fn isometry(p: &Vector3<f64>, r: &Matrix3<f64>) -> Isometry3<f64> {
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*r));
    Isometry3::from_parts(Translation3::from(*p), rot)
}

/// A Pinocchio model and its workspace for one arm. `Send`, not `Sync` (each call writes the
/// internal workspace).
pub struct Kinematics {
    raw: NonNull<FrPinArm>,
    description: ArmDescription,
}

// SAFETY: the C++ object is only touched through &mut self or Drop; it has no thread affinity.
unsafe impl Send for Kinematics {}

impl std::fmt::Debug for Kinematics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Kinematics").field("tcp", &self.description.tcp).finish()
    }
}

impl Kinematics {
    pub fn new(d: &ArmDescription) -> Result<Self, ModelError> {
        let mut pos = [0.0; 21];
        let mut quat = [0.0; 28];
        let mut axis = [0.0; 21];
        let mut mass = [0.0; 7];
        let mut com = [0.0; 21];
        let mut inertia = [0.0; 63];
        let mut armature = [0.0; 7];
        for (i, l) in d.links.iter().enumerate() {
            pos[3 * i..3 * i + 3].copy_from_slice(l.placement.translation.vector.as_slice());
            let q = l.placement.rotation.quaternion();
            quat[4 * i..4 * i + 4].copy_from_slice(&[q.w, q.i, q.j, q.k]);
            axis[3 * i..3 * i + 3].copy_from_slice(l.axis.as_slice());
            mass[i] = l.inertia.mass;
            com[3 * i..3 * i + 3].copy_from_slice(l.inertia.com.as_slice());
            inertia[9 * i..9 * i + 9].copy_from_slice(l.inertia.inertia.as_slice());
            armature[i] = l.armature;
        }
        let tq = d.tcp.rotation.quaternion();
        let tcp_quat = [tq.w, tq.i, tq.j, tq.k];
        let mut err = [0 as c_char; 256];
        // SAFETY: every pointer refers to an array of the length the C API documents.
        let raw = unsafe {
            fr_pin_arm_new(
                pos.as_ptr(),
                quat.as_ptr(),
                axis.as_ptr(),
                mass.as_ptr(),
                com.as_ptr(),
                inertia.as_ptr(),
                armature.as_ptr(),
                d.tcp.translation.vector.as_ptr(),
                tcp_quat.as_ptr(),
                d.gravity.as_ptr(),
                err.as_mut_ptr(),
                err.len() as c_int,
            )
        };
        match NonNull::new(raw) {
            Some(raw) => Ok(Self { raw, description: d.clone() }),
            None => {
                // SAFETY: the shim NUL-terminates its message within err_len (snprintf).
                let msg = unsafe { std::ffi::CStr::from_ptr(err.as_ptr()) };
                Err(ModelError(msg.to_string_lossy().into_owned()))
            }
        }
    }

    pub fn description(&self) -> &ArmDescription {
        &self.description
    }

    /// FK, Jacobian, J̇q̇, M, Coriolis and gravity in one pass (`computeAllTerms`).
    pub fn dynamics(&mut self, q: &JointVector, dq: &JointVector) -> Result<Dynamics, KinematicsError> {
        let mut p = Vector3::zeros();
        let mut r = Matrix3::zeros();
        let mut jacobian = Jacobian::zeros();
        let mut jdot_qdot = Vector6::zeros();
        let mut mass = JointMatrix::zeros();
        let mut coriolis = JointVector::zeros();
        let mut gravity = JointVector::zeros();
        // SAFETY: nalgebra fixed-size matrices are contiguous column-major, as the C API expects.
        check(unsafe {
            fr_pin_arm_compute(
                self.raw.as_ptr(),
                q.as_ptr(),
                dq.as_ptr(),
                p.as_mut_ptr(),
                r.as_mut_ptr(),
                jacobian.as_mut_ptr(),
                jdot_qdot.as_mut_ptr(),
                mass.as_mut_ptr(),
                coriolis.as_mut_ptr(),
                gravity.as_mut_ptr(),
            )
        })?;
        Ok(Dynamics { tcp: isometry(&p, &r), jacobian, jdot_qdot, mass, coriolis, gravity })
    }

    /// TCP pose, Jacobian and J̇q̇ only (about a third of [`Kinematics::dynamics`]'s cost).
    pub fn task(&mut self, q: &JointVector, dq: &JointVector) -> Result<TaskKinematics, KinematicsError> {
        let mut p = Vector3::zeros();
        let mut r = Matrix3::zeros();
        let mut jacobian = Jacobian::zeros();
        let mut jdot_qdot = Vector6::zeros();
        // SAFETY: as in `dynamics`.
        check(unsafe {
            fr_pin_arm_task(
                self.raw.as_ptr(),
                q.as_ptr(),
                dq.as_ptr(),
                p.as_mut_ptr(),
                r.as_mut_ptr(),
                jacobian.as_mut_ptr(),
                jdot_qdot.as_mut_ptr(),
            )
        })?;
        Ok(TaskKinematics { tcp: isometry(&p, &r), jacobian, jdot_qdot })
    }

    /// TCP pose and Jacobian only (for IK).
    pub fn tcp_and_jacobian(&mut self, q: &JointVector) -> Result<(Isometry3<f64>, Jacobian), KinematicsError> {
        let mut p = Vector3::zeros();
        let mut r = Matrix3::zeros();
        let mut jacobian = Jacobian::zeros();
        // SAFETY: as in `dynamics`.
        check(unsafe {
            fr_pin_arm_fk_jac(self.raw.as_ptr(), q.as_ptr(), p.as_mut_ptr(), r.as_mut_ptr(), jacobian.as_mut_ptr())
        })?;
        Ok((isometry(&p, &r), jacobian))
    }

    /// TCP pose in the base frame.
    pub fn tcp(&mut self, q: &JointVector) -> Result<Isometry3<f64>, KinematicsError> {
        self.tcp_and_jacobian(q).map(|(t, _)| t)
    }
}

impl Drop for Kinematics {
    fn drop(&mut self) {
        // SAFETY: raw came from fr_pin_arm_new and is freed exactly once.
        unsafe { fr_pin_arm_free(self.raw.as_ptr()) }
    }
}
