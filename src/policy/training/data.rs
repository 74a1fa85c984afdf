//! Training data: demonstrations grouped by task and variation, drawn uniformly (or by
//! `train.task_weights`) over tasks, then uniformly over variations, then episodes, then
//! keyframes (as the release samples), with each keyframe's
//! observation prepared (lifted, sampled) once and kept.
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

use rand::Rng;

use crate::data::Episode;
use crate::policy::config::PolicyConfig;
use crate::policy::error::{PolicyError, Result};
use crate::policy::inputs::{PreparedObservation, prepare};
use crate::policy::network::text_encoder::TextEncoder;
use crate::policy::scene::observation::Observation;

/// One training sample: keyframe `k` of episode `episode`.
#[derive(Debug, Clone, Copy)]
pub(super) struct SampleRef {
    pub(super) episode: usize,
    pub(super) k: usize,
}

/// The episodes read from dataset folders, and the episode files that could not be read.
pub struct DatasetEpisodes {
    pub episodes: Vec<Episode>,
    /// Episode files skipped, with the reason.
    pub skipped: Vec<(PathBuf, String)>,
}

/// Demonstrations grouped by task and variation, with observations prepared lazily (and kept).
pub struct TrainingData {
    episodes: Vec<Episode>,
    /// task -> variation -> episode indices.
    groups: BTreeMap<String, BTreeMap<usize, Vec<usize>>>,
    prepared: Vec<Vec<Option<Arc<PreparedObservation>>>>,
}

impl TrainingData {
    /// Reads the episodes of dataset folders for [`TrainingData::from_episodes`]. Episode files
    /// that fail to load are skipped and listed in [`DatasetEpisodes::skipped`] (for the caller
    /// to report before the episodes are checked).
    pub fn read_datasets(dirs: &[PathBuf]) -> Result<DatasetEpisodes> {
        let mut read = DatasetEpisodes { episodes: Vec::new(), skipped: Vec::new() };
        for dir in dirs {
            let loaded = crate::data::load_dataset(dir)
                .map_err(|e| PolicyError::File { path: dir.clone(), message: e.to_string() })?;
            read.skipped.extend(loaded.failures.into_iter().map(|(path, e)| (path, e.to_string())));
            read.episodes.extend(loaded.episodes);
        }
        Ok(read)
    }

    pub fn from_episodes(episodes: Vec<Episode>) -> Result<Self> {
        let episodes: Vec<Episode> = episodes.into_iter().filter(|e| e.success && e.keyframes() > 0).collect();
        if episodes.is_empty() {
            return Err(PolicyError::Invalid(
                "no successful episode with keyframes to train on: collect some with `flowram collect`".into(),
            ));
        }
        let cameras = &episodes[0].cameras;
        let mut groups: BTreeMap<String, BTreeMap<usize, Vec<usize>>> = BTreeMap::new();
        for (i, e) in episodes.iter().enumerate() {
            if &e.cameras != cameras || e.height != episodes[0].height {
                return Err(PolicyError::Invalid(format!(
                    "datasets disagree on cameras or image size ({:?} {}px vs {:?} {}px): train on datasets collected alike",
                    e.cameras, e.height, cameras, episodes[0].height
                )));
            }
            groups.entry(e.task.clone()).or_default().entry(e.variation).or_default().push(i);
        }
        let prepared = episodes.iter().map(|e| vec![None; e.keyframes()]).collect();
        Ok(Self { episodes, groups, prepared })
    }

    pub fn episodes(&self) -> &[Episode] {
        &self.episodes
    }

    /// Keyframe samples in all.
    pub fn samples(&self) -> usize {
        self.episodes.iter().map(Episode::keyframes).sum()
    }

    /// Checks `train.task_weights` against the data: every task it names must be one the data
    /// holds (a misspelt name would silently weigh nothing).
    pub fn check_task_weights(&self, weights: &BTreeMap<String, f64>) -> Result<()> {
        match weights.keys().find(|t| !self.groups.contains_key(*t)) {
            None => Ok(()),
            Some(task) => Err(PolicyError::Invalid(format!(
                "train.task_weights names {task}, but the training data holds only {:?}: weigh tasks of the datasets \
                 given to --data",
                self.groups.keys().collect::<Vec<_>>()
            ))),
        }
    }

    /// A task (uniformly, or by `weights`: `train.task_weights`, a task not named weighing 1),
    /// then a variation of it uniformly, an episode of that, a keyframe. Without weights the
    /// draws are those of every run before the option.
    pub(super) fn draw(&self, rng: &mut impl Rng, weights: &BTreeMap<String, f64>) -> SampleRef {
        let tasks: Vec<&BTreeMap<usize, Vec<usize>>> = self.groups.values().collect();
        let task = if weights.is_empty() {
            rng.random_range(0..tasks.len())
        } else {
            let w: Vec<f64> = self.groups.keys().map(|t| weights.get(t).copied().unwrap_or(1.0)).collect();
            let mut u = rng.random_range(0.0..w.iter().sum::<f64>());
            w.iter()
                .position(|&wi| {
                    u -= wi;
                    u < 0.0
                })
                .unwrap_or(w.len() - 1)
        };
        let variations = tasks[task];
        let episodes: Vec<&Vec<usize>> = variations.values().collect();
        let of_variation = episodes[rng.random_range(0..episodes.len())];
        let episode = of_variation[rng.random_range(0..of_variation.len())];
        SampleRef { episode, k: rng.random_range(0..self.episodes[episode].keyframes()) }
    }

    pub(super) fn prepared(
        &mut self,
        s: SampleRef,
        config: &PolicyConfig,
        text: &mut TextEncoder,
    ) -> Result<Arc<PreparedObservation>> {
        if let Some(p) = &self.prepared[s.episode][s.k] {
            return Ok(p.clone());
        }
        let observation = Observation::from_episode(&self.episodes[s.episode], s.k)?;
        let p = Arc::new(prepare(&observation, config, text)?);
        self.prepared[s.episode][s.k] = Some(p.clone());
        Ok(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// An episode of `task` with `keyframes` keyframes and no pixels (drawing reads only the
    /// grouping and the keyframe count).
    fn episode(task: &str, variation: usize, keyframes: usize) -> Episode {
        Episode {
            task: task.into(),
            variation,
            instruction: String::new(),
            seed: 0,
            cameras: vec!["front".into()],
            success: true,
            height: 1,
            width: 1,
            rgb: Vec::new(),
            depth: Vec::new(),
            intrinsics: Vec::new(),
            extrinsics: Vec::new(),
            proprio: vec![0.0; 8 * keyframes],
            action: vec![0.0; 8 * keyframes],
        }
    }

    fn data() -> TrainingData {
        TrainingData::from_episodes(vec![
            episode("a", 0, 2),
            episode("b", 0, 3),
            episode("b", 1, 1),
            episode("c", 0, 4),
        ])
        .unwrap()
    }

    fn task_counts(data: &TrainingData, weights: &BTreeMap<String, f64>, draws: usize) -> BTreeMap<String, usize> {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let mut counts = BTreeMap::new();
        for _ in 0..draws {
            let s = data.draw(&mut rng, weights);
            *counts.entry(data.episodes()[s.episode].task.clone()).or_insert(0) += 1;
        }
        counts
    }

    #[test]
    fn task_weights_draw_tasks_in_proportion_and_no_weights_draw_as_before() {
        let data = data();
        let draws = 30_000;
        let uniform = task_counts(&data, &BTreeMap::new(), draws);
        for n in uniform.values() {
            assert!((*n as f64 / draws as f64 - 1.0 / 3.0).abs() < 0.015, "{uniform:?}");
        }
        // "b" three times as often as each of the others (a task not named weighs 1).
        let weighted = task_counts(&data, &BTreeMap::from([("b".to_string(), 3.0)]), draws);
        assert!((weighted["b"] as f64 / draws as f64 - 0.6).abs() < 0.015, "{weighted:?}");
        assert!((weighted["a"] as f64 / draws as f64 - 0.2).abs() < 0.015, "{weighted:?}");
        assert!((weighted["c"] as f64 / draws as f64 - 0.2).abs() < 0.015, "{weighted:?}");
        // Without weights the draws are exactly those before the option: task, variation,
        // episode, keyframe from the same generator in the same order.
        let (mut r1, mut r2) = (rand::rngs::StdRng::seed_from_u64(3), rand::rngs::StdRng::seed_from_u64(3));
        for _ in 0..100 {
            let s = data.draw(&mut r1, &BTreeMap::new());
            let tasks: Vec<&BTreeMap<usize, Vec<usize>>> = data.groups.values().collect();
            let variations = tasks[r2.random_range(0..tasks.len())];
            let episodes: Vec<&Vec<usize>> = variations.values().collect();
            let of_variation = episodes[r2.random_range(0..episodes.len())];
            let episode = of_variation[r2.random_range(0..of_variation.len())];
            let k = r2.random_range(0..data.episodes[episode].keyframes());
            assert_eq!((s.episode, s.k), (episode, k));
        }
    }

    #[test]
    fn task_weights_must_be_finite_and_positive() {
        let mut config = PolicyConfig::cpu_default().unwrap();
        for w in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            config.train.task_weights = BTreeMap::from([("slide_block".to_string(), w)]);
            let message = config.validate().unwrap_err().to_string();
            assert!(message.contains("train.task_weights.slide_block") && message.contains("above 0"), "{message}");
        }
        config.train.task_weights = BTreeMap::from([("slide_block".to_string(), 3.0)]);
        config.validate().unwrap();
    }

    #[test]
    fn task_weights_must_name_tasks_of_the_data() {
        let data = data();
        assert!(data.check_task_weights(&BTreeMap::from([("b".to_string(), 2.0)])).is_ok());
        let err = data.check_task_weights(&BTreeMap::from([("slide_blok".to_string(), 2.0)])).unwrap_err().to_string();
        assert!(err.contains("train.task_weights names slide_blok") && err.contains("[\"a\", \"b\", \"c\"]"), "{err}");
    }
}
