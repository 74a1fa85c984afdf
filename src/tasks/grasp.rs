//! Gripper orientations and keyframe helpers shared by the experts (world frame).
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::control::keyframe::Keyframe;

/// The hand pointing down (TCP z = world -z), turned by `yaw` about the vertical; the fingers
/// close along the TCP's y axis.
pub fn top_down(yaw: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
}

/// The hand pointing horizontally along `approach` (unit, horizontal), fingers closing
/// horizontally (TCP y horizontal, TCP x = world up: the home posture pitched forward).
pub fn horizontal(approach: &Vector3<f64>) -> UnitQuaternion<f64> {
    let z = Vector3::new(approach.x, approach.y, 0.0).normalize();
    let x = Vector3::z();
    let y = z.cross(&x);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z])))
}

/// A keyframe at a world position and orientation.
pub fn keyframe(position: Vector3<f64>, rotation: UnitQuaternion<f64>, gripper_open: bool) -> Keyframe {
    Keyframe::at(&Isometry3::from_parts(Translation3::from(position), rotation), gripper_open)
}

/// The yaw (about world z) of a pose's x axis, folded to the gripper's symmetry: a parallel
/// gripper grasping a body with 90-degree symmetry may use any of 4 yaws; choose the one
/// closest to `preferred`.
pub fn symmetric_yaw(body_yaw: f64, symmetry: f64, preferred: f64) -> f64 {
    let k = ((preferred - body_yaw) / symmetry).round();
    body_yaw + k * symmetry
}

/// The six keyframes of a pick and place: above the object, down and close, lift; above the
/// place, down and open, lift (`clearance` metres above each).
pub fn pick_and_place(
    pick: Vector3<f64>,
    pick_rotation: UnitQuaternion<f64>,
    place: Vector3<f64>,
    place_rotation: UnitQuaternion<f64>,
    clearance: f64,
) -> [Keyframe; 6] {
    let up = Vector3::new(0.0, 0.0, clearance);
    [
        keyframe(pick + up, pick_rotation, true),
        keyframe(pick, pick_rotation, false),
        keyframe(pick + up, pick_rotation, false),
        keyframe(place + up, place_rotation, false),
        keyframe(place, place_rotation, true),
        keyframe(place + up, place_rotation, true),
    ]
}

/// Half the hand's palm length along the fingers' closing direction (the TCP's y), m. The palm
/// is about 4.5 cm above the TCP, so when the fingers reach an object on the table it is lower
/// than the tops of taller things nearby (jars, a stack) that lie along that line.
pub const PALM_HALF: f64 = 0.10;

/// How far (m, in the horizontal plane) the palm's line of a top-down hand at `at` turned by
/// `yaw` passes from the nearest of `obstacles` (their centres).
pub fn palm_clearance(at: &Vector3<f64>, yaw: f64, obstacles: &[Vector3<f64>]) -> f64 {
    let along = Vector3::new(-yaw.sin(), yaw.cos(), 0.0); // the TCP's y of `top_down(yaw)`, up to sign
    obstacles
        .iter()
        .map(|o| {
            let d = Vector3::new(o.x - at.x, o.y - at.y, 0.0);
            let t = d.dot(&along).clamp(-PALM_HALF, PALM_HALF);
            (d - along * t).norm()
        })
        .fold(f64::INFINITY, f64::min)
}

/// Of `candidates` (yaws, in order of preference), the one whose palm passes farthest from
/// `obstacles` ([`palm_clearance`]); the earlier one on a tie (within 1 mm).
pub fn clearest_yaw(at: &Vector3<f64>, candidates: impl IntoIterator<Item = f64>, obstacles: &[Vector3<f64>]) -> f64 {
    candidates
        .into_iter()
        .fold((0.0, f64::NEG_INFINITY), |(best, clearance), yaw| {
            let here = palm_clearance(at, yaw, obstacles);
            if here > clearance + 1e-3 { (yaw, here) } else { (best, clearance) }
        })
        .0
}
