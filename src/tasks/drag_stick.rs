//! drag_stick: "use the stick to drag the cube onto the _ target" (20 colours; Table A:
//! colour(20)). Tool use: the cube is dragged with a stick held near one end, as a rake.
//!
//! Scene: `models/tasks/drag_stick.xml`, a 30 cm stick and a 4 cm cube on the table and two
//! 10 cm target squares. Reset: the cube at x in [0.60, 0.64] m, y in [-0.06, 0.06] m (world);
//! the two targets on the line from the cube toward the robot, 8 and 20 cm from it (2 cm
//! apart; closer to the robot the low, turned hand runs out of joint range), the named
//! colour on one of them at random and another colour on the other; the stick lying along x
//! at x in [0.44, 0.50] m, y in [-0.26, -0.22] m, turned by up to 10 deg. Expert (6 keyframes,
//! as Table A): above the stick 10 cm from its near end, down and close across it, lift, above
//! the cube's far side with the hand turned 90 deg so that the stick lies across the cube's
//! path, down to the table there, drag toward the robot until the cube's centre is on the
//! target's. Success: the cube's centre on the named target (within its 5 cm half-width),
//! the cube on the table.
use std::f64::consts::{FRAC_PI_2, PI};

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;

use super::colors::{self, COLORS};
use super::grasp::{keyframe, symmetric_yaw, top_down};
use super::{TargetAlternatives, Task, TaskError, TaskState};
use crate::control::keyframe::Keyframe;
use crate::sim::World;

const TABLE_Z: f64 = 0.75;
const CUBE_HALF: f64 = 0.02;
const STICK_HALF: [f64; 3] = [0.15, 0.008, 0.008];
/// The stick is held this far from its near end (m): nearer its middle than a rake's handle,
/// because held 4 cm from the end its weight turned it about the fingers' axis.
const HOLD_FROM_END: f64 = 0.10;
const TARGET_HALF: f64 = 0.05;
/// The targets' distances from the cube toward the robot (m).
const TARGET_DISTANCES: [f64; 2] = [0.08, 0.20];

pub struct DragStick;

impl Task for DragStick {
    fn name(&self) -> &'static str {
        "drag_stick"
    }

    fn variation_count(&self) -> usize {
        COLORS.len()
    }

    fn instruction(&self, variation: usize) -> String {
        format!("use the stick to drag the cube onto the {} target", colors::name(variation))
    }

    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError> {
        let cube = Vector3::new(rng.random_range(0.60..0.64), rng.random_range(-0.06..0.06), TABLE_Z + CUBE_HALF);
        world.set_body_pose("cube", &Translation3::from(cube).into())?;
        let mut others: Vec<usize> = (0..COLORS.len()).filter(|&c| c != variation).collect();
        others.shuffle(rng);
        let named = rng.random_range(0..2usize);
        for (i, distance) in TARGET_DISTANCES.iter().enumerate() {
            let name = format!("target_{i}");
            world.set_fixed_body_pose(&name, &Translation3::new(cube.x - distance, cube.y, TABLE_Z + 0.0005).into())?;
            world.set_geom_rgba(&name, colors::rgba(if i == named { variation } else { others[0] }))?;
        }
        let stick = Isometry3::from_parts(
            Translation3::new(rng.random_range(0.44..0.50), rng.random_range(-0.26..-0.22), TABLE_Z + STICK_HALF[2]),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.random_range(-10f64..10.0).to_radians()),
        );
        world.set_body_pose("stick", &stick)?;
        Ok(TaskState { targets: vec![format!("target_{named}")], events: Vec::new() })
    }

    fn success(&self, world: &World, state: &TaskState) -> bool {
        let (Ok(cube), Ok(target)) = (world.body_pose("cube"), world.body_pose(&state.targets[0])) else {
            return false;
        };
        let d = cube.translation.vector - target.translation.vector;
        d.x.abs() < TARGET_HALF && d.y.abs() < TARGET_HALF && (cube.translation.z - TABLE_Z - CUBE_HALF).abs() < 0.01
    }

    /// Wrong: the other target square.
    fn target_alternatives(&self, state: &TaskState) -> TargetAlternatives {
        let wrong = (0..TARGET_DISTANCES.len()).map(|i| format!("target_{i}")).filter(|n| !state.targets.contains(n));
        TargetAlternatives { right: Vec::new(), wrong: TargetAlternatives::targeting(wrong) }
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        let stick = world.body_pose("stick")?;
        let cube = world.body_pose("cube")?.translation.vector;
        let target = world.body_pose(&state.targets[0])?.translation.vector;
        // Held near the end nearer the robot (the stick's -x end), fingers across it: the
        // stick along the TCP's x.
        let hold = stick * Point3::new(-(STICK_HALF[0] - HOLD_FROM_END), 0.0, 0.0);
        let (_, _, stick_yaw) = stick.rotation.euler_angles();
        let grip = top_down(symmetric_yaw(stick_yaw, PI, 0.0));
        let grasp = hold.coords + Vector3::new(0.0, 0.0, 0.005);
        let up = Vector3::new(0.0, 0.0, 0.12);
        // Turned 90 deg counter-clockwise, the stick (ahead of the TCP along its x) points along
        // +y, across the drag, just beyond the cube's far face. The cube meets the stick 5.5 cm
        // from the TCP: clear of the fingers, near enough that the drag's torque on the grasp
        // stays small (at 8 cm the stick turned in the fingers).
        let across = top_down(symmetric_yaw(stick_yaw, PI, 0.0) + FRAC_PI_2);
        let behind_x = cube.x + CUBE_HALF + STICK_HALF[1] + 0.006;
        let tcp_y = cube.y - 0.055;
        let low = TABLE_Z + STICK_HALF[2] + 0.004 + 0.005;
        let start = Vector3::new(behind_x, tcp_y, low);
        // The stick's near face ends where the cube's centre is on the target's.
        let end = Vector3::new(target.x + CUBE_HALF + STICK_HALF[1], tcp_y, low);
        Ok(vec![
            keyframe(grasp + up, grip, true),
            keyframe(grasp, grip, false),
            keyframe(grasp + up, grip, false),
            keyframe(start + up, across, false),
            keyframe(start, across, false),
            keyframe(end, across, false),
        ])
    }
}
