//! The FlowRAM policy (CVPR 2025): observation (RGB-D cameras, proprioception, instruction) in,
//! next keyframe (position, rotation, gripper open) out. Knows nothing of MuJoCo, control or
//! tasks.
//!
//! - [`scene`] (no candle): the observation, rotations, lifting depth to points, the workspace
//!   normalisation, farthest point sampling, the Dynamic Radius Schedule, the token order;
//! - [`network`] (candle modules): the FlowRAM network, region-aware Mamba, image and text
//!   encoders, positional and time encodings, initialisation;
//! - [`kernels`]: CPU kernels behind the network's custom ops (selective scan, Mamba
//!   element-wise ops, convolutions) and their SIMD plumbing;
//! - [`training`]: the trainer, data sampling, AdamW, LR schedule, EMA, metrics, loss plot,
//!   the training RNG;
//! - [`config`] (`models/policy/*.toml`), [`error`], [`runtime`] (process-wide thread-pool and
//!   allocator settings applied first thing in `main`), [`inputs`] (observations batched into
//!   the network's inputs), [`flow`] (conditional flow matching), [`checkpoint`] (files of a
//!   run), [`inference`] (a trained policy: observation to keyframes).
pub mod checkpoint;
pub mod config;
pub mod error;
pub mod flow;
pub mod inference;
pub mod inputs;
pub mod kernels;
pub mod network;
pub mod runtime;
pub mod scene;
pub mod training;

pub use error::{PolicyError, Result};
