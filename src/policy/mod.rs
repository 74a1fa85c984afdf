//! The FlowRAM policy (CVPR 2025): observation (RGB-D cameras, proprioception, instruction) in,
//! next keyframe (position, rotation, gripper open) out. Knows nothing of MuJoCo or control.
//!
//! - `observation`, `inputs`: what the policy sees, lifted to workspace points and batched;
//! - `image_encoder`, `text`: per-pixel image features (trained from scratch), the frozen
//!   MiniLM instruction encoder;
//! - `geometry`: rotations (6D), lifting, farthest point sampling, the Dynamic Radius Schedule;
//!   `serialization`: the order of point tokens in the scan;
//! - `scan` (+ `cpu_kernels`, `mamba_ops`), `mamba`: the selective-scan kernel and the
//!   region-aware Mamba blocks;
//! - `model`: the network (token order, conditioning, heads); `flow`: conditional flow matching;
//! - `train` (+ `optim`, `checkpoint`, `metrics`), `inference`: training and sampling;
//! - `config`: hyper-parameters (`models/policy/*.toml`); `runtime`: process-wide thread-pool
//!   and allocator settings applied first thing in `main`.
pub mod checkpoint;
pub mod config;
pub mod conv_kernels;
pub mod cpu_kernels;
pub mod error;
pub mod flow;
pub mod geometry;
pub mod image_encoder;
pub mod inference;
pub mod init;
pub mod inputs;
pub mod mamba;
pub mod mamba_ops;
pub mod metrics;
pub mod model;
pub mod observation;
pub mod optim;
pub mod runtime;
pub mod scan;
pub mod serialization;
pub mod text;
pub mod train;

pub use error::{PolicyError, Result};
