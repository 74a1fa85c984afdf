//! Demonstration datasets: round trip through the writer and loader, clear errors for damaged
//! files, and the on-disk bytes following the safetensors layout that Python reads.
use std::path::{Path, PathBuf};

use flowram::data::{
    DATASET_FORMAT, DataError, Dataset, EPISODE_FORMAT, Episode, load_dataset, read_episode, read_index, write_episode,
};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

const TASK: &str = "open_drawer";
const H: usize = 6;
const W: usize = 5;

fn cameras() -> Vec<String> {
    vec!["front".into(), "wrist".into()]
}

fn floats(rng: &mut StdRng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(-3.0f32..3.0)).collect()
}

/// An episode with `k` keyframes whose every value is random, so any mix-up shows.
fn episode(seed: u64, k: usize) -> Episode {
    let mut rng = StdRng::seed_from_u64(seed);
    let c = cameras().len();
    Episode {
        task: TASK.into(),
        variation: rng.random_range(0..20),
        instruction: format!("open the drawer nr. {seed} — «ünïcode»"),
        seed: rng.random::<u64>(),
        cameras: cameras(),
        success: seed.is_multiple_of(2),
        height: H,
        width: W,
        rgb: (0..k * c * H * W * 3).map(|_| rng.random::<u8>()).collect(),
        depth: floats(&mut rng, k * c * H * W),
        intrinsics: floats(&mut rng, c * 9),
        extrinsics: floats(&mut rng, k * c * 16),
        proprio: floats(&mut rng, k * 8),
        action: floats(&mut rng, k * 8),
    }
}

/// A dataset with three episodes (2, 3 and 4 keyframes) written through the writer.
fn three_episode_dataset(dir: &Path) -> (Vec<Episode>, Vec<PathBuf>) {
    let episodes: Vec<Episode> = (0..3).map(|i| episode(100 + i, 2 + i as usize)).collect();
    let mut writer = Dataset::create_or_open(dir, TASK, &cameras(), [H, W]).unwrap();
    let paths = episodes.iter().map(|e| writer.append(e).unwrap()).collect();
    (episodes, paths)
}

#[test]
fn round_trip_keeps_every_value_and_the_index() {
    let dir = tempfile::tempdir().unwrap();
    let (episodes, paths) = three_episode_dataset(dir.path());
    let names: Vec<_> = paths.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
    assert_eq!(names, ["episode_00000.safetensors", "episode_00001.safetensors", "episode_00002.safetensors"]);

    let loaded = load_dataset(dir.path()).unwrap();
    assert!(loaded.failures.is_empty(), "{:?}", loaded.failures);
    assert_eq!(loaded.episodes, episodes);
    assert_eq!(read_episode(&paths[1]).unwrap(), episodes[1]);

    let index = loaded.index;
    assert_eq!((index.format.as_str(), index.task.as_str()), (DATASET_FORMAT, TASK));
    assert_eq!((index.cameras.clone(), index.image_size), (cameras(), [H, W]));
    assert_eq!(index.episodes.len(), 3);
    for ((entry, e), name) in index.episodes.iter().zip(&episodes).zip(&names) {
        assert_eq!(&entry.file, name);
        assert_eq!((entry.variation, entry.seed, entry.keyframes), (e.variation, e.seed, e.keyframes()));
        assert_eq!(entry.instruction, e.instruction);
    }

    // Reopening continues the numbering and keeps the old entries; no temporary files are left.
    let mut writer = Dataset::create_or_open(dir.path(), TASK, &cameras(), [H, W]).unwrap();
    let fourth = writer.append(&episode(7, 1)).unwrap();
    assert!(fourth.ends_with("episode_00003.safetensors"));
    assert_eq!(read_index(dir.path()).unwrap().episodes.len(), 4);
    let stray: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .filter(|n| n.to_string_lossy().ends_with(".tmp"))
        .collect();
    assert!(stray.is_empty(), "{stray:?}");
}

#[test]
fn truncated_file_is_named_and_the_rest_still_loads() {
    let dir = tempfile::tempdir().unwrap();
    let (episodes, paths) = three_episode_dataset(dir.path());
    let bytes = std::fs::read(&paths[1]).unwrap();
    std::fs::write(&paths[1], &bytes[..bytes.len() / 2]).unwrap();

    let err = read_episode(&paths[1]).unwrap_err();
    assert!(matches!(err, DataError::Truncated { .. }), "{err:?}");
    let msg = err.to_string();
    assert!(msg.contains("episode_00001.safetensors") && msg.contains("truncated"), "{msg}");
    assert!(
        msg.contains(&format!("file has {}", bytes.len() / 2)) && msg.contains(&format!("header says {}", bytes.len())),
        "{msg}"
    );

    let loaded = load_dataset(dir.path()).unwrap();
    assert_eq!(loaded.episodes, vec![episodes[0].clone(), episodes[2].clone()]);
    assert_eq!(loaded.failures.len(), 1);
    assert_eq!(loaded.failures[0].0, paths[1]);
    assert!(loaded.failures[0].1.to_string().contains("episode_00001.safetensors"));

    // A file listed in the index but gone is a failure too, not an error for the whole dataset.
    std::fs::remove_file(&paths[2]).unwrap();
    let loaded = load_dataset(dir.path()).unwrap();
    assert_eq!(loaded.episodes, vec![episodes[0].clone()]);
    assert_eq!(loaded.failures.len(), 2);
    assert!(loaded.failures[1].1.to_string().contains("episode_00002.safetensors"), "{}", loaded.failures[1].1);
}

#[test]
fn corrupted_header_gives_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("episode_00000.safetensors");
    write_episode(&path, &episode(1, 2)).unwrap();
    let good = std::fs::read(&path).unwrap();

    let mut bad = good.clone();
    bad[8..20].copy_from_slice(b"#garbage!#@&");
    std::fs::write(&path, &bad).unwrap();
    let msg = read_episode(&path).unwrap_err().to_string();
    assert!(msg.contains("episode_00000.safetensors") && msg.contains("corrupted") && msg.contains("JSON"), "{msg}");

    let mut bad = good.clone();
    bad[..8].copy_from_slice(&u64::MAX.to_le_bytes());
    std::fs::write(&path, &bad).unwrap();
    let msg = read_episode(&path).unwrap_err().to_string();
    assert!(msg.contains("episode_00000.safetensors") && msg.contains("truncated or corrupted"), "{msg}");

    std::fs::write(&path, b"abc").unwrap();
    let msg = read_episode(&path).unwrap_err().to_string();
    assert!(msg.contains("episode_00000.safetensors") && msg.contains("corrupted"), "{msg}");

    let missing = dir.path().join("episode_00042.safetensors");
    let msg = read_episode(&missing).unwrap_err().to_string();
    assert!(msg.contains("episode_00042.safetensors") && msg.contains("cannot read"), "{msg}");
}

/// Writes a safetensors file from (name, dtype, shape, bytes) with the given metadata.
fn raw_file(path: &Path, tensors: &[(&str, safetensors::Dtype, Vec<usize>, Vec<u8>)], meta: Option<Vec<(&str, &str)>>) {
    let views: Vec<_> = tensors
        .iter()
        .map(|(n, d, s, b)| (*n, safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap()))
        .collect();
    let meta = meta.map(|m| m.into_iter().map(|(k, v)| (k.to_string(), v.to_string())).collect());
    std::fs::write(path, safetensors::serialize(views, meta).unwrap()).unwrap();
}

fn valid_tensors(k: usize) -> Vec<(&'static str, safetensors::Dtype, Vec<usize>, Vec<u8>)> {
    use safetensors::Dtype::{F32, U8};
    let c = cameras().len();
    let f = |shape: Vec<usize>| -> (Vec<usize>, Vec<u8>) {
        let n: usize = shape.iter().product();
        (shape, vec![0; n * 4])
    };
    let mut out = vec![("rgb", U8, vec![k, c, H, W, 3], vec![0u8; k * c * H * W * 3])];
    for (name, shape) in [
        ("depth", vec![k, c, H, W]),
        ("intrinsics", vec![c, 3, 3]),
        ("extrinsics", vec![k, c, 4, 4]),
        ("proprio", vec![k, 8]),
        ("action", vec![k, 8]),
    ] {
        let (shape, bytes) = f(shape);
        out.push((name, F32, shape, bytes));
    }
    out
}

fn valid_meta() -> Vec<(&'static str, &'static str)> {
    vec![
        ("format", EPISODE_FORMAT),
        ("task", TASK),
        ("variation", "3"),
        ("instruction", "x"),
        ("seed", "9"),
        ("cameras", r#"["front","wrist"]"#),
        ("success", "true"),
    ]
}

#[test]
fn foreign_files_get_errors_naming_the_tensor_or_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("episode_00005.safetensors");
    let check = |tensors: Vec<_>, meta, want: &str| {
        raw_file(&path, &tensors, meta);
        let msg = read_episode(&path).unwrap_err().to_string();
        assert!(msg.contains("episode_00005.safetensors") && msg.contains(want), "want {want:?} in: {msg}");
    };
    raw_file(&path, &valid_tensors(2), Some(valid_meta()));
    assert_eq!(read_episode(&path).unwrap().keyframes(), 2, "the hand-made file itself is valid");

    let mut t = valid_tensors(2);
    t.retain(|x| x.0 != "depth");
    check(t, Some(valid_meta()), "no tensor `depth`");

    let mut t = valid_tensors(2);
    t[0].1 = safetensors::Dtype::I8;
    check(t, Some(valid_meta()), "`rgb` has dtype I8, expected U8");

    let mut t = valid_tensors(2);
    t[4] = ("proprio", safetensors::Dtype::F32, vec![16], vec![0; 64]);
    check(t, Some(valid_meta()), "`proprio` has shape [16], expected rank 2");

    let mut t = valid_tensors(2);
    t[1] = ("depth", safetensors::Dtype::F32, vec![2, 2, H, W + 1], vec![0; 2 * 2 * H * (W + 1) * 4]);
    check(t, Some(valid_meta()), "`depth` has shape [2, 2, 6, 6], expected [2, 2, 6, 5]");

    check(valid_tensors(2), None, "metadata `format` is missing");
    let mut m = valid_meta();
    m[2] = ("variation", "three");
    check(valid_tensors(2), Some(m), "metadata `variation` is \"three\"");
    let mut m = valid_meta();
    m[5] = ("cameras", r#"["front"]"#);
    check(valid_tensors(2), Some(m), "metadata `cameras`");
}

#[test]
fn shape_mismatch_is_rejected_on_write() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("episode_00000.safetensors");
    let mut bad = episode(3, 2);
    bad.depth.pop();
    let msg = write_episode(&path, &bad).unwrap_err().to_string();
    assert!(msg.contains("`depth` has 119 values") && msg.contains("[2, 2, 6, 5]"), "{msg}");
    assert!(!path.exists(), "nothing written for an invalid episode");

    let mut bad = episode(3, 2);
    bad.action.extend([0.0; 8]);
    assert!(write_episode(&path, &bad).unwrap_err().to_string().contains("`action`"));
    let mut bad = episode(3, 2);
    bad.proprio.pop();
    assert!(write_episode(&path, &bad).unwrap_err().to_string().contains("`proprio`"));
    let mut writer = Dataset::create_or_open(dir.path(), TASK, &cameras(), [H, W]).unwrap();
    assert!(writer.append(&bad).is_err());
    assert!(read_index(dir.path()).unwrap().episodes.is_empty(), "a rejected episode is not indexed");
}

#[test]
fn mixing_tasks_cameras_or_sizes_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    three_episode_dataset(dir.path());
    let before = std::fs::read(dir.path().join("index.json")).unwrap();

    let err = Dataset::create_or_open(dir.path(), "close_jar", &cameras(), [H, W]).unwrap_err();
    let msg = err.to_string();
    assert!(
        matches!(err, DataError::Mismatch { .. }) && msg.contains("open_drawer") && msg.contains("close_jar"),
        "{msg}"
    );
    assert!(
        Dataset::create_or_open(dir.path(), TASK, &cameras()[..1], [H, W]).unwrap_err().to_string().contains("camera")
    );
    assert!(
        Dataset::create_or_open(dir.path(), TASK, &cameras(), [H, W + 1])
            .unwrap_err()
            .to_string()
            .contains("image size")
    );

    let mut writer = Dataset::create_or_open(dir.path(), TASK, &cameras(), [H, W]).unwrap();
    let mut other = episode(5, 2);
    other.task = "close_jar".into();
    assert!(writer.append(&other).unwrap_err().to_string().contains("close_jar"));
    assert_eq!(std::fs::read(dir.path().join("index.json")).unwrap(), before, "index untouched");
    assert!(!dir.path().join("episode_00003.safetensors").exists());
}

#[test]
fn malformed_index_is_an_error_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    three_episode_dataset(dir.path());
    let index = dir.path().join("index.json");
    std::fs::write(&index, b"{\"format\": \"flowram-dataset-v1\", \"task\": ").unwrap();
    let msg = load_dataset(dir.path()).unwrap_err().to_string();
    assert!(msg.contains("index.json"), "{msg}");
    assert!(
        Dataset::create_or_open(dir.path(), TASK, &cameras(), [H, W]).unwrap_err().to_string().contains("index.json")
    );

    std::fs::remove_file(&index).unwrap();
    let msg = load_dataset(dir.path()).unwrap_err().to_string();
    assert!(msg.contains("index.json") && msg.contains("cannot read"), "{msg}");
}

#[test]
fn bytes_on_disk_follow_the_safetensors_layout() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("episode_00000.safetensors");
    let e = episode(11, 3);
    write_episode(&path, &e).unwrap();
    let bytes = std::fs::read(&path).unwrap();

    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let data = &bytes[8 + n..];
    let expect = [
        ("rgb", "U8", vec![3, 2, H, W, 3]),
        ("depth", "F32", vec![3, 2, H, W]),
        ("intrinsics", "F32", vec![2, 3, 3]),
        ("extrinsics", "F32", vec![3, 2, 4, 4]),
        ("proprio", "F32", vec![3, 8]),
        ("action", "F32", vec![3, 8]),
    ];
    let mut total = 0;
    for (name, dtype, shape) in expect {
        let info = &header[name];
        assert_eq!(info["dtype"], dtype, "{name}");
        assert_eq!(info["shape"], serde_json::json!(shape), "{name}");
        let (start, end) =
            (info["data_offsets"][0].as_u64().unwrap() as usize, info["data_offsets"][1].as_u64().unwrap() as usize);
        let size = if dtype == "U8" { 1 } else { 4 };
        assert_eq!(end - start, shape.iter().product::<usize>() * size, "{name}");
        total += end - start;
        if name == "proprio" {
            let values: Vec<f32> =
                data[start..end].chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
            assert_eq!(values, e.proprio, "little-endian f32, C order");
        }
        if name == "rgb" {
            assert_eq!(&data[start..end], e.rgb.as_slice());
        }
    }
    assert_eq!(total, data.len(), "the data section holds exactly the six tensors");
    let meta = &header["__metadata__"];
    assert_eq!(meta["format"], EPISODE_FORMAT);
    assert_eq!(meta["task"], TASK);
    assert_eq!(meta["variation"], e.variation.to_string());
    assert_eq!(meta["seed"], e.seed.to_string());
    assert_eq!(meta["success"], "false");
    assert_eq!(meta["instruction"], e.instruction.as_str());
    let cams: Vec<String> = serde_json::from_str(meta["cameras"].as_str().unwrap()).unwrap();
    assert_eq!(cams, cameras());
}
