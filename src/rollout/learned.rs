//! A trained FlowRAM checkpoint as an episode's actor ([`KeyframePolicy`]): the observer's RGB-D
//! frames, the proprioception and the instruction in, the first sampled keyframe out.
use std::time::Instant;

use super::RolloutError;
use super::episode::{KeyframeObservation, KeyframePolicy};
use crate::control::keyframe::Keyframe;
use crate::policy::inference::{Policy, SamplingOptions};
use crate::policy::scene::observation::{CameraView, Observation};

/// The cameras the policies here are trained with, in the datasets' order.
pub const DEFAULT_CAMERAS: [&str; 4] = ["front", "left_shoulder", "right_shoulder", "wrist"];

/// A trained policy acting in lock-step with the simulation.
pub struct FlowRamActor {
    pub policy: Policy,
    /// Euler steps, samples (their consensus is executed), DRS; `seed` is the noise seed of an
    /// episode's first keyframe, keyframe k uses `seed + k` (an episode is the same whether run
    /// alone or as one of many).
    pub options: SamplingOptions,
    /// Wall-clock milliseconds of each prediction, observation to keyframe.
    pub inference_ms: Vec<f64>,
    /// The proprioception of the episode's observations so far, most recent first (the policy's
    /// `observation.proprio_history`); an episode's keyframe 0 starts it afresh.
    history: Vec<[f32; 8]>,
}

impl FlowRamActor {
    pub fn new(policy: Policy, options: SamplingOptions) -> Self {
        Self { policy, options, inference_ms: Vec::new(), history: Vec::new() }
    }

    /// The proprioception of the current episode's observations so far, most recent first.
    pub fn history(&self) -> &[[f32; 8]] {
        &self.history
    }
}

impl KeyframePolicy for FlowRamActor {
    fn next_keyframe(
        &mut self,
        instruction: &str,
        k: usize,
        observation: &KeyframeObservation,
    ) -> Result<Keyframe, RolloutError> {
        if k == 0 {
            self.history.clear();
        }
        let observation = policy_observation(instruction, k, observation, &self.history)?;
        self.history.insert(0, observation.proprio);
        self.history.truncate(crate::policy::config::MAX_PROPRIO_HISTORY);
        let options = SamplingOptions { seed: self.options.seed + k as u64, ..self.options };
        let start = Instant::now();
        let pose = self.policy.predict_keyframe(&observation, &options)?;
        self.inference_ms.push(start.elapsed().as_secs_f64() * 1e3);
        Ok(Keyframe {
            position: pose.position.map(f64::from),
            quat_wxyz: pose.quat_wxyz.map(f64::from),
            gripper_open: pose.gripper_open,
        })
    }
}

/// The policy's view of a keyframe observation (square frames of one size, in the observer's
/// camera order) taken after `keyframe` keyframes of the episode, whose earlier observations'
/// proprioception was `history` (most recent first).
pub fn policy_observation(
    instruction: &str,
    keyframe: usize,
    observation: &KeyframeObservation,
    history: &[[f32; 8]],
) -> Result<Observation, RolloutError> {
    let first = observation.frames.first().ok_or(RolloutError::NoCameras)?;
    let size = first.intrinsics.width;
    let mut cameras = Vec::with_capacity(observation.frames.len());
    for frame in &observation.frames {
        if frame.intrinsics.width != size || frame.intrinsics.height != size {
            return Err(RolloutError::FrameSize {
                camera: frame.camera.clone(),
                width: frame.intrinsics.width,
                height: frame.intrinsics.height,
                size,
            });
        }
        let k = frame.intrinsics.matrix();
        let e = frame.extrinsics.to_homogeneous();
        cameras.push(CameraView {
            name: frame.camera.clone(),
            rgb: frame.rgb.clone(),
            depth: frame.depth.clone(),
            intrinsics: std::array::from_fn(|r| std::array::from_fn(|c| k[(r, c)] as f32)),
            camera_to_world: std::array::from_fn(|r| std::array::from_fn(|c| e[(r, c)] as f32)),
        });
    }
    Ok(Observation {
        size,
        cameras,
        proprio: observation.proprio,
        instruction: instruction.to_string(),
        keyframe,
        history: history.to_vec(),
    })
}
