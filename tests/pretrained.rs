//! The checkpoint shipped in `models/policy/pretrained/five-tasks` (see its model card): it loads,
//! predicts the first keyframe of a held-out episode of every task near the expert's, and
//! follows the instruction. Fails if the checkpoint, its config or the inference path breaks.
use flowram::data::Episode;
use flowram::policy::inference::{Policy, SamplingOptions};
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::policy::scene::observation::{KeyframePose, Observation};
use flowram::rollout::collection;
use flowram::rollout::learned::DEFAULT_CAMERAS;
use flowram::sim::Visuals;
use flowram::tasks;

/// The held-out seed of every task (training data starts at seed 0 and stays below 1000).
const SEED: u64 = 1000;

fn shipped() -> Policy {
    flowram::policy::runtime::configure_malloc();
    let path = flowram::deps::models_dir().join("policy/pretrained/five-tasks");
    Policy::load(&path, TextEncoder::load_installed().unwrap()).unwrap()
}

/// The expert's episode of `task` at `seed` with `variation`, rendered as the policy sees it.
fn expert(policy: &Policy, task: &str, variation: usize, seed: u64) -> Episode {
    let task = tasks::by_name(task).unwrap();
    let size = policy.config().observation.image_size;
    let episode =
        collection::demonstration(task.as_ref(), variation, seed, &DEFAULT_CAMERAS, size, Visuals::Full).unwrap();
    assert!(episode.success, "the expert must solve {} seed {seed}", episode.task);
    episode
}

fn first_keyframe(policy: &mut Policy, observation: &Observation) -> KeyframePose {
    let options = SamplingOptions { steps: policy.config().flow.sampling_steps, samples: 1, drs: true, seed: 0 };
    policy.predict(observation, &options).unwrap()[0]
}

fn distance_mm(a: &KeyframePose, b: &KeyframePose) -> f64 {
    let d: f64 = (0..3).map(|i| (a.position[i] as f64 - b.position[i] as f64).powi(2)).sum();
    1e3 * d.sqrt()
}

#[test]
fn the_shipped_checkpoint_predicts_every_tasks_first_keyframe_within_2_cm() {
    let mut policy = shipped();
    let mut report = Vec::new();
    for task in ["open_drawer", "push_buttons", "slide_block", "close_jar", "stack_blocks"] {
        let variation = SEED as usize % tasks::by_name(task).unwrap().variation_count();
        let episode = expert(&policy, task, variation, SEED);
        let observation = Observation::from_episode(&episode, 0).unwrap();
        let predicted = first_keyframe(&mut policy, &observation);
        let target = Observation::episode_action(&episode, 0);
        report.push((task, distance_mm(&predicted, &target)));
    }
    let misses: Vec<_> = report.iter().filter(|(_, mm)| *mm > 20.0).collect();
    assert!(misses.is_empty(), "first keyframes further than 20 mm from the expert's: {misses:?} (all: {report:?})");
}

#[test]
fn changing_the_instruction_changes_the_drawer_the_policy_goes_to() {
    // One held-out open_drawer scene: the same seed lays out the same cabinet whatever the
    // variation, and the variation only names the drawer to open.
    let mut policy = shipped();
    let task = tasks::by_name("open_drawer").unwrap();
    let (told, other) = (0, 2);
    let episode = expert(&policy, "open_drawer", told, SEED);
    let other_episode = expert(&policy, "open_drawer", other, SEED);
    let (told_target, other_target) =
        (Observation::episode_action(&episode, 0), Observation::episode_action(&other_episode, 0));
    assert!(distance_mm(&told_target, &other_target) > 100.0, "the two drawers' handles must be apart");
    let observation = Observation::from_episode(&episode, 0).unwrap();
    let swapped = Observation { instruction: task.instruction(other), ..observation.clone() };
    let (as_told, as_swapped) = (first_keyframe(&mut policy, &observation), first_keyframe(&mut policy, &swapped));
    assert!(
        distance_mm(&as_told, &told_target) < distance_mm(&as_told, &other_target),
        "told {:?}, the policy went nearer the other drawer: {:?}",
        task.instruction(told),
        as_told.position
    );
    assert!(
        distance_mm(&as_swapped, &other_target) < distance_mm(&as_swapped, &told_target),
        "told {:?} in the same scene, the policy stayed nearer the first drawer: {:?}",
        task.instruction(other),
        as_swapped.position
    );
}
