//! open_drawer: "open the _ drawer" (left, middle, right; 3 variations, Table A: placement(3)).
//! RLBench stacks the drawers (top, middle, bottom); ours stand side by side, because the Panda
//! cannot hold its hand level 0.2-0.4 m above its base this close to its body (see the model).
//!
//! Scene: `models/tasks/open_drawer.xml`, a low cabinet with three drawers facing the robot.
//! Reset: the cabinet stands on the table at x in [0.70, 0.74] m, y in [-0.06, 0.06] m (world),
//! turned by up to +-6 deg about z. Expert (3 keyframes): 8 cm above the handle bar, down to
//! it and close the gripper (pointing down, fingers closing along the pull around the
//! horizontal bar), pull it 15 cm. Success: the named drawer is open by more than 10 cm.
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand::rngs::StdRng;

use std::f64::consts::{FRAC_PI_2, PI};

use super::grasp::{keyframe, symmetric_yaw, top_down};
use super::{Task, TaskError, TaskState};
use crate::control::keyframe::Keyframe;
use crate::sim::World;

pub(super) const DRAWERS: [&str; 3] = ["left", "middle", "right"];
/// The drawer counts as open beyond this (m).
const OPEN_THRESHOLD: f64 = 0.10;
pub(super) const PULL: f64 = 0.15;
/// The handle bar's centre in the drawer's frame (m): see `models/tasks/open_drawer.xml`.
const HANDLE: [f64; 3] = [-0.248, 0.0, 0.042];
/// The TCP closes 1 cm in front of the bar (toward the robot), so the open rear finger clears
/// the drawer front; closing then centres the bar (the drawer slides freely).
const GRASP_OFFSET: f64 = 0.01;
/// The TCP sits 5 mm below the bar's centre: the bar lies between the pads' upper parts.
const GRASP_BELOW: f64 = 0.005;

pub struct OpenDrawer;

impl Task for OpenDrawer {
    fn name(&self) -> &'static str {
        "open_drawer"
    }

    fn variation_count(&self) -> usize {
        DRAWERS.len()
    }

    fn instruction(&self, variation: usize) -> String {
        format!("open the {} drawer", DRAWERS[variation])
    }

    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError> {
        place_cabinet(world, rng)?;
        Ok(TaskState { targets: vec![DRAWERS[variation].to_string()], events: Vec::new() })
    }

    fn success(&self, world: &World, state: &TaskState) -> bool {
        world.joint_position(&format!("{}_drawer_slide", state.targets[0])).is_ok_and(|x| x > OPEN_THRESHOLD)
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        open_keyframes(world, &state.targets[0])
    }
}

/// Places the cabinet (the reset of the module docs; also `put_item_in_drawer`'s).
pub(super) fn place_cabinet(world: &mut World, rng: &mut StdRng) -> Result<(), TaskError> {
    let pose = Isometry3::from_parts(
        Translation3::new(rng.random_range(0.70..0.74), rng.random_range(-0.06..0.06), 0.75),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.random_range(-6f64..6.0).to_radians()),
    );
    world.set_fixed_body_pose("cabinet", &pose)?;
    Ok(())
}

/// The expert's keyframes opening `drawer` (left, middle, right): above the handle bar, down
/// and close, pull. The hand ends holding the bar.
pub(super) fn open_keyframes(world: &World, drawer: &str) -> Result<Vec<Keyframe>, TaskError> {
    let cabinet = world.body_pose("cabinet")?;
    let handle = world.body_pose(&format!("{drawer}_drawer"))? * nalgebra::Point3::from(HANDLE);
    // Toward the cabinet's back; the drawer opens along -inward.
    let inward = cabinet.rotation * Vector3::x();
    // From above, the fingers closing along the pull (TCP y = inward): pulling presses the
    // rear finger against the bar.
    let grip = top_down(symmetric_yaw(inward.y.atan2(inward.x) + FRAC_PI_2, PI, 0.0));
    let h = handle.coords - inward * GRASP_OFFSET - Vector3::z() * GRASP_BELOW;
    Ok(vec![
        keyframe(h + Vector3::z() * 0.08, grip, true),
        keyframe(h, grip, false),
        keyframe(h - inward * PULL, grip, false),
    ])
}
