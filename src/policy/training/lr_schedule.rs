//! The learning-rate schedule: linear warm-up, then cosine decay.
use serde::{Deserialize, Serialize};

use crate::policy::config::TrainConfig;

/// Linear warm-up then cosine decay of the learning rate, a pure function of
/// the step (so a resumed run gets the same rate).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LearningRateSchedule {
    /// Peak learning rate (1e-4 in the paper).
    pub base: f64,
    /// Steps of linear warm-up from 0 to `base` (0 = none).
    pub warmup_steps: u64,
    /// Step at which the cosine reaches `min`; `None` keeps `base` after warm-up.
    pub decay_until: Option<u64>,
    /// Final learning rate of the cosine.
    pub min: f64,
}

impl LearningRateSchedule {
    /// The schedule of a training config: warm-up, then constant or cosine to the last step.
    pub fn of(train: &TrainConfig) -> Self {
        Self {
            base: train.learning_rate,
            warmup_steps: train.warmup_steps as u64,
            decay_until: train.cosine_decay.then_some(train.steps as u64),
            min: train.min_learning_rate,
        }
    }

    /// A constant rate.
    pub fn constant(base: f64) -> Self {
        Self { base, warmup_steps: 0, decay_until: None, min: base }
    }

    /// The rate for optimiser step `step` (1-based: the first step is 1).
    pub fn at(&self, step: u64) -> f64 {
        if self.warmup_steps > 0 && step <= self.warmup_steps {
            return self.base * step as f64 / self.warmup_steps as f64;
        }
        match self.decay_until {
            Some(end) if end > self.warmup_steps => {
                let progress = ((step - self.warmup_steps) as f64 / (end - self.warmup_steps) as f64).min(1.0);
                self.min + 0.5 * (self.base - self.min) * (1.0 + (std::f64::consts::PI * progress).cos())
            }
            _ => self.base,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedule_warms_up_then_decays() {
        let s = LearningRateSchedule { base: 1e-4, warmup_steps: 10, decay_until: Some(110), min: 1e-5 };
        assert!((s.at(5) - 5e-5).abs() < 1e-15);
        assert!((s.at(10) - 1e-4).abs() < 1e-15);
        assert!((s.at(60) - 5.5e-5).abs() < 1e-12);
        assert!((s.at(500) - 1e-5).abs() < 1e-15);
        assert_eq!(LearningRateSchedule::constant(1e-4).at(123), 1e-4);
    }
}
