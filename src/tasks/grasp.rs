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
