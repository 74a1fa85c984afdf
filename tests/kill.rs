//! SIGKILL at random points (seeded) of `flowram collect` and `flowram train`: after every kill
//! the dataset and the checkpoints still load, and re-running (`collect` again, `train
//! --resume`) continues, losing at most one checkpoint interval of training and no episode
//! already listed.
mod common;

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use flowram::data::{load_dataset, read_index};
use rand::{Rng, SeedableRng};

/// Starts `cmd`, kills it with SIGKILL after `delay` unless it ended before; true if killed.
fn kill_after(mut cmd: Command, delay: Duration) -> bool {
    let mut child = cmd.stdout(std::process::Stdio::null()).stderr(std::process::Stdio::null()).spawn().unwrap();
    let deadline = Instant::now() + delay;
    while Instant::now() < deadline {
        if child.try_wait().unwrap().is_some() {
            return false;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    true
}

fn collect(out: &Path, episodes: usize) -> Command {
    let mut c = common::flowram();
    c.args(["collect", "--task", "open_drawer", "--episodes", &episodes.to_string(), "--seed", "0"]);
    c.args(["--cameras", "front", "--size", "48", "--out"]).arg(out);
    c.env_remove("SLURM_ARRAY_TASK_ID").env_remove("JOB_COMPLETION_INDEX");
    c
}

/// The seeds a dataset lists, checking that every listed episode loads.
fn listed_seeds(dir: &Path) -> Vec<u64> {
    if !dir.join("index.json").exists() {
        return Vec::new();
    }
    let loaded = load_dataset(dir).unwrap_or_else(|e| panic!("the dataset does not load after a kill: {e}"));
    assert!(loaded.failures.is_empty(), "episodes that do not load after a kill: {:?}", loaded.failures);
    read_index(dir).unwrap().episodes.iter().map(|e| e.seed).collect()
}

#[test]
fn collect_killed_at_random_points_keeps_its_dataset_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("data");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let mut before: Vec<u64> = Vec::new();
    let mut landed = 0;
    // Four kills at random points; on a loaded machine an episode can take longer than the
    // delays, so while none has landed after an episode, up to four more with longer delays.
    for attempt in 0..8u64 {
        if attempt >= 4 && landed > 0 {
            break;
        }
        let stretch = 1 + attempt.saturating_sub(3);
        let delay = Duration::from_millis(rng.random_range(700..4000) * stretch);
        let killed = kill_after(collect(&out, 6), delay);
        let seeds = listed_seeds(&out);
        assert!(seeds.starts_with(&before), "a kill lost listed episodes: {before:?} then {seeds:?}");
        landed += usize::from(killed && !seeds.is_empty() && seeds.len() < 6);
        before = seeds;
    }
    assert!(landed > 0, "no kill landed mid-collection (after an episode, before the end): retime the kills");
    let finished = collect(&out, 6).output().unwrap();
    assert!(finished.status.success(), "{}", String::from_utf8_lossy(&finished.stderr));
    let seeds = listed_seeds(&out);
    assert!(seeds.starts_with(&before));
    let mut unique = seeds.clone();
    unique.sort_unstable();
    unique.dedup();
    assert_eq!((seeds.len(), unique.len()), (6, 6), "six episodes, each once: {seeds:?}");
}

/// The last step written to `metrics.csv` (0 if none).
fn last_logged_step(run: &Path) -> u64 {
    std::fs::read_to_string(run.join("metrics.csv"))
        .unwrap_or_default()
        .lines()
        .rev()
        .find_map(|l| l.split(',').next()?.parse().ok())
        .unwrap_or(0)
}

/// The newest committed checkpoint's step (0 if none).
fn latest_checkpoint_step(run: &Path) -> u64 {
    let store = flowram::policy::checkpoint::store::CheckpointStore::open(run.join("checkpoints")).unwrap();
    store.committed().unwrap().last().map_or(0, |(step, _)| *step)
}

#[test]
fn train_killed_at_random_points_resumes_losing_at_most_one_checkpoint_interval() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let out = collect(&data, 2).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let mut config = common::tiny_policy_config();
    config.observation.cameras = vec!["front".into()];
    config.train.steps = 800;
    config.train.checkpoint_every = 25;
    config.train.log_every = 1;
    config.train.batch = 2;
    let config_file = dir.path().join("tiny.toml");
    std::fs::write(&config_file, toml::to_string(&config).unwrap()).unwrap();
    let run = dir.path().join("run");
    let train = || {
        let mut c = common::flowram();
        c.arg("train").arg("--data").arg(&data).arg("--out").arg(&run);
        if latest_checkpoint_step(&run) > 0 {
            c.arg("--resume");
        } else {
            c.arg("--config").arg(&config_file);
        }
        c
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
    let mut kills = 0;
    for _ in 0..6 {
        let delay = Duration::from_millis(rng.random_range(800..4000));
        if !kill_after(train(), delay) {
            break;
        }
        kills += 1;
        let (logged, saved) = (last_logged_step(&run), latest_checkpoint_step(&run));
        assert!(
            saved + config.train.checkpoint_every as u64 >= logged,
            "killed at step {logged} or later, but the newest checkpoint is step {saved}"
        );
        if saved > 0 {
            // what the next command resumes from loads, every file verified
            let checkpoint = store_dir(&run, saved);
            flowram::policy::checkpoint::store::read_checkpoint(&checkpoint, &candle_core::Device::Cpu)
                .unwrap_or_else(|e| panic!("checkpoint step {saved} does not load after a kill: {e}"));
        }
    }
    assert!(kills >= 2, "the runs finished before most kills: lengthen the run");
    let finished = train().output().unwrap();
    assert!(finished.status.success(), "{}", String::from_utf8_lossy(&finished.stderr));
    assert_eq!(latest_checkpoint_step(&run), 800);
    assert_eq!(last_logged_step(&run), 800);
}

fn store_dir(run: &Path, step: u64) -> std::path::PathBuf {
    run.join("checkpoints").join(format!("step-{step:09}"))
}
