//! Training data: demonstrations grouped by task and variation, drawn uniformly over tasks, then
//! variations, then episodes, then keyframes (as the release samples), with each keyframe's
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

    /// A task uniformly, then a variation of it uniformly, an episode of that, a keyframe.
    pub(super) fn draw(&self, rng: &mut impl Rng) -> SampleRef {
        let tasks: Vec<&BTreeMap<usize, Vec<usize>>> = self.groups.values().collect();
        let variations = tasks[rng.random_range(0..tasks.len())];
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
