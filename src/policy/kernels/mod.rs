//! CPU kernels behind the network's custom candle ops, each with its backward pass:
//! - [`selective_scan`]: Mamba's selective scan (S6), with a stateful forward for inference;
//! - [`mamba_ops`]: the fused element-wise ops of a Mamba block (AdaLN-RMSNorm, causal
//!   convolution + SiLU, SiLU gate, gated residual);
//! - [`conv_ops`]: the image encoder's im2col/col2im, LayerNorm + SiLU, upsample-add;
//! - [`simd`]: what the scan and the Mamba ops share: branch-free math written for
//!   auto-vectorisation, run-time AVX-512 / AVX2 dispatch, typed access to candle's CPU storage.
pub mod conv_ops;
pub mod mamba_ops;
pub mod selective_scan;
pub mod simd;
