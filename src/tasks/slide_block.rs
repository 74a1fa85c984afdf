//! slide_block: "slide the block to _ target" (green, blue, pink, yellow; Table A: colour(4)).
//! Non-prehensile: the closed gripper pushes the block.
//!
//! Scene: `models/tasks/slide_block.xml`, a 5 cm block and four 12 cm target zones. Reset: the
//! block at x in [0.50, 0.56] m, y in [-0.06, 0.06] m (world), turned by up to 10 deg; the
//! zones 0.13 m from it toward +x, -x, +y and -y with their colours shuffled. Expert
//! (4 keyframes): above the block on the far side from the target, down to 2 cm above the
//! table, push along the line until the block's centre is on the zone's, lift. Success: the
//! block's centre inside the named zone, block on the table.
use nalgebra::{Translation3, UnitQuaternion, Vector2, Vector3};
use rand::Rng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;

use super::grasp::{keyframe, symmetric_yaw, top_down};
use super::{Task, TaskError, TaskState};
use crate::control::keyframe::Keyframe;
use crate::sim::World;

const TARGETS: [(&str, [f32; 4]); 4] = [
    ("green", [0.0, 0.8, 0.0, 1.0]),
    ("blue", [0.0, 0.2, 1.0, 1.0]),
    ("pink", [1.0, 0.4, 0.7, 1.0]),
    ("yellow", [1.0, 0.9, 0.0, 1.0]),
];
const ZONE_OFFSET: f64 = 0.13;
const ZONE_HALF: f64 = 0.06;
const BLOCK_HALF: f64 = 0.025;
const TABLE_Z: f64 = 0.75;

pub struct SlideBlock;

impl Task for SlideBlock {
    fn name(&self) -> &'static str {
        "slide_block"
    }

    fn variation_count(&self) -> usize {
        TARGETS.len()
    }

    fn instruction(&self, variation: usize) -> String {
        format!("slide the block to {} target", TARGETS[variation].0)
    }

    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError> {
        let centre = Vector2::new(rng.random_range(0.50..0.56), rng.random_range(-0.06..0.06));
        let yaw = rng.random_range(-10f64..10.0).to_radians();
        world.set_body_pose(
            "block",
            &nalgebra::Isometry3::from_parts(
                Translation3::new(centre.x, centre.y, TABLE_Z + BLOCK_HALF),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
            ),
        )?;
        let mut colours: Vec<usize> = (0..TARGETS.len()).collect();
        colours.shuffle(rng);
        let directions =
            [Vector2::new(1.0, 0.0), Vector2::new(-1.0, 0.0), Vector2::new(0.0, 1.0), Vector2::new(0.0, -1.0)];
        let mut target = String::new();
        for (zone, (&colour, d)) in colours.iter().zip(directions).enumerate() {
            let p = centre + d * ZONE_OFFSET;
            let name = format!("zone_{zone}");
            world.set_fixed_body_pose(&name, &Translation3::new(p.x, p.y, TABLE_Z + 0.0005).into())?;
            world.set_geom_rgba(&name, TARGETS[colour].1)?;
            if colour == variation {
                target = name;
            }
        }
        Ok(TaskState { targets: vec![target], events: Vec::new() })
    }

    fn success(&self, world: &World, state: &TaskState) -> bool {
        let (Ok(block), Ok(zone)) = (world.body_pose("block"), world.body_pose(&state.targets[0])) else {
            return false;
        };
        let d = block.translation.vector - zone.translation.vector;
        d.x.abs() < ZONE_HALF && d.y.abs() < ZONE_HALF && (block.translation.z - TABLE_Z - BLOCK_HALF).abs() < 0.01
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        let block = world.body_pose("block")?.translation.vector;
        let zone = world.body_pose(&state.targets[0])?.translation.vector;
        let d = Vector3::new(zone.x - block.x, zone.y - block.y, 0.0).normalize();
        // The closed fingers' 6 cm face pushes: TCP x along the push (either sign, the closed
        // gripper is symmetric), as close to the home yaw as possible.
        let yaw = symmetric_yaw(d.y.atan2(d.x), std::f64::consts::PI, 0.0);
        let down = top_down(yaw);
        let height = TABLE_Z + 0.02;
        let behind = block - d * (BLOCK_HALF + 0.03);
        let start = Vector3::new(behind.x, behind.y, height);
        let end = Vector3::new(zone.x, zone.y, height) - d * (BLOCK_HALF + 0.005);
        Ok(vec![
            keyframe(start + Vector3::new(0.0, 0.0, 0.1), down, false),
            keyframe(start, down, false),
            keyframe(end, down, false),
            keyframe(end + Vector3::new(0.0, 0.0, 0.1), down, false),
        ])
    }
}
