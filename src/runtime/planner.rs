//! The planner thread: turns the policy's keyframes into motion plans (straight-line joint
//! goals by IK, as the lock-step runner does, but planned from the measured joint positions at
//! the request rather than from the previous plan's last goal) and refuses the ones the arm must not follow:
//! non-finite values, a quaternion that is not unit, a position outside the run's workspace box,
//! no IK solution. A refusal reaches the control thread as a [`Rejection`] and the arm holds.
use nalgebra::Isometry3;

use crate::control::execution::MotionPlan;
use crate::control::ik::{IkError, InverseKinematics, target_pose};
use crate::control::keyframe::Keyframe;
use crate::control::waypoints::straight_line_goals;
use crate::robot::{JointVector, Kinematics};

use super::messages::Rejection;

/// An axis-aligned box of TCP positions in the robot base frame (m).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct WorkspaceBox {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl WorkspaceBox {
    /// The table in front of the Panda in this project's scenes (base frame): 0.1 to 0.9 m ahead,
    /// 0.6 m to either side, from 5 cm below the base to 0.8 m above it.
    pub const TABLE: WorkspaceBox = WorkspaceBox { min: [0.1, -0.6, -0.05], max: [0.9, 0.6, 0.8] };

    pub fn contains(&self, p: &[f64; 3]) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }
}

/// IK and checks for the keyframes of one run.
pub struct Planner {
    pub ik: InverseKinematics,
    pub kinematics: Kinematics,
    pub workspace: WorkspaceBox,
}

impl Planner {
    /// The plan that takes the arm from `q` (at rest) to `keyframe` (base frame).
    pub fn plan(&mut self, keyframe: &Keyframe, q: &JointVector) -> Result<MotionPlan, Rejection> {
        let target = target_pose(keyframe.position, keyframe.quat_wxyz).map_err(|e| match e {
            IkError::NotUnitQuaternion { .. } => Rejection::NotUnitQuaternion,
            _ => Rejection::NonFinite,
        })?;
        if !self.workspace.contains(&keyframe.position) {
            return Err(Rejection::OutsideWorkspace);
        }
        let from = self.kinematics.tcp(q).unwrap_or_else(|_| Isometry3::identity());
        let goals = straight_line_goals(&self.ik, &mut self.kinematics, &from, &target, q)
            .map_err(|_| Rejection::Unreachable)?;
        MotionPlan::new(target, &goals, keyframe.gripper_open).map_err(|_| Rejection::BadPlan)
    }
}
