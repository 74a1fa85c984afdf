//! Demonstration datasets on disk: one safetensors file per episode plus a JSON index.
//!
//! A dataset is a folder holding `index.json` and one file per episode, `episode_00000.safetensors`,
//! `episode_00001.safetensors`, ... Every file is written atomically (temporary file + rename), and
//! an episode file is always written before the index that lists it, so a crash never leaves the
//! index pointing at a half-written file.
//!
//! Each episode file is plain safetensors (8-byte little-endian header length, JSON header, raw
//! little-endian C-order data), readable from Python with `safetensors.numpy.load_file`. With K
//! keyframes, C cameras and H x W images it holds:
//!
//! | tensor       | dtype | shape             | meaning                                                         |
//! |--------------|-------|-------------------|-----------------------------------------------------------------|
//! | `rgb`        | U8    | [K, C, H, W, 3]   | colour images                                                   |
//! | `depth`      | F32   | [K, C, H, W]      | z-depth in metres along the camera axis, 0 = no surface         |
//! | `intrinsics` | F32   | [C, 3, 3]         | pinhole matrix K in pixels, pixel centres at integer coordinates |
//! | `extrinsics` | F32   | [K, C, 4, 4]      | camera-to-world transform, OpenCV axes (x right, y down, z forward) |
//! | `proprio`    | F32   | [K, 8]            | TCP position (world frame, m), quaternion w,x,y,z, gripper open (1.0/0.0) |
//! | `action`     | F32   | [K, 8]            | the next keyframe the expert went to from keyframe k, same layout |
//!
//! The safetensors `__metadata__` string map holds `format` = `"flowram-episode-v1"`, `task`,
//! `variation` (integer as a string), `instruction`, `seed` (integer as a string), `cameras` (a
//! JSON array of camera names, in tensor order) and `success` (`"true"`/`"false"`).
//!
//! `index.json` holds `{"format": "flowram-dataset-v1", "task", "cameras", "image_size": [H, W],
//! "episodes": [{"file", "variation", "instruction", "seed", "keyframes", "fnv1a64"}, ...]}`; one
//! dataset has a single task, camera set and image size. `fnv1a64` is the 64-bit FNV-1a of the
//! episode file's bytes (16 hex digits): a file whose bytes changed after it was written (a bit
//! flip, a truncation) fails to load instead of loading as other data. Datasets written before
//! the digest existed have none, and load unchecked.
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use safetensors::tensor::{Metadata, TensorView};
use safetensors::{Dtype, SafeTensors};
use serde::{Deserialize, Serialize};

/// Value of the `format` metadata key of every episode file.
pub const EPISODE_FORMAT: &str = "flowram-episode-v1";
/// Value of the `format` field of `index.json`.
pub const DATASET_FORMAT: &str = "flowram-dataset-v1";
/// Name of the index file inside a dataset folder.
pub const INDEX_FILE: &str = "index.json";
/// Values per keyframe pose: position x,y,z (m), quaternion w,x,y,z, gripper open (1.0/0.0).
pub const POSE_LEN: usize = 8;

const FIX: &str = "re-collect it or delete it and its index entry";

/// Everything that can go wrong reading or writing a dataset. File errors name the file.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("cannot read {}: {source}; check the path and that the dataset was copied completely", path.display())]
    Read { path: PathBuf, source: std::io::Error },
    #[error("cannot write {}: {source}; check that the folder is writable and the disk has space", path.display())]
    Write { path: PathBuf, source: std::io::Error },
    #[error("{} is truncated or corrupted (header says {expected} bytes, file has {actual}); {FIX}", path.display())]
    Truncated { path: PathBuf, expected: u64, actual: u64 },
    #[error("{} is corrupted ({reason}); {FIX}", path.display())]
    Corrupted { path: PathBuf, reason: String },
    #[error("{} has no tensor `{name}`; a {EPISODE_FORMAT} file needs rgb, depth, intrinsics, extrinsics, proprio and action; {FIX}", path.display())]
    MissingTensor { path: PathBuf, name: &'static str },
    #[error("{}: tensor `{name}` has dtype {found}, expected {expected}; {FIX}", path.display())]
    WrongDtype { path: PathBuf, name: &'static str, found: String, expected: String },
    #[error("{}: tensor `{name}` has shape {found:?}, expected {expected}; {FIX}", path.display())]
    WrongShape { path: PathBuf, name: &'static str, found: Vec<usize>, expected: String },
    #[error("{}: metadata `{key}` {problem}; episode files must be written by flowram ({EPISODE_FORMAT}); {FIX}", path.display())]
    Metadata { path: PathBuf, key: &'static str, problem: String },
    #[error("invalid episode: {0}; fix the episode before writing it")]
    InvalidEpisode(String),
    #[error("{} is not a valid dataset index ({problem}); fix or delete it (episode files can be re-indexed)", path.display())]
    Index { path: PathBuf, problem: String },
    #[error("{} does not match its index entry ({problem}); delete the file and its index entry or re-collect it", path.display())]
    EntryMismatch { path: PathBuf, problem: String },
    #[error("cannot add to the dataset in {}: its {field} is {existing} but this is {new}; use a separate folder per task, camera set and image size", dir.display())]
    Mismatch { dir: PathBuf, field: &'static str, existing: String, new: String },
}

/// One recorded demonstration; all arrays are row-major (C order), see the module docs for the
/// shapes, units and frames.
#[derive(Debug, Clone, PartialEq)]
pub struct Episode {
    pub task: String,
    pub variation: usize,
    pub instruction: String,
    pub seed: u64,
    /// Camera names, in the order of the C axis of the image tensors.
    pub cameras: Vec<String>,
    pub success: bool,
    /// Image height in pixels.
    pub height: usize,
    /// Image width in pixels.
    pub width: usize,
    /// u8 [K, C, H, W, 3].
    pub rgb: Vec<u8>,
    /// f32 [K, C, H, W], z-depth in metres, 0 = no surface.
    pub depth: Vec<f32>,
    /// f32 [C, 3, 3], pinhole matrices in pixels.
    pub intrinsics: Vec<f32>,
    /// f32 [K, C, 4, 4], camera-to-world, OpenCV camera axes.
    pub extrinsics: Vec<f32>,
    /// f32 [K, 8], TCP pose (world frame, m) + gripper open at each keyframe.
    pub proprio: Vec<f32>,
    /// f32 [K, 8], the next keyframe the expert went to from each keyframe.
    pub action: Vec<f32>,
}

impl Episode {
    /// Number of keyframes K (taken from `proprio`).
    pub fn keyframes(&self) -> usize {
        self.proprio.len() / POSE_LEN
    }

    /// Expected shape of every tensor, derived from K (proprio), C (cameras), H and W.
    fn shapes(&self) -> [(&'static str, &'static str, Vec<usize>, usize); 6] {
        let (k, c, h, w) = (self.keyframes(), self.cameras.len(), self.height, self.width);
        [
            ("rgb", "[K, C, H, W, 3]", vec![k, c, h, w, 3], self.rgb.len()),
            ("depth", "[K, C, H, W]", vec![k, c, h, w], self.depth.len()),
            ("intrinsics", "[C, 3, 3]", vec![c, 3, 3], self.intrinsics.len()),
            ("extrinsics", "[K, C, 4, 4]", vec![k, c, 4, 4], self.extrinsics.len()),
            ("proprio", "[K, 8]", vec![k, POSE_LEN], self.proprio.len()),
            ("action", "[K, 8]", vec![k, POSE_LEN], self.action.len()),
        ]
    }

    /// Checks that every tensor length agrees with K, C, H and W.
    pub fn validate(&self) -> Result<(), DataError> {
        let bad = |m: String| Err(DataError::InvalidEpisode(m));
        if !self.proprio.len().is_multiple_of(POSE_LEN) || self.proprio.is_empty() {
            return bad(format!("`proprio` has {} values, expected K x {POSE_LEN} with K >= 1", self.proprio.len()));
        }
        if self.cameras.is_empty() || self.height == 0 || self.width == 0 {
            return bad(format!(
                "needs at least one camera and a non-empty image, got {} cameras of {}x{} pixels",
                self.cameras.len(),
                self.height,
                self.width
            ));
        }
        for (name, layout, shape, len) in self.shapes() {
            let expected: usize = shape.iter().product();
            if expected != len {
                return bad(format!("`{name}` has {len} values, expected {layout} = {shape:?} ({expected} values)"));
            }
        }
        Ok(())
    }
}

fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn f32_values(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
}

/// Validates `episode` and writes it to `path` atomically in the format of the module docs.
/// Returns the FNV-1a 64 digest (hex) of the bytes written.
pub fn write_episode(path: &Path, episode: &Episode) -> Result<String, DataError> {
    episode.validate()?;
    let shapes = episode.shapes();
    let mut buffers: Vec<(&str, Dtype, Vec<usize>, Vec<u8>)> = Vec::new();
    for ((name, _, shape, _), data) in shapes.into_iter().zip([
        episode.rgb.clone(),
        f32_bytes(&episode.depth),
        f32_bytes(&episode.intrinsics),
        f32_bytes(&episode.extrinsics),
        f32_bytes(&episode.proprio),
        f32_bytes(&episode.action),
    ]) {
        let dtype = if name == "rgb" { Dtype::U8 } else { Dtype::F32 };
        buffers.push((name, dtype, shape, data));
    }
    let corrupt =
        |e: safetensors::SafeTensorError| DataError::InvalidEpisode(format!("cannot encode {}: {e}", path.display()));
    let mut views = Vec::new();
    for (name, dtype, shape, data) in &buffers {
        views.push((*name, TensorView::new(*dtype, shape.clone(), data).map_err(corrupt)?));
    }
    let bytes = safetensors::serialize(views, Some(episode_metadata(episode))).map_err(corrupt)?;
    crate::files::write_atomic(path, &bytes).map_err(|source| DataError::Write { path: path.to_path_buf(), source })?;
    Ok(crate::files::fnv1a64_hex(&bytes))
}

fn episode_metadata(e: &Episode) -> HashMap<String, String> {
    let cameras = serde_json::to_string(&e.cameras).unwrap_or_else(|_| "[]".into());
    [
        ("format", EPISODE_FORMAT.to_string()),
        ("task", e.task.clone()),
        ("variation", e.variation.to_string()),
        ("instruction", e.instruction.clone()),
        ("seed", e.seed.to_string()),
        ("cameras", cameras),
        ("success", e.success.to_string()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect()
}

/// Reads and checks one episode file; every error names `path`.
pub fn read_episode(path: &Path) -> Result<Episode, DataError> {
    read_episode_checked(path, None)
}

/// [`read_episode`], refusing a file whose FNV-1a 64 digest (hex) is not `digest`.
pub fn read_episode_checked(path: &Path, digest: Option<&str>) -> Result<Episode, DataError> {
    let bytes = std::fs::read(path).map_err(|source| DataError::Read { path: path.to_path_buf(), source })?;
    if let Some(expected) = digest {
        let actual = crate::files::fnv1a64_hex(&bytes);
        if actual != expected {
            return Err(DataError::Corrupted {
                path: path.to_path_buf(),
                reason: format!(
                    "its content changed after it was written (FNV-1a {actual}, the index recorded {expected}); re-collect it or remove it from index.json"
                ),
            });
        }
    }
    check_layout(path, &bytes)?;
    let corrupted =
        |e: safetensors::SafeTensorError| DataError::Corrupted { path: path.to_path_buf(), reason: e.to_string() };
    let (header_len, meta) = SafeTensors::read_metadata(&bytes).map_err(corrupted)?;
    let data = &bytes[8 + header_len..];
    let get = |name, dtype, rank| tensor(path, &meta, data, name, dtype, rank);
    let (rgb_shape, rgb) = get("rgb", Dtype::U8, 5)?;
    let [k, c, h, w, 3] = rgb_shape[..] else {
        return Err(wrong_shape(path, "rgb", &rgb_shape, "[K, C, H, W, 3]".into()));
    };
    let mut floats = Vec::new();
    for (name, expected) in [
        ("depth", vec![k, c, h, w]),
        ("intrinsics", vec![c, 3, 3]),
        ("extrinsics", vec![k, c, 4, 4]),
        ("proprio", vec![k, POSE_LEN]),
        ("action", vec![k, POSE_LEN]),
    ] {
        let (shape, values) = get(name, Dtype::F32, expected.len())?;
        if shape != expected {
            return Err(wrong_shape(path, name, &shape, format!("{expected:?} to match rgb {rgb_shape:?}")));
        }
        floats.push(f32_values(values));
    }
    let empty = HashMap::new();
    let fields = meta.metadata().as_ref().unwrap_or(&empty);
    let field = |key: &'static str| -> Result<&String, DataError> {
        fields.get(key).ok_or_else(|| DataError::Metadata {
            path: path.to_path_buf(),
            key,
            problem: "is missing".into(),
        })
    };
    let parse_err = |key: &'static str, value: &str, what: &str| DataError::Metadata {
        path: path.to_path_buf(),
        key,
        problem: format!("is {value:?}, expected {what}"),
    };
    let format = field("format")?;
    if format != EPISODE_FORMAT {
        return Err(parse_err("format", format, &format!("{EPISODE_FORMAT:?}")));
    }
    let variation = field("variation")?;
    let variation = variation.parse().map_err(|_| parse_err("variation", variation, "a non-negative integer"))?;
    let seed = field("seed")?;
    let seed = seed.parse().map_err(|_| parse_err("seed", seed, "a non-negative integer"))?;
    let success = field("success")?;
    let success = success.parse().map_err(|_| parse_err("success", success, "\"true\" or \"false\""))?;
    let cams = field("cameras")?;
    let cameras: Vec<String> =
        serde_json::from_str(cams).map_err(|_| parse_err("cameras", cams, "a JSON array of names"))?;
    if cameras.len() != c {
        return Err(parse_err("cameras", cams, &format!("{c} names to match the camera axis of rgb {rgb_shape:?}")));
    }
    let mut floats = floats.into_iter();
    let mut next = || floats.next().unwrap_or_default();
    Ok(Episode {
        task: field("task")?.clone(),
        variation,
        instruction: field("instruction")?.clone(),
        seed,
        cameras,
        success,
        height: h,
        width: w,
        rgb: rgb.to_vec(),
        depth: next(),
        intrinsics: next(),
        extrinsics: next(),
        proprio: next(),
        action: next(),
    })
}

fn wrong_shape(path: &Path, name: &'static str, found: &[usize], expected: String) -> DataError {
    DataError::WrongShape { path: path.to_path_buf(), name, found: found.to_vec(), expected }
}

/// Checks the file size against what the header promises, so truncation gets a clear message.
fn check_layout(path: &Path, bytes: &[u8]) -> Result<(), DataError> {
    let actual = bytes.len() as u64;
    let corrupted = |reason: String| DataError::Corrupted { path: path.to_path_buf(), reason };
    let Some(len_bytes) = bytes.get(..8) else {
        return Err(corrupted(format!("{actual} bytes, shorter than the 8-byte safetensors header length")));
    };
    let header_len = u64::from_le_bytes(len_bytes.try_into().unwrap_or_default());
    let header_end = header_len.saturating_add(8);
    if header_end > actual {
        return Err(DataError::Truncated { path: path.to_path_buf(), expected: header_end, actual });
    }
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..header_end as usize])
        .map_err(|e| corrupted(format!("the safetensors header is not valid JSON: {e}")))?;
    let Some(entries) = header.as_object() else {
        return Err(corrupted("the safetensors header is not a JSON object".into()));
    };
    let data_end = entries
        .iter()
        .filter(|(name, _)| *name != "__metadata__")
        .filter_map(|(_, info)| info.get("data_offsets")?.get(1)?.as_u64())
        .max()
        .unwrap_or(0);
    let expected = header_end.saturating_add(data_end);
    if expected != actual {
        return Err(DataError::Truncated { path: path.to_path_buf(), expected, actual });
    }
    Ok(())
}

/// Looks up tensor `name`, checks its dtype and rank and returns its shape and raw bytes.
fn tensor<'a>(
    path: &Path,
    meta: &Metadata,
    data: &'a [u8],
    name: &'static str,
    dtype: Dtype,
    rank: usize,
) -> Result<(Vec<usize>, &'a [u8]), DataError> {
    let info = meta.info(name).ok_or_else(|| DataError::MissingTensor { path: path.to_path_buf(), name })?;
    if info.dtype != dtype {
        return Err(DataError::WrongDtype {
            path: path.to_path_buf(),
            name,
            found: info.dtype.to_string(),
            expected: dtype.to_string(),
        });
    }
    if info.shape.len() != rank {
        return Err(wrong_shape(path, name, &info.shape, format!("rank {rank}")));
    }
    let (start, end) = info.data_offsets;
    let bytes = data.get(start..end).ok_or_else(|| DataError::Corrupted {
        path: path.to_path_buf(),
        reason: format!("tensor `{name}` lies outside the file"),
    })?;
    Ok((info.shape.clone(), bytes))
}

/// The contents of `index.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetIndex {
    /// Always [`DATASET_FORMAT`].
    pub format: String,
    pub task: String,
    pub cameras: Vec<String>,
    /// Image height and width in pixels.
    pub image_size: [usize; 2],
    pub episodes: Vec<IndexEntry>,
}

/// One episode listed in `index.json`; `file` is relative to the dataset folder.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IndexEntry {
    pub file: String,
    pub variation: usize,
    pub instruction: String,
    pub seed: u64,
    pub keyframes: usize,
    /// FNV-1a 64 of the episode file (hex); absent in datasets written before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fnv1a64: Option<String>,
}

/// Reads and checks `dir/index.json`; errors name the file.
pub fn read_index(dir: &Path) -> Result<DatasetIndex, DataError> {
    let path = dir.join(INDEX_FILE);
    let text = std::fs::read(&path).map_err(|source| DataError::Read { path: path.clone(), source })?;
    let index: DatasetIndex =
        serde_json::from_slice(&text).map_err(|e| DataError::Index { path: path.clone(), problem: e.to_string() })?;
    if index.format != DATASET_FORMAT {
        return Err(DataError::Index {
            path,
            problem: format!("format is {:?}, expected {DATASET_FORMAT:?}", index.format),
        });
    }
    Ok(index)
}

fn write_index(dir: &Path, index: &DatasetIndex) -> Result<(), DataError> {
    let path = dir.join(INDEX_FILE);
    let json = serde_json::to_vec_pretty(index)
        .map_err(|e| DataError::Index { path: path.clone(), problem: e.to_string() })?;
    crate::files::write_atomic(&path, &json).map_err(|source| DataError::Write { path, source })
}

/// Entry point for writing datasets.
pub struct Dataset;

/// Appends episodes to one dataset folder, keeping `index.json` in step.
#[derive(Debug)]
pub struct DatasetWriter {
    dir: PathBuf,
    index: DatasetIndex,
}

impl Dataset {
    /// Opens the dataset in `dir`, or creates it (folder + empty index) if it has no index yet.
    /// An existing dataset must have the same task, cameras and image size ([H, W], pixels).
    pub fn create_or_open(
        dir: &Path,
        task: &str,
        cameras: &[String],
        image_size: [usize; 2],
    ) -> Result<DatasetWriter, DataError> {
        if dir.join(INDEX_FILE).exists() {
            let index = read_index(dir)?;
            check_same(dir, &index, task, cameras, image_size)?;
            return Ok(DatasetWriter { dir: dir.to_path_buf(), index });
        }
        let index = DatasetIndex {
            format: DATASET_FORMAT.into(),
            task: task.into(),
            cameras: cameras.to_vec(),
            image_size,
            episodes: Vec::new(),
        };
        write_index(dir, &index)?;
        Ok(DatasetWriter { dir: dir.to_path_buf(), index })
    }
}

/// Refuses to mix a different task, camera list or image size ([H, W]) into the dataset in `dir`.
fn check_same(
    dir: &Path,
    index: &DatasetIndex,
    task: &str,
    cameras: &[String],
    image_size: [usize; 2],
) -> Result<(), DataError> {
    let mismatch = |field, existing: String, new: String| {
        Err(DataError::Mismatch { dir: dir.to_path_buf(), field, existing, new })
    };
    if index.task != task {
        return mismatch("task", format!("{:?}", index.task), format!("{task:?}"));
    }
    if index.cameras != cameras {
        return mismatch("camera list", format!("{:?}", index.cameras), format!("{cameras:?}"));
    }
    if index.image_size != image_size {
        return mismatch("image size [H, W]", format!("{:?}", index.image_size), format!("{image_size:?}"));
    }
    Ok(())
}

impl DatasetWriter {
    /// The index as last written.
    pub fn index(&self) -> &DatasetIndex {
        &self.index
    }

    /// Writes `episode` as the next `episode_NNNNN.safetensors`, then rewrites the index.
    pub fn append(&mut self, episode: &Episode) -> Result<PathBuf, DataError> {
        let index = &self.index;
        check_same(&self.dir, index, &episode.task, &episode.cameras, [episode.height, episode.width])?;
        let mut number = index.episodes.len();
        let name = |n: usize| format!("episode_{n:05}.safetensors");
        while index.episodes.iter().any(|e| e.file == name(number)) {
            number += 1;
        }
        let file = name(number);
        let path = self.dir.join(&file);
        let digest = write_episode(&path, episode)?;
        let entry = IndexEntry {
            file,
            variation: episode.variation,
            instruction: episode.instruction.clone(),
            seed: episode.seed,
            keyframes: episode.keyframes(),
            fnv1a64: Some(digest),
        };
        self.index.episodes.push(entry);
        if let Err(e) = write_index(&self.dir, &self.index) {
            self.index.episodes.pop();
            return Err(e);
        }
        Ok(path)
    }
}

/// A dataset read back: the episodes that loaded, in index order, and the ones that did not.
impl DatasetWriter {
    /// Adds the episode file `source` (an entry of another dataset, e.g. a shard's) under the
    /// next free name, hard-linked when on the same file system, else copied (atomically), and
    /// lists it with `entry`'s fields. The file is read and checked against `entry` and this
    /// dataset's task, cameras and image size first.
    pub fn append_file(&mut self, source: &Path, entry: &IndexEntry) -> Result<PathBuf, DataError> {
        load_entry(source, &IndexEntry { file: file_name_of(source), ..entry.clone() }, &self.index)?;
        let mut number = self.index.episodes.len();
        let name = |n: usize| format!("episode_{n:05}.safetensors");
        while self.index.episodes.iter().any(|e| e.file == name(number)) {
            number += 1;
        }
        let file = name(number);
        let path = self.dir.join(&file);
        let _ = std::fs::remove_file(&path); // a leftover of a killed merge, not in the index
        let bytes = std::fs::read(source).map_err(|e| DataError::Read { path: source.to_path_buf(), source: e })?;
        if std::fs::hard_link(source, &path).is_err() {
            crate::files::write_atomic(&path, &bytes)
                .map_err(|source| DataError::Write { path: path.clone(), source })?;
        }
        let fnv1a64 = Some(crate::files::fnv1a64_hex(&bytes));
        self.index.episodes.push(IndexEntry { file, fnv1a64, ..entry.clone() });
        if let Err(e) = write_index(&self.dir, &self.index) {
            self.index.episodes.pop();
            return Err(e);
        }
        Ok(path)
    }
}

fn file_name_of(path: &Path) -> String {
    path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
}

#[derive(Debug)]
pub struct LoadedDataset {
    pub index: DatasetIndex,
    pub episodes: Vec<Episode>,
    /// Episode files that are missing, corrupted or disagree with the index, with the reason.
    pub failures: Vec<(PathBuf, DataError)>,
}

/// Loads every episode listed in `dir/index.json`. A bad episode file goes into `failures` and
/// the rest still load; only a missing or malformed index is an error.
pub fn load_dataset(dir: &Path) -> Result<LoadedDataset, DataError> {
    let index = read_index(dir)?;
    let mut episodes = Vec::new();
    let mut failures = Vec::new();
    for entry in &index.episodes {
        let path = dir.join(&entry.file);
        match load_entry(&path, entry, &index) {
            Ok(episode) => episodes.push(episode),
            Err(e) => failures.push((path, e)),
        }
    }
    Ok(LoadedDataset { index, episodes, failures })
}

fn load_entry(path: &Path, entry: &IndexEntry, index: &DatasetIndex) -> Result<Episode, DataError> {
    let plain = Path::new(&entry.file).file_name().is_some_and(|n| n == entry.file.as_str());
    if !plain {
        return Err(DataError::EntryMismatch {
            path: path.to_path_buf(),
            problem: "the file name must be a plain name inside the dataset folder".into(),
        });
    }
    let episode = read_episode_checked(path, entry.fnv1a64.as_deref())?;
    let problem = if episode.task != index.task || episode.cameras != index.cameras {
        format!(
            "task/cameras {:?}/{:?}, index says {:?}/{:?}",
            episode.task, episode.cameras, index.task, index.cameras
        )
    } else if [episode.height, episode.width] != index.image_size {
        format!("image size {:?}, index says {:?}", [episode.height, episode.width], index.image_size)
    } else if episode.keyframes() != entry.keyframes
        || episode.seed != entry.seed
        || episode.variation != entry.variation
    {
        format!(
            "keyframes/seed/variation {}/{}/{}, index says {}/{}/{}",
            episode.keyframes(),
            episode.seed,
            episode.variation,
            entry.keyframes,
            entry.seed,
            entry.variation
        )
    } else {
        return Ok(episode);
    };
    Err(DataError::EntryMismatch { path: path.to_path_buf(), problem })
}
