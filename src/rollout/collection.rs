//! Expert demonstrations: episodes of a task's expert observed by cameras at every keyframe,
//! kept when they succeed, appended to a dataset (`crate::data`, format in the README), with a
//! manifest of every attempt so that a collection can be split into shards, resumed and merged
//! (`super::shard`, `docs/scale-out.md`).
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::RolloutError;
use super::episode::{Actor, Observer, Perturbation, camera_rig, run_episode};
use super::shard::{Shard, check_shard_set, source_revision};
use crate::data::{DataError, Dataset, Episode};
use crate::files::write_atomic;
use crate::sim::Visuals;
use crate::tasks::{self, Task};

/// Name of the collection manifest inside a dataset folder.
pub const MANIFEST_FILE: &str = "manifest.json";
/// Value of the manifest's `format` field.
pub const MANIFEST_FORMAT: &str = "flowram-collection-v1";

/// What [`collect`] did.
#[derive(Debug, Clone, Serialize)]
pub struct CollectReport {
    pub task: String,
    pub shard: Shard,
    /// Episodes in the dataset now (those of earlier, interrupted runs included).
    pub episodes: usize,
    /// Episode slots this shard owns.
    pub owned: usize,
    /// Owned slots already done by an earlier run into the same folder (a resumed shard).
    pub resumed: usize,
    /// Expert attempts made by this run.
    pub attempts: usize,
    /// Successful episodes saved by this run.
    pub successes: usize,
    /// Owned slots whose every attempt failed (left empty).
    pub given_up: usize,
    pub keyframes_mean: f64,
    pub seconds: f64,
    pub episodes_per_minute: f64,
}

/// Progress of a collection, for a progress bar.
pub trait CollectProgress {
    /// A successful episode was saved (or found done); `done` owned slots are finished.
    fn saved(&mut self, done: usize);
    /// The expert failed on `seed` (the episode is not saved).
    fn failed(&mut self, seed: u64, reached: usize, keyframes: usize);
}

/// How [`collect`] runs.
#[derive(Debug, Clone)]
pub struct CollectOptions {
    /// Episode slots: the dataset gets one successful episode per slot.
    pub episodes: usize,
    /// Base seed: slot k's attempt r uses seed `seed + k + r * episodes` ([`attempt_seed`]).
    pub seed: u64,
    /// Attempts per slot before it is given up (the experts succeed 92-100 %).
    pub attempts_per_episode: usize,
    /// Cameras to record, in order.
    pub cameras: Vec<String>,
    /// Image size (square, pixels).
    pub size: usize,
    /// The slots this process collects (`Shard::WHOLE`: all).
    pub shard: Shard,
    /// Recovery samples (detours before approach keyframes); `None`: the plain expert.
    pub perturbation: Option<Perturbation>,
}

/// The seed of attempt `attempt` (0-based) of episode slot `slot`: `seed + slot + attempt *
/// episodes`. Every slot's seeds are its own, so a slot's outcome does not depend on the others
/// and any split of the slots over shards collects the same episodes. The variation of an
/// attempt is its seed modulo the task's variations.
pub fn attempt_seed(seed: u64, episodes: usize, slot: usize, attempt: usize) -> u64 {
    seed + slot as u64 + (attempt * episodes) as u64
}

/// One expert attempt, as the manifest records it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Attempt {
    /// The episode slot.
    pub episode: usize,
    pub seed: u64,
    pub success: bool,
}

/// `manifest.json` of a collected dataset folder: the request that made it, the shard, the
/// source revision, and every attempt (so a re-run skips what is done, failures included).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CollectionManifest {
    pub format: String,
    /// `git describe` of the source tree that collected it (see [`source_revision`]); a merge of
    /// several lists them all, comma-separated.
    pub revision: String,
    pub task: String,
    /// The task's [`Task::expert_version`] when collected (absent in older manifests: 1).
    #[serde(default = "first_expert_version")]
    pub expert_version: u32,
    pub cameras: Vec<String>,
    pub image_size: usize,
    pub seed: u64,
    pub episodes: usize,
    pub attempts_per_episode: usize,
    pub shard: Shard,
    /// The recovery samples' perturbation (absent: the plain expert; older manifests).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub perturbation: Option<Perturbation>,
    /// In the order made (slot order).
    pub attempts: Vec<Attempt>,
}

fn first_expert_version() -> u32 {
    1
}

impl CollectionManifest {
    fn new(task: &dyn Task, options: &CollectOptions) -> Self {
        Self {
            format: MANIFEST_FORMAT.into(),
            revision: source_revision(),
            task: task.name().into(),
            expert_version: task.expert_version(),
            cameras: options.cameras.clone(),
            image_size: options.size,
            seed: options.seed,
            episodes: options.episodes,
            attempts_per_episode: options.attempts_per_episode,
            shard: options.shard,
            perturbation: options.perturbation,
            attempts: Vec::new(),
        }
    }

    /// The request as a sentence, for error messages.
    fn request(&self) -> String {
        let perturbation = match self.perturbation {
            Some(p) => format!(
                " --perturb-sigma {} --perturb-probability {} --perturb-target {} --perturb-grasp-probability {} --perturb-detours {} --perturb-yaw-deg {}",
                p.sigma_m,
                p.probability,
                p.target.name(),
                p.grasp_probability,
                p.detours,
                p.yaw_sigma_deg
            ),
            None => String::new(),
        };
        format!(
            "--task {} --episodes {} --seed {} --cameras {} --size {} --attempts-per-episode {} --shard-index {} --shard-count {}{perturbation} (expert version {})",
            self.task,
            self.episodes,
            self.seed,
            self.cameras.join(","),
            self.image_size,
            self.attempts_per_episode,
            self.shard.index,
            self.shard.count,
            self.expert_version
        )
    }

    fn same_request(&self, other: &Self) -> bool {
        (
            &self.task,
            self.expert_version,
            &self.cameras,
            self.image_size,
            self.seed,
            self.episodes,
            self.attempts_per_episode,
            self.shard,
        ) == (
            &other.task,
            other.expert_version,
            &other.cameras,
            other.image_size,
            other.seed,
            other.episodes,
            other.attempts_per_episode,
            other.shard,
        ) && self.perturbation == other.perturbation
    }

    /// Whether slot `k` has its episode.
    fn done(&self, k: usize) -> bool {
        self.attempts.iter().any(|a| a.episode == k && a.success)
    }

    /// Attempts made for slot `k`.
    fn tried(&self, k: usize) -> usize {
        self.attempts.iter().filter(|a| a.episode == k).count()
    }

    /// Whether every owned slot is done or given up.
    pub fn complete(&self) -> bool {
        self.shard.items(self.episodes).all(|k| self.done(k) || self.tried(k) >= self.attempts_per_episode)
    }

    /// The manifest of `dir`, `None` when it has none.
    pub fn read(dir: &Path) -> Result<Option<Self>, RolloutError> {
        let path = dir.join(MANIFEST_FILE);
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read(&path).map_err(|source| DataError::Read { path: path.clone(), source })?;
        let manifest: Self = serde_json::from_slice(&text)
            .map_err(|e| RolloutError::Manifest { path: path.clone(), problem: e.to_string() })?;
        if manifest.format != MANIFEST_FORMAT {
            return Err(RolloutError::Manifest {
                path,
                problem: format!("format is {:?}, expected {MANIFEST_FORMAT:?}", manifest.format),
            });
        }
        Ok(Some(manifest))
    }

    fn write(&self, dir: &Path) -> Result<(), RolloutError> {
        let path = dir.join(MANIFEST_FILE);
        let json = serde_json::to_vec_pretty(self)
            .map_err(|e| RolloutError::Manifest { path: path.clone(), problem: e.to_string() })?;
        write_atomic(&path, &json).map_err(|source| DataError::Write { path, source })?;
        Ok(())
    }
}

/// Runs the expert of `task` on the episode slots `options.shard` owns, until each has a
/// successful episode or `attempts_per_episode` failures, appending the successes to the dataset
/// at `out` in slot order, with `manifest.json` beside its index. A folder that already holds
/// this very collection (same request and shard) is resumed: slots done or given up are
/// skipped, so a killed shard re-run neither repeats nor misses a seed. Nothing is written
/// before the cameras and the folder are checked.
pub fn collect(
    task: &dyn Task,
    out: &Path,
    options: &CollectOptions,
    progress: &mut dyn CollectProgress,
) -> Result<CollectReport, RolloutError> {
    if options.episodes == 0 {
        return Err(RolloutError::Zero { what: "the episodes to collect" });
    }
    if options.attempts_per_episode == 0 {
        return Err(RolloutError::Zero { what: "the attempts per episode" });
    }
    if let Some(p) = &options.perturbation {
        p.validate_for(task).map_err(|problem| RolloutError::Perturbation { problem })?;
    }
    let actor = || match options.perturbation {
        Some(p) => Actor::PerturbedExpert(p),
        None => Actor::Expert,
    };
    let mut world = tasks::load_world(task)?;
    let (mut rig, cameras) = camera_rig(&world, options.size, Visuals::Full, &options.cameras)?;
    let mut manifest = CollectionManifest::new(task, options);
    match CollectionManifest::read(out)? {
        Some(found) if found.same_request(&manifest) => manifest.attempts = found.attempts,
        Some(found) => {
            return Err(RolloutError::OtherRun {
                dir: out.to_path_buf(),
                found: found.request(),
                asked: manifest.request(),
            });
        }
        None => {
            if out.join(crate::data::INDEX_FILE).exists() && !crate::data::read_index(out)?.episodes.is_empty() {
                return Err(RolloutError::OtherRun {
                    dir: out.to_path_buf(),
                    found: "episodes but no manifest.json (an older flowram, or written by hand)".into(),
                    asked: manifest.request(),
                });
            }
        }
    }
    let mut writer = Dataset::create_or_open(out, task.name(), &options.cameras, [options.size, options.size])?;
    // An episode listed by the index but not the manifest: the run was killed between the two
    // writes. It is done.
    for entry in &writer.index().episodes {
        if !manifest.attempts.iter().any(|a| a.seed == entry.seed && a.success) {
            let slot = (entry.seed.wrapping_sub(options.seed) % options.episodes as u64) as usize;
            manifest.attempts.push(Attempt { episode: slot, seed: entry.seed, success: true });
        }
    }
    manifest.write(out)?;
    let start = Instant::now();
    let owned = options.shard.items(options.episodes).count();
    let (mut attempts, mut successes, mut keyframes, mut given_up, mut done) = (0, 0, 0, 0, 0);
    let resumed = options.shard.items(options.episodes).filter(|&k| manifest.done(k)).count();
    for k in options.shard.items(options.episodes) {
        if manifest.done(k) {
            done += 1;
            progress.saved(done);
            continue;
        }
        for r in manifest.tried(k)..options.attempts_per_episode {
            let seed = attempt_seed(options.seed, options.episodes, k, r);
            let variation = seed as usize % task.variation_count();
            let mut observer = Observer { rig: &mut rig, cameras: cameras.clone() };
            let result = run_episode(task, &mut world, variation, seed, actor(), Some(&mut observer))?;
            attempts += 1;
            if result.success {
                let episode = result.to_dataset_episode().ok_or(RolloutError::NoImages)?;
                writer.append(&episode)?;
                manifest.attempts.push(Attempt { episode: k, seed, success: true });
                manifest.write(out)?;
                successes += 1;
                keyframes += result.keyframes;
                break;
            }
            manifest.attempts.push(Attempt { episode: k, seed, success: false });
            manifest.write(out)?;
            progress.failed(seed, result.reached, result.keyframes);
        }
        if manifest.done(k) {
            done += 1;
            progress.saved(done);
        } else {
            given_up += 1;
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    Ok(CollectReport {
        task: task.name().into(),
        shard: options.shard,
        episodes: writer.index().episodes.len(),
        owned,
        resumed,
        attempts,
        successes,
        given_up,
        keyframes_mean: if successes > 0 { keyframes as f64 / successes as f64 } else { 0.0 },
        seconds,
        episodes_per_minute: successes as f64 / seconds * 60.0,
    })
}

/// What [`merge_collections`] made.
#[derive(Debug, Clone, Serialize)]
pub struct CollectionMerge {
    pub task: String,
    pub shards: usize,
    pub episodes: usize,
    /// Slots every attempt of which failed.
    pub given_up: usize,
    /// The shards' source revisions (one if they agree).
    pub revisions: Vec<String>,
}

/// Whether the dataset folder `dir` was collected with another version of its task's expert
/// than this build's ([`Task::expert_version`]): the sentence saying so (a dataset of an older
/// expert still trains and scores, for reproducing what it made, so this is for a warning),
/// `None` when the versions agree, the folder has no manifest (written by hand or by an older
/// flowram) or the task is unknown here.
pub fn stale_expert(dir: &Path) -> Result<Option<String>, RolloutError> {
    let Some(manifest) = CollectionManifest::read(dir)? else { return Ok(None) };
    let Ok(task) = tasks::by_name(&manifest.task) else { return Ok(None) };
    let now = task.expert_version();
    Ok((manifest.expert_version != now).then(|| {
        format!(
            "{} holds {} demonstrations of expert version {}, and this build's expert is version {now}: its keyframes \
             are not what `flowram collect` makes now (see the task's `expert_version`); collect the task again into \
             a new folder unless you mean to reproduce a run made with it",
            dir.display(),
            manifest.task,
            manifest.expert_version
        )
    }))
}

/// Merges the dataset folders of all shards of one collection into a new dataset at `out`: the
/// episodes in slot order (the files hard-linked where possible, else copied), one index and
/// one manifest, exactly as one unsharded run writes them. Refuses shards of different
/// collections (task, cameras, image size, seeds, slots, shard count), a missing or repeated
/// shard, an incomplete shard (re-run it: it resumes), and an `out` that exists and is not
/// empty.
pub fn merge_collections(shards: &[PathBuf], out: &Path) -> Result<CollectionMerge, RolloutError> {
    let refuse = |problem: String| Err(RolloutError::Merge { problem });
    let mut parts = Vec::with_capacity(shards.len());
    for dir in shards {
        let Some(manifest) = CollectionManifest::read(dir)? else {
            return refuse(format!(
                "{} has no {MANIFEST_FILE}: not a folder written by `flowram collect` (with this version)",
                dir.display()
            ));
        };
        let index = crate::data::read_index(dir)?;
        parts.push((dir, manifest, index));
    }
    let Some((first_dir, first, _)) = parts.first() else {
        return refuse("no shard folders given".into());
    };
    let set: Vec<(Shard, String)> = parts.iter().map(|(d, m, _)| (m.shard, d.display().to_string())).collect();
    check_shard_set(&set).map_err(|problem| RolloutError::Merge { problem })?;
    let count = first.shard.count;
    for (dir, m, _) in &parts {
        let differs = |what: &str, a: String, b: String| {
            refuse(format!(
                "{} and {} are shards of different collections: {what} {a} vs {b}",
                first_dir.display(),
                dir.display()
            ))
        };
        if m.task != first.task {
            return differs("task", m.task.clone(), first.task.clone());
        }
        if m.expert_version != first.expert_version {
            return differs("expert version", m.expert_version.to_string(), first.expert_version.to_string());
        }
        if m.cameras != first.cameras {
            return differs("cameras", format!("{:?}", m.cameras), format!("{:?}", first.cameras));
        }
        if m.image_size != first.image_size {
            return differs("image size", m.image_size.to_string(), first.image_size.to_string());
        }
        if (m.seed, m.episodes, m.attempts_per_episode) != (first.seed, first.episodes, first.attempts_per_episode) {
            return differs(
                "(seed, episodes, attempts per episode)",
                format!("{:?}", (m.seed, m.episodes, m.attempts_per_episode)),
                format!("{:?}", (first.seed, first.episodes, first.attempts_per_episode)),
            );
        }
        if m.perturbation != first.perturbation {
            return differs("perturbation", format!("{:?}", m.perturbation), format!("{:?}", first.perturbation));
        }
        if !m.complete() {
            return refuse(format!(
                "{} (shard {} of {count}) is incomplete: re-run its `flowram collect` with the same arguments ({}); it resumes",
                dir.display(),
                m.shard.index,
                m.request()
            ));
        }
    }
    if out.exists() && std::fs::read_dir(out).map(|mut d| d.next().is_some()).unwrap_or(true) {
        return refuse(format!("{} exists and is not empty: merge into a new folder", out.display()));
    }
    // Every episode, in slot order.
    let mut episodes = Vec::new();
    for (dir, m, index) in &parts {
        for entry in &index.episodes {
            let slot = m.attempts.iter().find(|a| a.seed == entry.seed && a.success).map(|a| a.episode);
            let Some(slot) = slot else {
                return refuse(format!(
                    "{} lists seed {} but its manifest has no success for it",
                    dir.display(),
                    entry.seed
                ));
            };
            episodes.push((slot, dir.join(&entry.file), entry.clone()));
        }
    }
    episodes.sort_by_key(|(slot, _, _)| *slot);
    let mut merged = CollectionManifest {
        shard: Shard::WHOLE,
        attempts: parts.iter().flat_map(|(_, m, _)| m.attempts.iter().copied()).collect(),
        ..first.clone()
    };
    merged.attempts.sort_by_key(|a| (a.episode, a.seed));
    let mut revisions: Vec<String> = parts.iter().map(|(_, m, _)| m.revision.clone()).collect();
    revisions.sort();
    revisions.dedup();
    merged.revision = revisions.join(",");
    let mut writer = Dataset::create_or_open(out, &first.task, &first.cameras, [first.image_size, first.image_size])?;
    for (_, file, entry) in &episodes {
        writer.append_file(file, entry)?;
    }
    merged.write(out)?;
    let given_up = (0..first.episodes).filter(|&k| !merged.done(k)).count();
    Ok(CollectionMerge { task: first.task.clone(), shards: count, episodes: episodes.len(), given_up, revisions })
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
