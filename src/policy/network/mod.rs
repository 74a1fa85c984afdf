//! The FlowRAM network as candle modules (`new(cfg, vb)` + `forward`, weights named by their
//! `VarBuilder` path): the model (token layout, conditioning, heads), the region-aware Mamba
//! stack, the image encoder (trained from scratch), the frozen MiniLM text encoder, positional
//! and time encodings, and the seeded initialisation.
pub mod encoding;
pub mod image_encoder;
pub mod init;
pub mod mamba;
pub mod model;
pub mod text_encoder;
