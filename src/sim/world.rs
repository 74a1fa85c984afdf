//! `World`: one loaded scene and its state. Resets, steps at the model's timestep (1 ms in
//! flowram's scenes), reads the arm state, applies joint torques and the gripper command, and
//! reads and sets object poses. Nothing outside `sim` calls MuJoCo directly. Two more
//! `impl World` blocks sit beside this one: the video recorder (`recorder`) and the arm's
//! export for the controller's Pinocchio model (`arm_export`).
use std::path::{Path, PathBuf};

use mujoco_rs::prelude::*;
use mujoco_rs::wrappers::mj_model::MjtObjBase;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};

use super::SimError;
use super::recorder::Recorder;
use super::scene::{self, ARM_JOINTS, ARM_MOTORS, BASE_BODY, FINGER_JOINTS, GRIPPER_ACTUATOR, TCP_SITE};
use crate::deps::Deps;
use crate::robot::JointVector;

/// A loose object of the scene: see [`World::objects`].
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SceneObject {
    pub name: String,
    /// World frame, m.
    pub position: [f64; 3],
    pub rgba: [f32; 4],
}

/// What a torque-controlled arm reports every tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmState {
    /// Simulation time (s).
    pub time: f64,
    /// Joint positions (rad).
    pub q: JointVector,
    /// Joint velocities (rad/s).
    pub dq: JointVector,
    /// Torques the motors applied on the last step, after the actuators' limits (Nm).
    pub tau: JointVector,
    /// Tool centre point in the robot base frame (`panda_link0`), metres.
    pub tcp_in_base: Isometry3<f64>,
    /// Distance between the fingers (m): 0 closed, 0.08 fully open.
    pub gripper_width: f64,
    /// Constraint torques on the arm's joints (Nm): what contacts and joint limits exert on
    /// them (MuJoCo's `qfrc_constraint`), the simulated counterpart of a Franka's
    /// external-torque estimate.
    pub tau_ext: JointVector,
}

/// MuJoCo indices of the arm, resolved once at load.
#[derive(Debug, Clone)]
pub(super) struct ArmIndex {
    qpos: [usize; 7],
    pub(super) dof: [usize; 7],
    motor: [usize; 7],
    finger_qpos: [usize; 2],
    finger_dof: [usize; 2],
    gripper: usize,
    pub(super) tcp_site: usize,
    pub(super) base_body: usize,
}

/// A loaded scene with the Panda in it.
pub struct World {
    scene_path: PathBuf,
    pub(super) data: MjData<Box<MjModel>>,
    pub(super) arm: ArmIndex,
    pub(super) recorder: Option<Recorder>,
}

impl std::fmt::Debug for World {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("World").field("scene", &self.scene_path).field("time", &self.time()).finish()
    }
}

impl World {
    /// Loads a scene file (see `models/scene.xml`) with the Panda from `deps`, and resets it to
    /// the `home` posture.
    pub fn load(scene_path: &Path, deps: &Deps) -> Result<Self, SimError> {
        Self::load_with(scene_path, &[], deps)
    }

    /// Loads a scene with extra MJCF files merged into its world (task objects, `models/tasks/`).
    pub fn load_with(scene_path: &Path, extra: &[PathBuf], deps: &Deps) -> Result<Self, SimError> {
        super::logging::install();
        let model = Box::new(scene::compose(scene_path, extra, deps)?);
        let arm = ArmIndex::resolve(&model, scene_path)?;
        let data = MjData::new(model);
        let mut world = Self { scene_path: scene_path.to_path_buf(), data, arm, recorder: None };
        world.reset_to("home")?;
        Ok(world)
    }

    /// Loads a scene by name (`default`, or a file in `models/`) or path, with the installed deps.
    pub fn load_named(scene: &str) -> Result<Self, SimError> {
        let path = scene::resolve_scene(scene)?;
        Self::load(&path, &Deps::locate())
    }

    pub fn scene_path(&self) -> &Path {
        &self.scene_path
    }

    pub fn model(&self) -> &MjModel {
        self.data.model()
    }

    pub(crate) fn data_mut(&mut self) -> &mut MjData<Box<MjModel>> {
        &mut self.data
    }

    pub(crate) fn data(&self) -> &MjData<Box<MjModel>> {
        &self.data
    }

    /// Names of the scene's cameras, in model order.
    pub fn camera_names(&self) -> Vec<String> {
        let model = self.model();
        names(model, MjtObjBase::mjOBJ_CAMERA, model.ffi().ncam as usize)
    }

    /// Physics timestep (s).
    pub fn timestep(&self) -> f64 {
        self.model().ffi().opt.timestep
    }

    pub fn time(&self) -> f64 {
        self.data.ffi().time
    }

    /// Resets everything to the model defaults, then the arm to a named posture: a MuJoCo
    /// `<key name=..>` if the scene has one, else a `<numeric name="q_NAME">` of 7 joint angles
    /// (the scene's `q_home`, `q_ready`). The gripper starts open.
    pub fn reset_to(&mut self, name: &str) -> Result<(), SimError> {
        let model = self.data.model();
        if let Some(key) = model.name_to_id(MjtObjBase::mjOBJ_KEY, name) {
            self.data
                .reset_keyframe(key)
                .map_err(|e| SimError::InvalidInput { what: "keyframe", detail: e.to_string() })?;
            self.data.forward();
            return Ok(());
        }
        let q = named_posture(model, name).ok_or_else(|| SimError::UnknownName {
            kind: "posture",
            name: name.into(),
            valid: posture_names(model).join(", "),
        })?;
        self.reset_to_configuration(&q)
    }

    /// Resets everything to the model defaults with the arm at `q` (rad) and the gripper open.
    pub fn reset_to_configuration(&mut self, q: &JointVector) -> Result<(), SimError> {
        check_finite("joint configuration", q.as_slice())?;
        self.data.reset();
        let qpos = self.data.qpos_mut();
        for (i, &adr) in self.arm.qpos.iter().enumerate() {
            qpos[adr] = q[i];
        }
        for &adr in &self.arm.finger_qpos {
            qpos[adr] = 0.04;
        }
        self.data.ctrl_mut()[self.arm.gripper] = 1.0;
        self.data.forward();
        Ok(())
    }

    /// Sets the arm's joint positions and velocities, leaving everything else as it is.
    pub fn set_arm_state(&mut self, q: &JointVector, dq: &JointVector) -> Result<(), SimError> {
        check_finite("joint configuration", q.as_slice())?;
        check_finite("joint velocities", dq.as_slice())?;
        for i in 0..7 {
            self.data.qpos_mut()[self.arm.qpos[i]] = q[i];
            self.data.qvel_mut()[self.arm.dof[i]] = dq[i];
        }
        self.data.forward();
        Ok(())
    }

    /// Advances the physics by one timestep with the current torques and gripper command.
    pub fn step(&mut self) {
        self.data.step();
        self.capture_frame();
    }

    /// Joint torques (Nm) for the next steps. The motors clamp them to the Panda's rated
    /// torques (87 Nm joints 1-4, 12 Nm joints 5-7); non-finite values are refused.
    pub fn apply_torques(&mut self, tau: &JointVector) -> Result<(), SimError> {
        check_finite("joint torques", tau.as_slice())?;
        let ctrl = self.data.ctrl_mut();
        for (i, &u) in self.arm.motor.iter().enumerate() {
            ctrl[u] = tau[i];
        }
        Ok(())
    }

    /// Gripper command: 1 = open (0.08 m between the fingers), 0 = closed; values in between
    /// ask for that fraction of the full opening. The hand's actuator limits the force to 100 N.
    pub fn set_gripper(&mut self, opening: f64) -> Result<(), SimError> {
        if !(0.0..=1.0).contains(&opening) {
            return Err(SimError::InvalidInput {
                what: "gripper command",
                detail: format!("{opening} is outside [0, 1] (1 = open, 0 = closed)"),
            });
        }
        self.data.ctrl_mut()[self.arm.gripper] = opening;
        Ok(())
    }

    /// The arm's state now.
    pub fn arm_state(&self) -> ArmState {
        let qpos = self.data.qpos();
        let qvel = self.data.qvel();
        let force = self.data.actuator_force();
        let q = JointVector::from_fn(|i, _| qpos[self.arm.qpos[i]]);
        let dq = JointVector::from_fn(|i, _| qvel[self.arm.dof[i]]);
        let tau = JointVector::from_fn(|i, _| force[self.arm.motor[i]]);
        let tau_ext = self.external_joint_torques();
        let gripper_width = self.arm.finger_qpos.iter().map(|&a| qpos[a]).sum();
        ArmState {
            time: self.time(),
            q,
            dq,
            tau,
            tcp_in_base: self.base_pose().inverse() * self.tcp_pose(),
            gripper_width,
            tau_ext,
        }
    }

    /// Constraint torques on the arm's joints without the joints' own dry friction (MuJoCo
    /// models it as a constraint too; a robot's external-torque estimate does not count it).
    fn external_joint_torques(&self) -> JointVector {
        let constraint = self.data.qfrc_constraint();
        let mut tau = JointVector::from_fn(|i, _| constraint[self.arm.dof[i]]);
        let types = self.data.efc_type();
        let ids = self.data.efc_id();
        // SAFETY: efc_force holds nefc entries written by the last step, like efc_type and efc_id.
        let forces = unsafe { self.data.efc_force() };
        for ((kind, &id), &force) in types.iter().zip(ids).zip(forces) {
            if *kind == mujoco_rs::mujoco_c::mjtConstraint::mjCNSTR_FRICTION_DOF
                && let Some(i) = self.arm.dof.iter().position(|&d| d as i32 == id)
            {
                tau[i] -= force;
            }
        }
        tau
    }

    /// Finger joint velocities (m/s), for grasp detection.
    pub fn finger_velocities(&self) -> [f64; 2] {
        let qvel = self.data.qvel();
        [qvel[self.arm.finger_dof[0]], qvel[self.arm.finger_dof[1]]]
    }

    /// Tool centre point in the world frame.
    pub fn tcp_pose(&self) -> Isometry3<f64> {
        let d = &self.data;
        pose_from(&d.site_xpos()[self.arm.tcp_site], &d.site_xmat()[self.arm.tcp_site])
    }

    /// The robot base frame (`panda_link0`) in the world frame.
    pub fn base_pose(&self) -> Isometry3<f64> {
        let d = &self.data;
        pose_from(&d.xpos()[self.arm.base_body], &d.xmat()[self.arm.base_body])
    }

    /// World pose of any body (objects, links).
    pub fn body_pose(&self, name: &str) -> Result<Isometry3<f64>, SimError> {
        let id = self.body_id(name)?;
        Ok(pose_from(&self.data.xpos()[id], &self.data.xmat()[id]))
    }

    /// The scene's loose objects (bodies with a free joint), in model order: name, world position
    /// (m) and the colour of the body's first geom (RGBA in [0, 1]), e.g. to read where an
    /// episode left the blocks.
    pub fn objects(&self) -> Vec<SceneObject> {
        let model = self.model();
        let geomadr = model.body_geomadr();
        (0..model.ffi().nbody as usize)
            .filter(|&b| free_joint(model, b).is_some())
            .map(|b| SceneObject {
                name: model.id_to_name(MjtObjBase::mjOBJ_BODY, b).unwrap_or_default().to_owned(),
                position: self.data.xpos()[b],
                rgba: if geomadr[b] >= 0 { model.geom_rgba()[geomadr[b] as usize] } else { [0.0; 4] },
            })
            .collect()
    }

    /// Places a free-floating body (one with a free joint) at `pose` in the world frame, at rest,
    /// and recomputes the kinematics.
    pub fn set_body_pose(&mut self, name: &str, pose: &Isometry3<f64>) -> Result<(), SimError> {
        check_finite("pose", pose.translation.vector.as_slice())?;
        check_finite("pose", pose.rotation.coords.as_slice())?;
        let id = self.body_id(name)?;
        let model = self.data.model();
        let jnt = free_joint(model, id).ok_or_else(|| SimError::NotFreeBody { name: name.into() })?;
        let qadr = model.jnt_qposadr()[jnt] as usize;
        let vadr = model.jnt_dofadr()[jnt] as usize;
        let t = pose.translation.vector;
        let r = pose.rotation.quaternion();
        self.data.qpos_mut()[qadr..qadr + 7].copy_from_slice(&[t.x, t.y, t.z, r.w, r.i, r.j, r.k]);
        self.data.qvel_mut()[vadr..vadr + 6].fill(0.0);
        self.data.forward();
        Ok(())
    }

    /// A geom's own colour (RGBA in [0, 1]); the cameras show it unless it is MuJoCo's default
    /// grey on a geom with a material, which shows the material's.
    pub fn geom_rgba(&self, name: &str) -> Result<[f32; 4], SimError> {
        let id = self.id_of(MjtObjBase::mjOBJ_GEOM, "geom", name, self.model().ffi().ngeom as usize)?;
        Ok(self.model().geom_rgba()[id])
    }

    /// Sets a geom's colour (RGBA in [0, 1]), e.g. for a task variation's object colours. It shows
    /// over the geom's material colour unless it is MuJoCo's default grey (0.5, 0.5, 0.5, 1).
    pub fn set_geom_rgba(&mut self, name: &str, rgba: [f32; 4]) -> Result<(), SimError> {
        let id = self.id_of(MjtObjBase::mjOBJ_GEOM, "geom", name, self.model().ffi().ngeom as usize)?;
        // SAFETY: only a colour changes; no size, index or address of the model does.
        unsafe { self.data.model_mut() }.geom_rgba_mut()[id] = rgba;
        Ok(())
    }

    /// What a camera could tell apart between two resets: every geom's colour, every body's
    /// placement in its parent and the joint positions, flattened. Equal fingerprints are the
    /// same scene (e.g. two variations of a task that differ only in the instruction).
    pub fn scene_fingerprint(&self) -> Vec<f64> {
        let model = self.model();
        let mut out: Vec<f64> = model.geom_rgba().iter().flatten().map(|&v| f64::from(v)).collect();
        out.extend(model.body_pos().iter().flatten());
        out.extend(model.body_quat().iter().flatten());
        out.extend(self.data.qpos().iter());
        out
    }

    /// Moves a fixed (joint-less) body relative to its parent, e.g. to place a task's fixture.
    pub fn set_fixed_body_pose(&mut self, name: &str, pose: &Isometry3<f64>) -> Result<(), SimError> {
        let id = self.body_id(name)?;
        let t = pose.translation.vector;
        let q = pose.rotation.quaternion();
        // SAFETY: only the body's placement changes; no size, index or address of the model does.
        let model = unsafe { self.data.model_mut() };
        model.body_pos_mut()[id] = [t.x, t.y, t.z];
        model.body_quat_mut()[id] = [q.w, q.i, q.j, q.k];
        self.data.forward();
        Ok(())
    }

    /// Position (m or rad) of a named joint with one coordinate (slide or hinge).
    pub fn joint_position(&self, name: &str) -> Result<f64, SimError> {
        let id = self.id_of(MjtObjBase::mjOBJ_JOINT, "joint", name, self.model().ffi().njnt as usize)?;
        Ok(self.data.qpos()[self.model().jnt_qposadr()[id] as usize])
    }

    /// Sets a named one-coordinate joint (slide or hinge) at rest and recomputes kinematics.
    pub fn set_joint_position(&mut self, name: &str, value: f64) -> Result<(), SimError> {
        check_finite("joint position", &[value])?;
        let id = self.id_of(MjtObjBase::mjOBJ_JOINT, "joint", name, self.model().ffi().njnt as usize)?;
        let (qadr, vadr) = (self.model().jnt_qposadr()[id] as usize, self.model().jnt_dofadr()[id] as usize);
        self.data.qpos_mut()[qadr] = value;
        self.data.qvel_mut()[vadr] = 0.0;
        self.data.forward();
        Ok(())
    }

    /// The contacts now, as pairs of geom names (unnamed geoms as `body:<name>`) with the
    /// penetration distance (m, negative = overlapping); for diagnosing blocked motions.
    pub fn contacts(&self) -> Vec<(String, String, f64)> {
        let model = self.model();
        let name = |g: i32| {
            let g = g.max(0) as usize;
            model.id_to_name(MjtObjBase::mjOBJ_GEOM, g).map(str::to_owned).unwrap_or_else(|| {
                let b = model.geom_bodyid()[g].max(0) as usize;
                format!("body:{}", model.id_to_name(MjtObjBase::mjOBJ_BODY, b).unwrap_or("?"))
            })
        };
        self.data.contact().iter().map(|c| (name(c.geom[0]), name(c.geom[1]), c.dist)).collect()
    }

    fn id_of(&self, kind: MjtObjBase, label: &'static str, name: &str, count: usize) -> Result<usize, SimError> {
        let model = self.data.model();
        model.name_to_id(kind, name).ok_or_else(|| SimError::UnknownName {
            kind: label,
            name: name.into(),
            valid: names(model, kind, count).join(", "),
        })
    }

    /// Length of [`World::copy_physics_state`]'s output: qpos, qvel, act.
    pub fn physics_state_len(&self) -> usize {
        let m = self.model().ffi();
        (m.nq + m.nv + m.na) as usize
    }

    /// Copies joint positions, velocities and actuator activations into `out` (at least
    /// [`World::physics_state_len`] long, else nothing is copied); allocates nothing.
    pub fn copy_physics_state(&self, out: &mut [f64]) {
        let (q, v, a) = (self.data.qpos(), self.data.qvel(), self.data.act());
        let (nq, nv, na) = (q.len(), v.len(), a.len());
        if out.len() >= nq + nv + na {
            out[..nq].copy_from_slice(q);
            out[nq..nq + nv].copy_from_slice(v);
            out[nq + nv..nq + nv + na].copy_from_slice(a);
        }
    }

    /// Sets the state copied by [`World::copy_physics_state`] from a world of the same model,
    /// and recomputes positions (to render it or check a task on it; time is not part of it).
    pub fn set_physics_state(&mut self, state: &[f64]) -> Result<(), SimError> {
        let n = self.physics_state_len();
        if state.len() < n {
            return Err(SimError::InvalidInput {
                what: "physics state",
                detail: format!("{} values for a model that needs {n} (qpos, qvel, act)", state.len()),
            });
        }
        let (nq, nv) = (self.data.qpos().len(), self.data.qvel().len());
        self.data.qpos_mut().copy_from_slice(&state[..nq]);
        self.data.qvel_mut().copy_from_slice(&state[nq..nq + nv]);
        let na = self.data.act().len();
        self.data.act_mut().copy_from_slice(&state[nq + nv..nq + nv + na]);
        self.data.forward();
        Ok(())
    }

    /// Recomputes positions, velocities and forces from the current state (after editing it).
    pub fn forward(&mut self) {
        self.data.forward();
    }

    fn body_id(&self, name: &str) -> Result<usize, SimError> {
        let model = self.data.model();
        model.name_to_id(MjtObjBase::mjOBJ_BODY, name).ok_or_else(|| SimError::UnknownName {
            kind: "body",
            name: name.into(),
            valid: names(model, MjtObjBase::mjOBJ_BODY, model.ffi().nbody as usize).join(", "),
        })
    }
}

impl ArmIndex {
    fn resolve(model: &MjModel, scene: &Path) -> Result<Self, SimError> {
        let find = |kind: MjtObjBase, label: &'static str, name: &str| {
            model.name_to_id(kind, name).ok_or_else(|| SimError::MissingElement {
                path: scene.to_path_buf(),
                kind: label,
                name: name.into(),
            })
        };
        let joint = |name: &str| find(MjtObjBase::mjOBJ_JOINT, "joint", name);
        let mut qpos = [0; 7];
        let mut dof = [0; 7];
        let mut motor = [0; 7];
        for i in 0..7 {
            let j = joint(ARM_JOINTS[i])?;
            qpos[i] = model.jnt_qposadr()[j] as usize;
            dof[i] = model.jnt_dofadr()[j] as usize;
            motor[i] = find(MjtObjBase::mjOBJ_ACTUATOR, "actuator", ARM_MOTORS[i])?;
        }
        let mut finger_qpos = [0; 2];
        let mut finger_dof = [0; 2];
        for i in 0..2 {
            let j = joint(FINGER_JOINTS[i])?;
            finger_qpos[i] = model.jnt_qposadr()[j] as usize;
            finger_dof[i] = model.jnt_dofadr()[j] as usize;
        }
        Ok(Self {
            qpos,
            dof,
            motor,
            finger_qpos,
            finger_dof,
            gripper: find(MjtObjBase::mjOBJ_ACTUATOR, "actuator", GRIPPER_ACTUATOR)?,
            tcp_site: find(MjtObjBase::mjOBJ_SITE, "site", TCP_SITE)?,
            base_body: find(MjtObjBase::mjOBJ_BODY, "body", BASE_BODY)?,
        })
    }
}

/// A pose from MuJoCo's position and row-major rotation matrix.
pub(crate) fn pose_from(pos: &[f64; 3], mat: &[f64; 9]) -> Isometry3<f64> {
    let rot = Rotation3::from_matrix_unchecked(Matrix3::from_row_slice(mat));
    Isometry3::from_parts(Translation3::new(pos[0], pos[1], pos[2]), UnitQuaternion::from_rotation_matrix(&rot))
}

fn check_finite(what: &'static str, values: &[f64]) -> Result<(), SimError> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => Err(SimError::InvalidInput { what, detail: format!("element {i} is {}", values[i]) }),
    }
}

/// The 7 joint angles of `<numeric name="q_NAME">`, if the scene defines it.
fn named_posture(model: &MjModel, name: &str) -> Option<JointVector> {
    let id = model.name_to_id(MjtObjBase::mjOBJ_NUMERIC, &format!("q_{name}"))?;
    let adr = model.numeric_adr()[id] as usize;
    let size = model.numeric_size()[id] as usize;
    (size == 7).then(|| JointVector::from_column_slice(&model.numeric_data()[adr..adr + 7]))
}

fn posture_names(model: &MjModel) -> Vec<String> {
    let mut out = names(model, MjtObjBase::mjOBJ_KEY, model.ffi().nkey as usize);
    out.extend(
        names(model, MjtObjBase::mjOBJ_NUMERIC, model.ffi().nnumeric as usize)
            .into_iter()
            .filter_map(|n| n.strip_prefix("q_").map(str::to_owned)),
    );
    out
}

/// The free joint of `body` (its first joint, if that is free): a loose object's.
fn free_joint(model: &MjModel, body: usize) -> Option<usize> {
    let jnt = usize::try_from(model.body_jntadr()[body]).ok()?;
    (model.jnt_type()[jnt] == MjtJoint::mjJNT_FREE).then_some(jnt)
}

pub(crate) fn names(model: &MjModel, kind: MjtObjBase, count: usize) -> Vec<String> {
    (0..count).filter_map(|i| model.id_to_name(kind, i).map(str::to_owned)).collect()
}
