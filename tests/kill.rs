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

/// Starts `cmd` and kills it with SIGKILL `jitter` after `ready()` first holds (polled every
/// 5 ms), unless it ended before; true if killed. Kills keyed to the run's own progress land
/// mid-run on any machine, however fast or loaded; the jitter spreads them over the work that
/// follows (an episode being simulated or written, a step, a checkpoint being saved).
fn kill_when(mut cmd: Command, ready: impl Fn() -> bool, jitter: Duration) -> bool {
    let mut child = cmd.stdout(std::process::Stdio::null()).stderr(std::process::Stdio::null()).spawn().unwrap();
    let give_up = Instant::now() + Duration::from_secs(600);
    let mut deadline: Option<Instant> = None;
    loop {
        if child.try_wait().unwrap().is_some() {
            return false;
        }
        let now = Instant::now();
        if now >= give_up {
            child.kill().unwrap();
            child.wait().unwrap();
            panic!("the run made no progress in 600 s");
        }
        match deadline {
            Some(at) if now >= at => break,
            None if ready() => deadline = Some(now + jitter),
            _ => {}
        }
        std::thread::sleep(Duration::from_millis(5));
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

/// How many episodes the index lists now (0 while it is absent); cheap enough to poll.
fn listed_count(dir: &Path) -> usize {
    read_index(dir).map_or(0, |index| index.episodes.len())
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

/// Episodes of the killed collection.
const EPISODES: usize = 8;

#[test]
fn collect_killed_at_random_points_keeps_its_dataset_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("data");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let mut before: Vec<u64> = Vec::new();
    let mut landed = 0;
    // The first kill comes at a random time from the start (it may land while the simulator and
    // renderer start up). The second comes as soon as the run lists its second new episode,
    // and measures how long an episode takes (simulation, rendering, writing). Each later one
    // comes a uniformly random fraction of that time after the run lists one more episode, so
    // the kills fall anywhere in an episode's life, its writing included.
    let mut interval: Option<Duration> = None;
    for attempt in 0..5u64 {
        let listed = before.len();
        let killed = match (attempt, interval) {
            (0, _) => kill_when(collect(&out, EPISODES), || true, Duration::from_millis(rng.random_range(50..1500))),
            (_, None) => {
                let first_new = std::cell::Cell::new(None);
                let ready = || {
                    let n = listed_count(&out);
                    if n > listed && first_new.get().is_none() {
                        first_new.set(Some(Instant::now()));
                    }
                    n > listed + 1
                };
                let killed = kill_when(collect(&out, EPISODES), ready, Duration::ZERO);
                interval = first_new.get().map(|t| t.elapsed());
                killed
            }
            (_, Some(episode)) => {
                let jitter = episode.mul_f64(rng.random_range(0.0..1.0));
                kill_when(collect(&out, EPISODES), || listed_count(&out) > listed, jitter)
            }
        };
        let seeds = listed_seeds(&out);
        assert!(seeds.starts_with(&before), "a kill lost listed episodes: {before:?} then {seeds:?}");
        landed += usize::from(killed && !seeds.is_empty() && seeds.len() < EPISODES);
        before = seeds;
    }
    assert!(landed >= 2, "fewer than two kills landed mid-collection (after an episode, before the end): {landed}");
    let finished = collect(&out, EPISODES).output().unwrap();
    assert!(finished.status.success(), "{}", String::from_utf8_lossy(&finished.stderr));
    let seeds = listed_seeds(&out);
    assert!(seeds.starts_with(&before));
    let mut unique = seeds.clone();
    unique.sort_unstable();
    unique.dedup();
    assert_eq!((seeds.len(), unique.len()), (EPISODES, EPISODES), "every episode, each once: {seeds:?}");
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
        // once the run has logged 1-60 steps past where it started, plus 0-300 ms
        let (start, ahead) = (last_logged_step(&run), rng.random_range(1..60u64));
        let jitter = Duration::from_millis(rng.random_range(0..300));
        if !kill_when(train(), || last_logged_step(&run) >= start + ahead, jitter) {
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
