//! put_item_in_drawer: "put the item in the _ drawer" (left, middle, right; Table A:
//! placement(3)). The longest horizon: open a drawer, then pick and place into it.
//!
//! Scene: open_drawer's cabinet (`models/tasks/open_drawer.xml`, placed as there) and the item
//! (`models/tasks/put_item_in_drawer.xml`), a 4 cm cube on the cabinet's top at x in [-0.13,
//! -0.02] m, y in [-0.16, 0.16] m of the cabinet's frame (its front half: the far corners are
//! beyond the Panda's reach from above), turned by up to 20 deg. Expert (11
//! keyframes; Table A: 12): open the named drawer as open_drawer's expert (3), open the hand
//! and lift off the handle (2), above the item, down and close, lift (3), above the open
//! drawer, down and open, lift (3). Success: the item inside the named drawer (its centre
//! within the drawer's floor, front, back and 8 cm half-width, below the top of its front).
use std::f64::consts::FRAC_PI_2;
use std::path::PathBuf;

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand::rngs::StdRng;

use super::grasp::{keyframe, symmetric_yaw, top_down};
use super::open_drawer::{DRAWERS, open_keyframes, place_cabinet};
use super::{Task, TaskError, TaskState, model_file};
use crate::control::keyframe::Keyframe;
use crate::sim::World;

const ITEM_HALF: f64 = 0.02;
/// The cabinet's top surface above its origin (m), see open_drawer.xml.
const CABINET_TOP: f64 = 0.2;
/// The drawer's interior in its own frame (m): floor top, front inner face, back inner face,
/// half-width, front's top; see open_drawer.xml.
const FLOOR_TOP: f64 = -0.051;
const FRONT_INNER: f64 = -0.157;
const BACK_INNER: f64 = 0.126;
const HALF_WIDTH: f64 = 0.08;
const FRONT_TOP: f64 = 0.055;
/// Where the item goes, in the drawer's frame: mid-way in the part that the 15 cm pull brings
/// out of the cabinet.
const PLACE_X: f64 = -0.09;

pub struct PutItemInDrawer;

impl Task for PutItemInDrawer {
    fn name(&self) -> &'static str {
        "put_item_in_drawer"
    }

    fn variation_count(&self) -> usize {
        DRAWERS.len()
    }

    fn instruction(&self, variation: usize) -> String {
        format!("put the item in the {} drawer", DRAWERS[variation])
    }

    fn model_files(&self) -> Vec<PathBuf> {
        vec![model_file("open_drawer"), model_file(self.name())]
    }

    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError> {
        place_cabinet(world, rng)?;
        let cabinet = world.body_pose("cabinet")?;
        let local = Point3::new(rng.random_range(-0.13..-0.02), rng.random_range(-0.16..0.16), CABINET_TOP + ITEM_HALF);
        let yaw = rng.random_range(-20f64..20.0).to_radians();
        let pose = Isometry3::from_parts(
            Translation3::from((cabinet * local).coords),
            cabinet.rotation * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
        );
        world.set_body_pose("item", &pose)?;
        Ok(TaskState { targets: vec![DRAWERS[variation].to_string()], events: Vec::new() })
    }

    fn success(&self, world: &World, state: &TaskState) -> bool {
        let (Ok(item), Ok(drawer)) =
            (world.body_pose("item"), world.body_pose(&format!("{}_drawer", state.targets[0])))
        else {
            return false;
        };
        let p = drawer.inverse() * Point3::from(item.translation.vector);
        (FRONT_INNER..BACK_INNER).contains(&p.x)
            && p.y.abs() < HALF_WIDTH
            && p.z > FLOOR_TOP
            && p.z < FLOOR_TOP + 2.0 * ITEM_HALF + 0.01
            && p.z < FRONT_TOP
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        let mut plan = open_keyframes(world, &state.targets[0])?;
        // Let go of the handle where the pull ended, then lift off it.
        let pulled = *plan.last().expect("open_keyframes ends with the pull");
        let [x, y, z] = pulled.position;
        plan.push(Keyframe { gripper_open: true, ..pulled });
        plan.push(Keyframe { position: [x, y, z + 0.08], gripper_open: true, ..pulled });
        // The item, taken across a pair of its faces with the hand's long side (the palm, along
        // the fingers' closing direction) along the cabinet's y, so that it fits above the
        // drawer between its neighbours' handles.
        let cabinet = world.body_pose("cabinet")?;
        let item = world.body_pose("item")?;
        let (_, _, cabinet_yaw) = cabinet.rotation.euler_angles();
        let (_, _, item_yaw) = item.rotation.euler_angles();
        let grip = top_down(symmetric_yaw(item_yaw, FRAC_PI_2, cabinet_yaw));
        let up = Vector3::new(0.0, 0.0, 0.08);
        let grasp = item.translation.vector + Vector3::new(0.0, 0.0, 0.005);
        plan.extend([
            keyframe(grasp + up, grip, true),
            keyframe(grasp, grip, false),
            keyframe(grasp + up, grip, false),
        ]);
        // Into the drawer as it will be after the pull (the pull keyframe's 15 cm).
        let drawer = world.body_pose(&format!("{}_drawer", state.targets[0]))?;
        let opened = Translation3::from(-(cabinet.rotation * Vector3::x()) * super::open_drawer::PULL) * drawer;
        let place =
            (opened * Point3::new(PLACE_X, 0.0, FLOOR_TOP + ITEM_HALF)).coords + Vector3::new(0.0, 0.0, 0.005 + 0.01);
        // Above the drawer the carried item clears the cabinet's top (2.5 cm above the drawer's
        // floor) on the way there.
        let above = place + Vector3::new(0.0, 0.0, 0.15);
        plan.extend([keyframe(above, grip, false), keyframe(place, grip, true), keyframe(above, grip, true)]);
        Ok(plan)
    }
}
