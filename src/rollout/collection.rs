//! Expert demonstrations: episodes of a task's expert observed by cameras at every keyframe,
//! kept when they succeed, appended to a dataset (`crate::data`, format in the README).
use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use super::RolloutError;
use super::episode::{Actor, Observer, camera_rig, run_episode};
use crate::data::{Dataset, Episode};
use crate::sim::Visuals;
use crate::tasks::{self, Task};

/// What [`collect`] did.
#[derive(Debug, Clone, Serialize)]
pub struct CollectReport {
    pub task: String,
    /// Episodes in the dataset now (earlier ones included).
    pub episodes: usize,
    pub attempts: usize,
    pub successes: usize,
    pub keyframes_mean: f64,
    pub seconds: f64,
    pub episodes_per_minute: f64,
}

/// Progress of a collection, for a progress bar.
pub trait CollectProgress {
    /// A successful episode was saved.
    fn saved(&mut self, successes: usize);
    /// The expert failed on `seed` (the episode is not saved).
    fn failed(&mut self, seed: u64, reached: usize, keyframes: usize);
}

/// How [`collect`] runs.
#[derive(Debug, Clone)]
pub struct CollectOptions {
    /// Successful episodes to collect.
    pub episodes: usize,
    /// Seed of the first attempt; attempt i uses seed + i (variation = seed modulo variations).
    pub seed: u64,
    /// Give up after this many attempts.
    pub max_attempts: usize,
    /// Cameras to record, in order.
    pub cameras: Vec<String>,
    /// Image size (square, pixels).
    pub size: usize,
}

/// Runs the expert of `task` until `options.episodes` episodes succeeded (or the attempts run
/// out) and appends the successful ones to the dataset at `out` (created, or extended if it
/// holds the same task, cameras and size). Nothing is written before the cameras are checked.
pub fn collect(
    task: &dyn Task,
    out: &Path,
    options: &CollectOptions,
    progress: &mut dyn CollectProgress,
) -> Result<CollectReport, RolloutError> {
    if options.episodes == 0 {
        return Err(RolloutError::Zero { what: "the episodes to collect" });
    }
    let mut world = tasks::load_world(task)?;
    let (mut rig, cameras) = camera_rig(&world, options.size, Visuals::Full, &options.cameras)?;
    let mut writer = Dataset::create_or_open(out, task.name(), &options.cameras, [options.size, options.size])?;
    let start = Instant::now();
    let (mut attempts, mut successes, mut keyframes) = (0usize, 0usize, 0usize);
    while successes < options.episodes && attempts < options.max_attempts {
        let seed = options.seed + attempts as u64;
        attempts += 1;
        let variation = seed as usize % task.variation_count();
        let mut observer = Observer { rig: &mut rig, cameras: cameras.clone() };
        let result = run_episode(task, &mut world, variation, seed, Actor::Expert, Some(&mut observer))?;
        if !result.success {
            progress.failed(seed, result.reached, result.keyframes);
            continue;
        }
        let episode = result.to_dataset_episode().ok_or(RolloutError::NoImages)?;
        writer.append(&episode)?;
        successes += 1;
        keyframes += result.keyframes;
        progress.saved(successes);
    }
    let seconds = start.elapsed().as_secs_f64();
    Ok(CollectReport {
        task: task.name().into(),
        episodes: writer.index().episodes.len(),
        attempts,
        successes,
        keyframes_mean: if successes > 0 { keyframes as f64 / successes as f64 } else { 0.0 },
        seconds,
        episodes_per_minute: successes as f64 / seconds * 60.0,
    })
}

/// One expert demonstration of `task` (variation, seed) seen by `cameras` at `size` pixels with
/// the arm drawn as `visuals`, as a dataset episode (what benchmarks and tests train and predict
/// on; its `success` says whether the expert succeeded).
pub fn demonstration(
    task: &dyn Task,
    variation: usize,
    seed: u64,
    cameras: &[&str],
    size: usize,
    visuals: Visuals,
) -> Result<Episode, RolloutError> {
    let mut world = tasks::load_world(task)?;
    let (mut rig, cameras) = camera_rig(&world, size, visuals, cameras)?;
    let mut observer = Observer { rig: &mut rig, cameras };
    let result = run_episode(task, &mut world, variation, seed, Actor::Expert, Some(&mut observer))?;
    result.to_dataset_episode().ok_or(RolloutError::NoImages)
}
