//! Straight-line Cartesian waypoints: a move to a keyframe is cut into joint goals along the
//! straight line (and slerp) from the current TCP pose to the target, one every 3 cm / 0.1 rad,
//! each solved by IK seeded with the previous one. The runner feeds them to the trajectory one
//! after the other (switching at `WAYPOINT_SWITCH`), so the TCP moves along a line.
use nalgebra::Isometry3;

use super::ik::{IkError, InverseKinematics};
use crate::robot::{JointVector, Kinematics};

/// Straight-line motions get a joint goal every this many metres or radians.
const WAYPOINT_SPACING: f64 = 0.03;
const WAYPOINT_ANGLE: f64 = 0.1;
/// Switch to the next waypoint when the joint reference is this close to the current one (rad).
pub const WAYPOINT_SWITCH: f64 = 0.03;

/// Joint goals along the straight line (and slerp) from `from` to `target`, one every
/// 3 cm / 0.1 rad, each solved by IK seeded with the previous one, so that the TCP moves
/// along a line near objects instead of along a joint-space curve. If a point of the line
/// has no IK solution the move goes straight to the target in joint space.
pub fn straight_line_goals(
    ik: &InverseKinematics,
    kinematics: &mut Kinematics,
    from: &Isometry3<f64>,
    target: &Isometry3<f64>,
    seed: &JointVector,
) -> Result<Vec<JointVector>, IkError> {
    let distance = (target.translation.vector - from.translation.vector).norm();
    let angle = from.rotation.angle_to(&target.rotation);
    let steps = ((distance / WAYPOINT_SPACING).max(angle / WAYPOINT_ANGLE).ceil() as usize).clamp(1, 100);
    let mut goals = Vec::with_capacity(steps);
    let mut q = *seed;
    for i in 1..=steps {
        let s = i as f64 / steps as f64;
        let pose = Isometry3::from_parts(
            nalgebra::Translation3::from(from.translation.vector.lerp(&target.translation.vector, s)),
            from.rotation.slerp(&target.rotation, s),
        );
        match ik.solve_near(kinematics, &pose, &q, 0.5) {
            Ok(solution) => {
                q = solution.q;
                goals.push(q);
            }
            Err(_) => {
                let direct = ik.solve(kinematics, target, seed)?;
                return Ok(vec![direct.q]);
            }
        }
    }
    Ok(goals)
}
