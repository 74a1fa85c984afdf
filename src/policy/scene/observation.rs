//! What the policy sees and predicts, independent of the simulator: camera views (RGB-D with
//! intrinsics and extrinsics), proprioception and the instruction in; a keyframe (position,
//! rotation, gripper open) out. Also the lifting of an observation to the workspace point set
//! that semantic and geometric tokens are drawn from, and the action vector the flow runs on.
use serde::Serialize;

use super::farthest_point::farthest_point_sample;
use super::lifting::lift_depth;
use super::radius_schedule::global_geometric_tokens;
use super::rotation::{quaternion_from_6d, quaternion_to_6d};
use super::workspace::WorkspaceBounds;
use crate::data::Episode;
use crate::policy::error::{PolicyError, Result};

/// Position dimensions of the flowed action (normalised to the workspace, [-1, 1]).
pub const POSITION_DIMS: usize = 3;
/// 6D rotation dimensions of the flowed action (first two rotation-matrix columns).
pub const ROTATION_DIMS: usize = 6;
/// All flowed dimensions: `POSITION_DIMS + ROTATION_DIMS`.
pub const ACTION_DIMS: usize = POSITION_DIMS + ROTATION_DIMS;

/// One camera's images and calibration.
#[derive(Debug, Clone)]
pub struct CameraView {
    /// The camera's name (`front`, `wrist`, ...; see `flowram collect --cameras`).
    pub name: String,
    /// Row-major H x W x 3 RGB.
    pub rgb: Vec<u8>,
    /// Row-major H x W z-depth in metres (0 = nothing).
    pub depth: Vec<f32>,
    /// Pinhole K (pixels, pixel centres at integer coordinates), row-major.
    pub intrinsics: [[f32; 3]; 3],
    /// Camera-to-world (OpenCV camera axes: x right, y down, z forward), row-major.
    pub camera_to_world: [[f32; 4]; 4],
}

/// The policy's input at one keyframe.
#[derive(Debug, Clone)]
pub struct Observation {
    /// Square images of `size` pixels, one view per camera (in a fixed camera order).
    pub size: usize,
    pub cameras: Vec<CameraView>,
    /// TCP position (world, m), quaternion w, x, y, z, gripper open (1/0).
    pub proprio: [f32; 8],
    pub instruction: String,
    /// Keyframes of the episode executed before this observation (0 at the start); read by
    /// policies with `observation.keyframe_index`.
    pub keyframe: usize,
    /// Proprioception (as `proprio`) at the episode's earlier keyframe observations, most recent
    /// first, recovery detours left out; read by policies with `observation.proprio_history` > 1.
    pub history: Vec<[f32; 8]>,
}

/// A keyframe: what the policy predicts and what the control stack executes.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct KeyframePose {
    /// TCP position, world frame, metres.
    pub position: [f32; 3],
    /// TCP orientation, unit quaternion w, x, y, z (w >= 0), world frame.
    pub quat_wxyz: [f32; 4],
    pub gripper_open: bool,
}

impl KeyframePose {
    /// From the dataset layout (position, quat wxyz, open).
    pub fn from_proprio(v: &[f32; 8]) -> Self {
        Self { position: [v[0], v[1], v[2]], quat_wxyz: [v[3], v[4], v[5], v[6]], gripper_open: v[7] > 0.5 }
    }

    /// The [`ACTION_DIMS`] continuous action dimensions the flow runs on: position normalised to the
    /// workspace ([-1, 1] per axis), then the 6D rotation (the rotation matrix's first two
    /// columns).
    pub fn to_action(&self, workspace: &WorkspaceBounds) -> Result<[f32; ACTION_DIMS]> {
        let p = workspace.normalize(self.position);
        let r = quaternion_to_6d(self.quat_wxyz)?;
        Ok([p[0], p[1], p[2], r[0], r[1], r[2], r[3], r[4], r[5]])
    }

    /// Back from the action vector (rotation re-orthonormalised by Gram-Schmidt) and the
    /// gripper-open logit.
    pub fn from_action(a: &[f32; ACTION_DIMS], open_logit: f32, workspace: &WorkspaceBounds) -> Self {
        let position = workspace.denormalize([a[0], a[1], a[2]]);
        let quat_wxyz = quaternion_from_6d([a[3], a[4], a[5], a[6], a[7], a[8]]);
        Self { position, quat_wxyz, gripper_open: open_logit > 0.0 }
    }

    /// Position error (m) and rotation error (rad) to another keyframe.
    pub fn error_to(&self, other: &KeyframePose) -> (f32, f32) {
        let d: f32 = (0..3).map(|i| (self.position[i] - other.position[i]).powi(2)).sum::<f32>().sqrt();
        let dot: f32 = (0..4).map(|i| self.quat_wxyz[i] * other.quat_wxyz[i]).sum::<f32>().abs().min(1.0);
        (d, 2.0 * dot.acos())
    }
}

/// Proprioception as network input: normalised position, 6D rotation, gripper open (10 values).
pub fn proprio_features(proprio: &[f32; 8], workspace: &WorkspaceBounds) -> Result<[f32; 10]> {
    let a = KeyframePose::from_proprio(proprio).to_action(workspace)?;
    let mut f = [0.0; 10];
    f[..9].copy_from_slice(&a);
    f[9] = proprio[7];
    Ok(f)
}

/// The `poses` gripper poses of an observation as network input: [`proprio_features`] of the
/// current pose, then of each earlier one in [`Observation::history`] (most recent first),
/// repeating the oldest pose there is when the episode has fewer. `10 * poses` values.
pub fn proprio_history_features(
    observation: &Observation,
    poses: usize,
    workspace: &WorkspaceBounds,
) -> Result<Vec<[f32; 10]>> {
    let mut features = Vec::with_capacity(poses);
    let mut last = &observation.proprio;
    for i in 0..poses {
        if i > 0 {
            last = observation.history.get(i - 1).unwrap_or(last);
        }
        features.push(proprio_features(last, workspace)?);
    }
    Ok(features)
}

impl Observation {
    /// Keyframe `k` of a dataset episode (all its cameras, in the episode's order). Its
    /// [`Observation::keyframe`] counts the samples before `k` that are not recovery detours
    /// ([`is_detour`]) and [`Observation::history`] holds their proprioception: a detour's
    /// observation stands in for the next one's state, off target, and closed loop the policy
    /// never makes it.
    pub fn from_episode(episode: &Episode, k: usize) -> Result<Self> {
        let keyframes = episode.keyframes();
        if k >= keyframes {
            return Err(PolicyError::Invalid(format!(
                "keyframe {k} does not exist: the episode has keyframes 0..{}",
                keyframes.saturating_sub(1)
            )));
        }
        if episode.height != episode.width {
            return Err(PolicyError::Invalid(format!(
                "the policy needs square images; the episode has {}x{}",
                episode.height, episode.width
            )));
        }
        let (h, w, cams) = (episode.height, episode.width, episode.cameras.len());
        let mut cameras = Vec::with_capacity(cams);
        for c in 0..cams {
            let image = k * cams + c;
            let k9 = &episode.intrinsics[c * 9..c * 9 + 9];
            let e16 = &episode.extrinsics[image * 16..image * 16 + 16];
            cameras.push(CameraView {
                name: episode.cameras[c].clone(),
                rgb: episode.rgb[image * h * w * 3..(image + 1) * h * w * 3].to_vec(),
                depth: episode.depth[image * h * w..(image + 1) * h * w].to_vec(),
                intrinsics: std::array::from_fn(|r| std::array::from_fn(|col| k9[r * 3 + col])),
                camera_to_world: std::array::from_fn(|r| std::array::from_fn(|col| e16[r * 4 + col])),
            });
        }
        let proprio: [f32; 8] = std::array::from_fn(|i| episode.proprio[k * 8 + i]);
        let keyframe = keyframe_index(&episode.action, k);
        let history = (0..k)
            .rev()
            .filter(|&i| !is_detour(&episode.action, i))
            .map(|i| std::array::from_fn(|j| episode.proprio[i * 8 + j]))
            .collect();
        Ok(Self { size: h, cameras, proprio, instruction: episode.instruction.clone(), keyframe, history })
    }

    /// The recorded expert action at keyframe `k` of an episode.
    pub fn episode_action(episode: &Episode, k: usize) -> KeyframePose {
        KeyframePose::from_proprio(&std::array::from_fn(|i| episode.action[k * 8 + i]))
    }
}

/// Whether sample `k` of an episode is a recovery detour's observation: the perturbed expert
/// (`collect --perturb-sigma`, recovery target `next`) records the observation at the detour
/// with the action of the approach keyframe's successor, which is also the action of the sample
/// after it (the observation at the approach), so a detour is a sample whose action equals its
/// successor's. Expert keyframes never repeat (a missed grasp's samples act grasp, approach,
/// grasp). In datasets collected with `--perturb-target approach` (arm R) the detour shares its
/// action with the clean sample *before* it, so that one is flagged instead; the keyframe
/// indices ([`keyframe_index`]) come out the same from the sample after the detour on.
/// `actions` is an episode's `action` tensor, [K, 8] row-major.
pub fn is_detour(actions: &[f32], k: usize) -> bool {
    let next = k + 1;
    (next + 1) * 8 <= actions.len() && actions[k * 8..next * 8] == actions[next * 8..(next + 1) * 8]
}

/// How much higher the keyframe after a stage's end is, at least (m): the arm leaves going up.
pub const STAGE_RISE_M: f32 = 0.02;

/// The end of sample `k`'s stage (`flow.goal_keyframe = "stage_end"`): the first sample `j >= k`
/// whose action the arm reaches coming down and leaves going up: the next action is at least
/// [`STAGE_RISE_M`] higher, and the nearest earlier action at a different height (more than
/// [`STAGE_RISE_M`] apart, so detours' repeated actions and a push's level path count as one
/// plateau) is higher. A press, a grasp, a placing, the end of a push. The episode's last sample
/// where none follows (so the goal is the last keyframe, as `"last"` has it, once the last stage
/// has begun). `actions` is an episode's `action` tensor, [K, 8] row-major.
pub fn stage_end(actions: &[f32], k: usize) -> usize {
    let samples = actions.len() / 8;
    let z = |j: usize| actions[j * 8 + 2];
    let last = samples.saturating_sub(1);
    (k..last)
        .find(|&j| {
            let rises = z(j + 1) >= z(j) + STAGE_RISE_M;
            let came_down = (0..j).rev().map(z).find(|&h| (h - z(j)).abs() > STAGE_RISE_M).is_some_and(|h| h > z(j));
            rises && came_down
        })
        .unwrap_or(last)
}

/// Keyframes executed before sample `k` of an episode whose `action` tensor is `actions`: the
/// samples before it that are not detours ([`is_detour`]).
pub fn keyframe_index(actions: &[f32], k: usize) -> usize {
    (0..k).filter(|&i| !is_detour(actions, i)).count()
}

/// The lifted feature pixels of an observation that lie in the workspace.
#[derive(Debug, Clone, Default)]
pub struct SceneCloud {
    /// Normalised workspace coordinates ([-1, 1]^3).
    pub points_norm: Vec<[f32; 3]>,
    /// For each point, its feature pixel: `camera * cells_per_camera + row * grid + col`.
    pub cells: Vec<usize>,
    /// N1 indices into `points_norm`: the semantic tokens (farthest point sampling; repeated
    /// cyclically when the cloud has fewer points), in scan order (Z-order curve).
    pub semantic: Vec<usize>,
    /// N2 indices into `points_norm`: the global geometric tokens
    /// ([`global_geometric_tokens`]), computed once for every flow step that uses them.
    pub geometric_global: Vec<usize>,
}

/// Lifts every feature pixel (stride `stride`) of every camera to the world, keeps those in the
/// workspace, picks the N1 semantic tokens and the N2 global geometric tokens. Errors when no
/// pixel lies in the workspace.
pub fn lift_scene(
    observation: &Observation,
    stride: usize,
    workspace: &WorkspaceBounds,
    n1: usize,
    n2: usize,
) -> Result<SceneCloud> {
    let grid = observation.size / stride.max(1);
    let per_camera = grid * grid;
    let mut cloud = SceneCloud::default();
    for (c, view) in observation.cameras.iter().enumerate() {
        let lifted = lift_depth(
            &view.depth,
            observation.size,
            observation.size,
            &view.intrinsics,
            &view.camera_to_world,
            stride,
        )?;
        let cropped = workspace.crop_and_normalize(&lifted);
        cloud.points_norm.extend_from_slice(&cropped.points_norm);
        cloud.cells.extend(cropped.cells.iter().map(|&cell| c * per_camera + cell));
    }
    if cloud.points_norm.is_empty() {
        return Err(PolicyError::Invalid(
            "no depth pixel of the observation lies in the policy's workspace: check the cameras and observation.workspace".into(),
        ));
    }
    cloud.semantic = if cloud.points_norm.len() >= n1 {
        farthest_point_sample(&cloud.points_norm, n1, 0)?
    } else {
        (0..cloud.points_norm.len()).cycle().take(n1).collect()
    };
    // scan order: along a Z-order curve (see `scene::token_order`)
    crate::policy::scene::token_order::sort_by_morton(&cloud.points_norm, &mut cloud.semantic);
    cloud.geometric_global = global_geometric_tokens(&cloud.points_norm, n2)?;
    Ok(cloud)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An action tensor of keyframes at these heights (x = the sample's index, so that equal
    /// heights are different keyframes; a test copies a row onto the next to make a detour).
    fn heights(z: &[f32]) -> Vec<f32> {
        z.iter().enumerate().flat_map(|(i, &h)| [i as f32, 0.0, h, 1.0, 0.0, 0.0, 0.0, 1.0]).collect()
    }

    fn ends(actions: &[f32]) -> Vec<usize> {
        (0..actions.len() / 8).map(|k| stage_end(actions, k)).collect()
    }

    #[test]
    fn a_stage_ends_where_the_arm_arrives_coming_down_and_leaves_going_up() {
        // The experts' keyframe heights (held-out episodes of each task).
        // push_buttons, two buttons: above, press, above, press, up: each press ends its stage
        assert_eq!(ends(&heights(&[0.84, 0.78, 0.84, 0.78, 0.86])), [1, 1, 3, 3, 4]);
        // slide_block: above, down beside the block, the push (level), up: the push's end
        assert_eq!(ends(&heights(&[0.87, 0.77, 0.77, 0.87])), [2, 2, 2, 3]);
        // open_drawer: above, down on the handle, the pull (level): never up, the last keyframe
        assert_eq!(ends(&heights(&[0.99, 0.91, 0.91])), [2, 2, 2]);
        // close_jar: above the lid, grasp, lift, above the jar (higher still), place, up: the
        // lift and the carry are one way up, not the end of a stage
        assert_eq!(ends(&heights(&[0.88, 0.76, 0.88, 0.97, 0.85, 0.97])), [1, 1, 4, 4, 4, 5]);
        // stack_blocks: pick (above, grasp, lift), place (above, down, up), pick again; the
        // place's approach is 1 cm above the lift, under STAGE_RISE_M
        assert_eq!(
            ends(&heights(&[0.89, 0.77, 0.89, 0.90, 0.78, 0.90, 0.89, 0.77, 0.89])),
            [1, 1, 4, 4, 4, 7, 7, 7, 8]
        );
    }

    #[test]
    fn detours_repeat_their_action_and_do_not_end_a_stage() {
        // push_buttons with a detour before each approach: the detour's sample has the press
        // as its action, like the sample after it
        let mut a = heights(&[0.84, 0.78, 0.78, 0.84, 0.78, 0.78, 0.86]);
        // samples 1 and 2 are the same press (the detour's action repeats it); so are 4 and 5
        a.copy_within(8..16, 16);
        a.copy_within(32..40, 40);
        assert!(is_detour(&a, 1) && is_detour(&a, 4));
        assert_eq!(ends(&a), [2, 2, 2, 5, 5, 5, 6]);
        // one sample, or none: the last (or 0)
        assert_eq!(ends(&heights(&[0.8])), [0]);
        assert_eq!(stage_end(&[], 0), 0);
    }
}
