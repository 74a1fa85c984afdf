//! Training FlowRAM: the trainer (Algorithm 1, checkpoints, exact resume), training data
//! sampling, AdamW, the learning-rate schedule, the EMA of the weights, `metrics.csv` and the
//! loss plot, and the training RNG (pure in seed and step).
pub mod adamw;
pub mod checkpointing;
pub mod data;
pub mod ema;
pub mod loss_plot;
pub mod lr_schedule;
pub mod metrics;
mod named_state;
pub mod rng;
#[cfg(test)]
pub(crate) mod test_support;
pub mod trainer;
