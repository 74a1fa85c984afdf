//! sweep_to_dustpan: "sweep dirt to the _ dustpan" (short, tall; Table A: size(2), "sweep dirt
//! to dustpan"). Tool use with contact: a brush pushes loose dirt into a pan.
//!
//! Scene: `models/tasks/sweep_to_dustpan.xml`, a brush, five dirt pieces and a short and a tall
//! dustpan. Reset: the dirt in a 6 cm cluster around x in [0.48, 0.56] m, y in [-0.03, 0.03] m
//! (world); the two pans 20 cm either side of it along y, open toward it, which size on which
//! side at random; the brush lying along x (head toward +x) at x in [0.36, 0.40] m, y in
//! [-0.42, -0.38] m, turned by up to 10 deg. Expert (7 keyframes; Table A: 4.6): above the
//! handle, down and close, lift, turn the hand 90 deg toward the named pan's side (the head
//! ahead) above the cluster's far side, down until the head is 2 mm above the table, sweep
//! along y into the pan, lift. Success: every dirt piece on the named pan's floor.
use std::f64::consts::FRAC_PI_2;

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand::rngs::StdRng;

use super::grasp::{keyframe, top_down};
use super::{Task, TaskError, TaskState};
use crate::control::keyframe::Keyframe;
use crate::sim::World;

const SIZES: [&str; 2] = ["short", "tall"];
const TABLE_Z: f64 = 0.75;
const DIRT: usize = 5;
const DIRT_HALF: f64 = 0.006;
/// The pans' centres from the cluster's, along y (m).
const PAN_OFFSET: f64 = 0.20;
/// The pan floor's half sizes (m) in its frame (x across, y toward its back).
const FLOOR_HALF: [f64; 2] = [0.06, 0.05];
/// The brush: the head's centre and half height in its frame (m).
const HEAD_X: f64 = 0.1;
const HEAD_HALF_Z: f64 = 0.01;
/// The handle is held this far from its centre toward the head (near the brush's centre of
/// mass, so its weight does not turn it in the fingers).
const HOLD_X: f64 = 0.03;

pub struct SweepToDustpan;

impl Task for SweepToDustpan {
    fn name(&self) -> &'static str {
        "sweep_to_dustpan"
    }

    fn variation_count(&self) -> usize {
        SIZES.len()
    }

    fn instruction(&self, variation: usize) -> String {
        format!("sweep dirt to the {} dustpan", SIZES[variation])
    }

    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError> {
        let centre = Vector3::new(rng.random_range(0.48..0.56), rng.random_range(-0.03..0.03), TABLE_Z);
        for i in 0..DIRT {
            let p = centre + Vector3::new(rng.random_range(-0.03..0.03), rng.random_range(-0.03..0.03), DIRT_HALF);
            let yaw = rng.random_range(0.0..FRAC_PI_2);
            world.set_body_pose(
                &format!("dirt_{i}"),
                &Isometry3::from_parts(p.into(), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)),
            )?;
        }
        // The short pan on +y or -y; each opens toward the dirt (its -y side faces it).
        let short_side = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
        for (size, side) in [("short", short_side), ("tall", -short_side)] {
            let at = Translation3::new(centre.x, centre.y + side * PAN_OFFSET, TABLE_Z);
            let facing = UnitQuaternion::from_axis_angle(
                &Vector3::z_axis(),
                if side > 0.0 { 0.0 } else { std::f64::consts::PI },
            );
            world.set_fixed_body_pose(&format!("{size}_dustpan"), &Isometry3::from_parts(at, facing))?;
        }
        let brush = Isometry3::from_parts(
            Translation3::new(
                rng.random_range(0.36..0.40),
                rng.random_range(-0.42..-0.38),
                TABLE_Z + HEAD_HALF_Z + 0.001,
            ),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.random_range(-10f64..10.0).to_radians()),
        );
        world.set_body_pose("brush", &brush)?;
        Ok(TaskState { targets: vec![format!("{}_dustpan", SIZES[variation])], events: Vec::new() })
    }

    fn success(&self, world: &World, state: &TaskState) -> bool {
        let Ok(pan) = world.body_pose(&state.targets[0]) else { return false };
        (0..DIRT).all(|i| {
            world.body_pose(&format!("dirt_{i}")).is_ok_and(|d| {
                let p = pan.inverse() * Point3::from(d.translation.vector);
                p.x.abs() < FLOOR_HALF[0] && p.y.abs() < FLOOR_HALF[1] && p.z < 0.02
            })
        })
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        let brush = world.body_pose("brush")?;
        let pan_pose = world.body_pose(&state.targets[0])?;
        let pan = pan_pose.translation.vector;
        // The pan's +y points from its open side to its back wall: the sweep's direction along y.
        let side = (pan_pose.rotation * Vector3::y()).y.signum();
        let (_, _, brush_yaw) = brush.rotation.euler_angles();
        // Fingers across the handle: the handle (head toward +x) along the TCP's x.
        let hold = (brush * Point3::new(HOLD_X, 0.0, 0.0)).coords + Vector3::new(0.0, 0.0, 0.005);
        let grip = top_down(brush_yaw);
        let up = Vector3::new(0.0, 0.0, 0.12);
        // Turned so that the head leads along +-y, straight along the pan's axis (the cluster
        // lies within the head's 10 cm, which passes 1 cm inside each side wall); where the
        // sweep starts, from the dirt itself.
        let sweep = top_down(side * FRAC_PI_2);
        let dirt: Vec<Vector3<f64>> = (0..DIRT)
            .map(|i| world.body_pose(&format!("dirt_{i}")).map(|p| p.translation.vector))
            .collect::<Result<_, _>>()?;
        let rear = dirt.iter().map(|d| -side * d.y).fold(f64::NEG_INFINITY, f64::max) * -side;
        let lead = HEAD_X - HOLD_X; // TCP to the head's centre, along the sweep
        let z = TABLE_Z + HEAD_HALF_Z + 0.002 + 0.005;
        // The head's leading face starts 1.5 cm behind the rearmost piece and ends 3 cm short of
        // the pan's back wall.
        let start = Vector3::new(pan.x, rear - side * (0.01 + 0.015) - side * lead, z);
        let end_head = pan.y + side * (FLOOR_HALF[1] - 0.03 - 0.01);
        let end = Vector3::new(pan.x, end_head - side * lead, z);
        Ok(vec![
            keyframe(hold + up, grip, true),
            keyframe(hold, grip, false),
            keyframe(hold + up, grip, false),
            keyframe(start + up, sweep, false),
            keyframe(start, sweep, false),
            keyframe(end, sweep, false),
            keyframe(end + up, sweep, false),
        ])
    }
}
