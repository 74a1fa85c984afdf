//! Composes the simulated world: the project's scene MJCF (`models/*.xml`: table, lights,
//! cameras, arm torque motors) plus the Franka Panda arm and hand from the model installed by
//! `scripts/setup.sh`, attached with MuJoCo's model-editing API (never copied into the repo).
use std::path::{Path, PathBuf};

use mujoco_rs::prelude::*;
use mujoco_rs::wrappers::mj_editing::{Attach, MjSpec};

use super::SimError;
use crate::deps::Deps;

/// The 7 arm joints, base to flange.
pub const ARM_JOINTS: [&str; 7] =
    ["panda_joint1", "panda_joint2", "panda_joint3", "panda_joint4", "panda_joint5", "panda_joint6", "panda_joint7"];
/// The torque motors of the arm joints (defined by the scene file).
pub const ARM_MOTORS: [&str; 7] = [
    "panda_torque1",
    "panda_torque2",
    "panda_torque3",
    "panda_torque4",
    "panda_torque5",
    "panda_torque6",
    "panda_torque7",
];
/// The two finger slide joints of the Franka hand (m, 0 = closed, 0.04 = open).
pub const FINGER_JOINTS: [&str; 2] = ["panda_finger_joint1", "panda_finger_joint2"];
/// The hand's tendon-driven position actuator: ctrl 0 closes, 1 opens.
pub const GRIPPER_ACTUATOR: &str = "panda_hand_actuator";
/// Tool centre point: between the fingertips, 0.1034 m from the flange along the hand's z.
pub const TCP_SITE: &str = "TCP";
/// Body whose frame is the robot base frame.
pub const BASE_BODY: &str = "panda_link0";
/// The finger pads' collision boxes.
pub const FINGER_PADS: [&str; 2] = ["panda_leftfinger_collision", "panda_rightfinger_collision"];
/// The cameras every scene has, in RLBench's names and order.
pub const CAMERAS: [&str; 4] = ["front", "left_shoulder", "right_shoulder", "wrist"];

/// Where the robot stands in the scene file.
const MOUNT_SITE: &str = "panda_mount";
/// Flange body of the arm model, and the hand's rotation on it (-45 deg about z, as on the real
/// robot and in franka_description's URDF).
const FLANGE_BODY: &str = "panda_link8";
const HAND_ON_FLANGE_QUAT: [f64; 4] = [0.923_879_532_511_286_7, 0.0, 0.0, -0.382_683_432_365_089_8];
/// Wrist camera in the hand frame: 5.5 cm off the hand's side, 3 cm up, looking along the
/// approach axis (+z) tilted 10 deg toward the fingers, image up = the hand's +x.
const WRIST_CAMERA_POS: [f64; 3] = [0.055, 0.0, 0.03];
const WRIST_CAMERA_TILT_RAD: f64 = 10.0 * std::f64::consts::PI / 180.0;
const WRIST_CAMERA_FOVY_DEG: f64 = 70.0;

/// Finger pad contact: high sliding friction, torsional friction (condim 4) and priority over
/// the objects' own friction, so grasps hold (see the MuJoCo Menagerie Panda grasp reports).
const FINGER_FRICTION: [f64; 3] = [1.5, 0.02, 0.0002];
const FINGER_CONDIM: i32 = 4;
/// Grip stiffening of the hand's actuator (see `prepare_hand`).
const GRIP_SCALE: f64 = 5.0;

/// Resolves `--scene`: a name in `models/` (`default` is `models/scene.xml`) or a path.
pub fn resolve_scene(name_or_path: &str) -> Result<PathBuf, SimError> {
    let as_path = Path::new(name_or_path);
    let path = if name_or_path == "default" {
        crate::deps::models_dir().join("scene.xml")
    } else if as_path.extension().is_some() || as_path.components().count() > 1 {
        as_path.to_path_buf()
    } else {
        crate::deps::models_dir().join(format!("{name_or_path}.xml"))
    };
    if path.is_file() { Ok(path) } else { Err(SimError::SceneNotFound { path }) }
}

/// Loads a scene file, attaches the Panda and merges `extra` MJCF files (task objects) into
/// its world; returns the compiled model.
pub fn compose(scene: &Path, extra: &[PathBuf], deps: &Deps) -> Result<MjModel, SimError> {
    // Dependency checks first: a missing setup must say so, not fail later inside MuJoCo.
    let arm_path = deps.panda_arm_mjcf()?;
    let hand_path = deps.panda_hand_mjcf()?;
    if !scene.is_file() {
        return Err(SimError::SceneNotFound { path: scene.to_path_buf() });
    }
    let load = |path: &Path| {
        MjSpec::from_xml(path).map_err(|e| SimError::Load { path: path.to_path_buf(), message: e.to_string() })
    };
    let mut world = load(scene)?;
    let mut arm = load(&arm_path)?;
    let mut hand = load(&hand_path)?;

    prepare_hand(&mut hand, &hand_path)?;

    // Hand on the flange.
    let flange = arm.body_mut(FLANGE_BODY).ok_or_else(|| SimError::MissingElement {
        path: arm_path.clone(),
        kind: "body",
        name: FLANGE_BODY.into(),
    })?;
    let mount = flange.add_site().with_quat(HAND_ON_FLANGE_QUAT);
    mount.set_name("hand_mount").map_err(|e| edit_error(&arm_path, e))?;
    mount.attach_by_deep_copy(&mut hand, "", "").map_err(|e| edit_error(&hand_path, e))?;

    // Arm on the scene's mount site.
    let site = world.site_mut(MOUNT_SITE).ok_or_else(|| SimError::MissingElement {
        path: scene.to_path_buf(),
        kind: "site",
        name: MOUNT_SITE.into(),
    })?;
    site.attach_by_deep_copy(&mut arm, "", "").map_err(|e| edit_error(&arm_path, e))?;

    for path in extra {
        if !path.is_file() {
            return Err(SimError::SceneNotFound { path: path.clone() });
        }
        let mut objects = load(path)?;
        world
            .world_body_mut()
            .add_frame()
            .attach_by_deep_copy(&mut objects, "", "")
            .map_err(|e| edit_error(path, e))?;
    }

    world.compile().map_err(|e| SimError::Load { path: scene.to_path_buf(), message: e.to_string() })
}

/// Adds the wrist camera and grasp-friendly finger contacts to the hand before it is attached.
fn prepare_hand(hand: &mut MjSpec, hand_path: &Path) -> Result<(), SimError> {
    let missing =
        |kind, name: &str| SimError::MissingElement { path: hand_path.to_path_buf(), kind, name: name.into() };
    // The hand repeats the arm's `wrist_site`, `panda` texture and `panda` material (the same
    // texture file and values); keep the arm's, and the hand's geoms resolve to them by name.
    // SAFETY (each delete): no other handle to the element is alive; the spec stays valid.
    if let Some(site) = hand.site_mut("wrist_site") {
        unsafe { site.delete() }.map_err(|e| edit_error(hand_path, e))?;
    }
    if let Some(material) = hand.material_mut("panda") {
        unsafe { material.delete() }.map_err(|e| edit_error(hand_path, e))?;
    }
    if let Some(texture) = hand.texture_mut("panda") {
        unsafe { texture.delete() }.map_err(|e| edit_error(hand_path, e))?;
    }
    for pad in FINGER_PADS {
        let geom = hand.geom_mut(pad).ok_or_else(|| missing("geom", pad))?;
        geom.set_condim(FINGER_CONDIM);
        geom.set_priority(1);
        let _ = geom.with_friction(FINGER_FRICTION);
    }
    // The hand's position actuator pulls the tendon toward its target with 600 N/m, which
    // squeezes a 16 mm object with only ~5 N; the real Franka hand grasps with 20-70 N. Scale
    // gain, stiffness and damping together: the same open/closed positions, ~5x the grip.
    let actuator = hand.actuator_mut(GRIPPER_ACTUATOR).ok_or_else(|| missing("actuator", GRIPPER_ACTUATOR))?;
    actuator.gainprm_mut()[0] *= GRIP_SCALE;
    actuator.biasprm_mut()[1] *= GRIP_SCALE;
    actuator.biasprm_mut()[2] *= GRIP_SCALE;
    let body = hand.body_mut("panda_hand").ok_or_else(|| missing("body", "panda_hand"))?;
    let (s, c) = WRIST_CAMERA_TILT_RAD.sin_cos();
    let camera = body.add_camera().with_pos(WRIST_CAMERA_POS);
    camera.alt_mut().set_xy_axis(&[0.0, 1.0, 0.0, c, 0.0, s]);
    camera.set_fovy(WRIST_CAMERA_FOVY_DEG);
    camera.set_name("wrist").map_err(|e| edit_error(hand_path, e))?;
    Ok(())
}

fn edit_error(path: &Path, e: impl std::fmt::Display) -> SimError {
    SimError::Load { path: path.to_path_buf(), message: e.to_string() }
}
