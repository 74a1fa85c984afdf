//! meat_off_grill: "take the _ off the grill" (chicken, steak; Table A: object(2)).
//!
//! Scene: `models/tasks/meat_off_grill.xml`, a grill (top 8 cm above the table) with a chicken
//! piece and a steak on it, and a plate beside it. Reset: the grill centre at x in [0.46, 0.56]
//! m, y in [-0.20, -0.10] m (world), its long side along y; the two items on it 7 cm either
//! side of its centre along y (which one where at random), each shifted by up to 2 cm in x and
//! turned by up to 30 deg; the plate centre at x in [0.44, 0.58], y in [0.10, 0.20]. Expert (5
//! keyframes, as Table A): above the named item, down and close across its narrow side, lift,
//! above the plate, down and open. Success: the named item resting on the plate (centre within
//! its 8 cm radius, its bottom on the plate's top within 1 cm) and the other still on the grill.
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand::rngs::StdRng;

use super::grasp::{pick_and_place, symmetric_yaw, top_down};
use super::{Task, TaskError, TaskState};
use crate::control::keyframe::Keyframe;
use crate::sim::World;

/// The items, their half heights (m).
const ITEMS: [(&str, f64); 2] = [("chicken", 0.015), ("steak", 0.01)];
const TABLE_Z: f64 = 0.75;
const GRILL_TOP: f64 = TABLE_Z + 0.08;
const GRILL_HALF: [f64; 2] = [0.1, 0.15];
const PLATE_TOP: f64 = TABLE_Z + 0.01;
const PLATE_RADIUS: f64 = 0.08;
/// Items' centres this far from the grill centre along its long side (m).
const ITEM_OFFSET: f64 = 0.07;

pub struct MeatOffGrill;

/// Half the height of the item `name` (one of [`ITEMS`]; the task's own names, never input).
fn half_height(name: &str) -> f64 {
    ITEMS.iter().find(|(n, _)| *n == name).map_or(0.0, |(_, h)| *h)
}

impl Task for MeatOffGrill {
    fn name(&self) -> &'static str {
        "meat_off_grill"
    }

    fn variation_count(&self) -> usize {
        ITEMS.len()
    }

    fn instruction(&self, variation: usize) -> String {
        format!("take the {} off the grill", ITEMS[variation].0)
    }

    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError> {
        let grill = Vector3::new(rng.random_range(0.46..0.56), rng.random_range(-0.20..-0.10), TABLE_Z);
        world.set_fixed_body_pose("grill", &Translation3::from(grill).into())?;
        let plate = Vector3::new(rng.random_range(0.44..0.58), rng.random_range(0.10..0.20), TABLE_Z);
        world.set_fixed_body_pose("plate", &Translation3::from(plate).into())?;
        let side = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
        for (i, (name, half)) in ITEMS.iter().enumerate() {
            let along = if i == 0 { side } else { -side } * ITEM_OFFSET;
            let p = Vector3::new(grill.x + rng.random_range(-0.02..0.02), grill.y + along, GRILL_TOP + half);
            let yaw = rng.random_range(-30f64..30.0).to_radians();
            let pose = Isometry3::from_parts(p.into(), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw));
            world.set_body_pose(name, &pose)?;
        }
        Ok(TaskState { targets: vec![ITEMS[variation].0.into(), ITEMS[1 - variation].0.into()], events: Vec::new() })
    }

    fn success(&self, world: &World, state: &TaskState) -> bool {
        let (Ok(item), Ok(other), Ok(plate), Ok(grill)) = (
            world.body_pose(&state.targets[0]),
            world.body_pose(&state.targets[1]),
            world.body_pose("plate"),
            world.body_pose("grill"),
        ) else {
            return false;
        };
        let on_plate = (item.translation.vector - plate.translation.vector).xy().norm() < PLATE_RADIUS
            && (item.translation.z - half_height(&state.targets[0]) - PLATE_TOP).abs() < 0.01;
        let d = other.translation.vector - grill.translation.vector;
        let still_on_grill = d.x.abs() < GRILL_HALF[0]
            && d.y.abs() < GRILL_HALF[1]
            && (other.translation.z - half_height(&state.targets[1]) - GRILL_TOP).abs() < 0.01;
        on_plate && still_on_grill
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        let item = world.body_pose(&state.targets[0])?;
        let plate = world.body_pose("plate")?.translation.vector;
        let half = half_height(&state.targets[0]);
        // The fingers close along the TCP's y: across the item's narrow (local y) side.
        let (_, _, item_yaw) = item.rotation.euler_angles();
        let grasp_rotation = top_down(symmetric_yaw(item_yaw, std::f64::consts::PI, 0.0));
        // Closed 5 mm above the item's centre; set down 1 cm above the plate and released.
        let grasp = item.translation.vector + Vector3::new(0.0, 0.0, 0.005);
        let place = Vector3::new(plate.x, plate.y, PLATE_TOP + half + 0.005 + 0.01);
        Ok(pick_and_place(grasp, grasp_rotation, place, top_down(0.0), 0.12)[..5].to_vec())
    }
}
