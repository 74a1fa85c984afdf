//! open_drawer: "open the _ drawer" (left, middle, right; 3 variations, Table A: placement(3)).
//! RLBench stacks the drawers (top, middle, bottom); ours stand side by side, because the Panda
//! cannot hold its hand level 0.2-0.4 m above its base this close to its body (see the model).
//!
//! Scene: `models/tasks/open_drawer.xml`, a low cabinet with three drawers facing the robot.
//! Reset: the cabinet stands on the table at x in [0.70, 0.74] m, y in [-0.06, 0.06] m (world),
//! turned by up to +-6 deg about z. Expert (3 keyframes): in front of the handle, at the
//! handle and close the gripper, pull it 15 cm. The hand approaches level with the wrist above
//! it (clear of the table), fingers closing around the vertical bar 2 cm deep between the pads. Success: the named drawer is open by more than 10 cm.
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand::rngs::StdRng;

use super::grasp::{horizontal_wrist_up, keyframe};
use super::{Task, TaskError, TaskState};
use crate::control::runner::Keyframe;
use crate::sim::World;

const DRAWERS: [&str; 3] = ["left", "middle", "right"];
/// The drawer counts as open beyond this (m).
const OPEN_THRESHOLD: f64 = 0.10;
const PULL: f64 = 0.15;
const GRASP_DEPTH: f64 = 0.02;

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
        let pose = Isometry3::from_parts(
            Translation3::new(rng.random_range(0.70..0.74), rng.random_range(-0.06..0.06), 0.75),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.random_range(-6f64..6.0).to_radians()),
        );
        world.set_fixed_body_pose("cabinet", &pose)?;
        Ok(TaskState { targets: vec![DRAWERS[variation].to_string()], events: Vec::new() })
    }

    fn success(&self, world: &World, state: &TaskState) -> bool {
        world.joint_position(&format!("{}_drawer_slide", state.targets[0])).is_ok_and(|x| x > OPEN_THRESHOLD)
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        let drawer = &state.targets[0];
        let cabinet = world.body_pose("cabinet")?;
        let handle = world.body_pose(&format!("{drawer}_drawer"))? * nalgebra::Point3::new(-0.215, 0.0, 0.0);
        // Approach along the cabinet's +x (toward its back), fingers closing horizontally.
        let inward = cabinet.rotation * Vector3::x();
        let grip = horizontal_wrist_up(&inward);
        // The bar sits 2 cm deep between the finger pads, not at their tips.
        let h = handle.coords + inward * GRASP_DEPTH;
        Ok(vec![
            keyframe(h - inward * 0.10, grip, true),
            keyframe(h, grip, false),
            keyframe(h - inward * PULL, grip, false),
        ])
    }
}
