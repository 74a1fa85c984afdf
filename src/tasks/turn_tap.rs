//! turn_tap: "turn _ tap" (left, right; Table A: placement(2)). Rotation about a hinge while
//! grasped.
//!
//! Scene: `models/tasks/turn_tap.xml`, a tap with a left (+y, as the robot sees it) and a right
//! handle, each a lever bar on a vertical hinge. Reset: the tap at x in [0.48, 0.58] m, y in
//! [-0.10, 0.10] m (world), turned by up to 15 deg about z; both handles at 0. Expert (4
//! keyframes): 8 cm above the named lever, down and close across it (the TCP on the hinge
//! axis), turn the hand 100 deg counter-clockwise about the vertical, open and lift. Table A
//! counts 2 (grasp, turn); the approach and the release are ours. Success: the named handle
//! turned past 85 deg (the other handle is not checked, as in RLBench).
use std::f64::consts::{FRAC_PI_4, PI};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand::rngs::StdRng;

use super::grasp::{keyframe, symmetric_yaw, top_down};
use super::{Task, TaskError, TaskState};
use crate::control::keyframe::Keyframe;
use crate::sim::World;

const TAPS: [&str; 2] = ["left", "right"];
const TABLE_Z: f64 = 0.75;
/// The lever's centre above its handle's frame (m): see the model.
const LEVER_HEIGHT: f64 = 0.047;
/// Success beyond this turn (rad).
const TURNED: f64 = 85.0 * PI / 180.0;
/// How far the expert turns (rad).
const TURN: f64 = 100.0 * PI / 180.0;

pub struct TurnTap;

fn hinge(side: &str) -> String {
    format!("{side}_tap_hinge")
}

impl Task for TurnTap {
    fn name(&self) -> &'static str {
        "turn_tap"
    }

    fn variation_count(&self) -> usize {
        TAPS.len()
    }

    fn instruction(&self, variation: usize) -> String {
        format!("turn {} tap", TAPS[variation])
    }

    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError> {
        let centre = Translation3::new(rng.random_range(0.48..0.58), rng.random_range(-0.10..0.10), TABLE_Z);
        let yaw = rng.random_range(-15f64..15.0).to_radians();
        world.set_fixed_body_pose(
            "tap",
            &Isometry3::from_parts(centre, UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)),
        )?;
        for side in TAPS {
            world.set_joint_position(&hinge(side), 0.0)?;
        }
        Ok(TaskState { targets: vec![TAPS[variation].into()], events: Vec::new() })
    }

    fn success(&self, world: &World, state: &TaskState) -> bool {
        world.joint_position(&hinge(&state.targets[0])).is_ok_and(|q| q > TURNED)
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        let handle = world.body_pose(&format!("{}_tap", state.targets[0]))?;
        let lever = handle * nalgebra::Point3::new(0.0, 0.0, LEVER_HEIGHT);
        let (_, _, lever_yaw) = handle.rotation.euler_angles();
        // The fingers (along the TCP's y) close across the bar (along the handle's x): TCP y
        // along the handle's y. Of the two such hands, the one nearer -45 deg, so that the
        // turn ends near +55 deg, well inside the wrist's range.
        let start = symmetric_yaw(lever_yaw, PI, -FRAC_PI_4);
        // As the drawer handles: the TCP 5 mm below the bar's centre, the bar between the pads'
        // upper parts.
        let grasp = lever.coords - Vector3::new(0.0, 0.0, 0.005);
        let above = grasp + Vector3::new(0.0, 0.0, 0.08);
        Ok(vec![
            keyframe(above, top_down(start), true),
            keyframe(grasp, top_down(start), false),
            keyframe(grasp, top_down(start + TURN), false),
            keyframe(above, top_down(start + TURN), true),
        ])
    }
}
