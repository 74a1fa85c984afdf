//! The checkpoints shipped in `models/policy/pretrained/` (see their model cards): `five-tasks`,
//! the default for its five tasks, and `ten-tasks`, the default for the other five. Each loads,
//! predicts the first keyframe of a held-out episode of every task it was trained on where it did
//! when shipped, and follows the instruction. Fails if a checkpoint, its config or the inference path breaks.
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

fn load(name: &str) -> Policy {
    flowram::policy::runtime::configure_malloc();
    let path = flowram::deps::models_dir().join("policy/pretrained").join(name);
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

/// The keyframe the shipped checkpoint executes: its config's sampling.
fn first_keyframe(policy: &mut Policy, observation: &Observation) -> KeyframePose {
    let flow = &policy.config().flow;
    let options = SamplingOptions {
        steps: flow.sampling_steps,
        samples: flow.consensus_samples,
        drs: true,
        seed: 0,
        consensus: flow.consensus,
        sharpening: flow.pointer_sharpening,
    };
    policy.predict_keyframe(observation, &options).unwrap()
}

#[test]
#[ignore = "prints the shipped predictions for SHIPPED_PREDICTIONS and TEN_TASK_PREDICTIONS"]
fn print_shipped_predictions() {
    for (task, predicted, expert) in shipped_first_keyframes() {
        println!("five-tasks {task} {:?} {:.1}", predicted.position, distance_mm(&predicted, &expert));
    }
    for (task, predicted, expert) in first_keyframes("ten-tasks", &TEN_TASKS) {
        println!("ten-tasks {task} {:?} {:.1}", predicted.position, distance_mm(&predicted, &expert));
    }
}

const TEN_TASKS: [&str; 10] = [
    "open_drawer",
    "push_buttons",
    "slide_block",
    "close_jar",
    "stack_blocks",
    "meat_off_grill",
    "turn_tap",
    "put_item_in_drawer",
    "drag_stick",
    "sweep_to_dustpan",
];

fn distance_mm(a: &KeyframePose, b: &KeyframePose) -> f64 {
    let d: f64 = (0..3).map(|i| (a.position[i] as f64 - b.position[i] as f64).powi(2)).sum();
    1e3 * d.sqrt()
}

/// The first keyframe of each task's held-out episode at [`SEED`], as the shipped checkpoint
/// executes it (world frame, m; 8 Euler steps, noise seed 0, the consensus of its config's 8
/// samples since 2026-12-02 session 7), and the expert's distance from it (mm). Re-recorded when
/// GUR shipped (2026-12-06, session 27), when its config took the pointer's posterior (session
/// 30, arm POST), when LP5 shipped (session 33; `print_shipped_predictions`) and when PB5
/// shipped (session 35, trained on push_buttons' expert version 2).
const OPEN_DRAWER: [f32; 3] = [0.45154577, 0.020214975, 0.9935826];
const PUSH_BUTTONS: [f32; 3] = [0.61743826, -0.1320542, 0.8427131];
const SLIDE_BLOCK: [f32; 3] = [0.50689334, -0.027027965, 0.8722242];
const CLOSE_JAR: [f32; 3] = [0.60629326, 0.16322964, 0.8797106];
const STACK_BLOCKS: [f32; 3] = [0.5752674, -0.19549918, 0.88901144];
const SHIPPED_PREDICTIONS: [(&str, [f32; 3], f64); 5] = [
    ("open_drawer", OPEN_DRAWER, 6.1),
    ("push_buttons", PUSH_BUTTONS, 1.9),
    ("slide_block", SLIDE_BLOCK, 6.2),
    ("close_jar", CLOSE_JAR, 7.7),
    ("stack_blocks", STACK_BLOCKS, 16.1),
];

/// Each prediction is within [`REPRODUCE_MM`] of the one recorded when the checkpoint shipped,
/// and the expert is as far from it as it was then.
fn assert_reproduces(predictions: &[(&str, KeyframePose, KeyframePose)], recorded: &[[f32; 3]], expert_mm: &[f64]) {
    assert_eq!(predictions.len(), recorded.len());
    for (((task, predicted, expert), position), mm) in predictions.iter().zip(recorded).zip(expert_mm) {
        let recorded = KeyframePose { position: *position, ..*predicted };
        let moved = distance_mm(predicted, &recorded);
        assert!(
            moved < REPRODUCE_MM,
            "{task}: predicted {:?}, shipped {:?} ({moved:.1} mm apart)",
            predicted.position,
            recorded.position
        );
        assert!((distance_mm(predicted, expert) - mm).abs() < REPRODUCE_MM, "{task}: the expert moved");
    }
}

/// How far a prediction may move from the recorded one: float sums differ between the AVX-512
/// and AVX2 kernels, which can flip a geometric token at the edge of r(t). A broken checkpoint or
/// inference path moves it by centimetres.
const REPRODUCE_MM: f64 = 5.0;

fn shipped_first_keyframes() -> Vec<(&'static str, KeyframePose, KeyframePose)> {
    first_keyframes("five-tasks", &["open_drawer", "push_buttons", "slide_block", "close_jar", "stack_blocks"])
}

fn first_keyframes(checkpoint: &str, task_names: &[&'static str]) -> Vec<(&'static str, KeyframePose, KeyframePose)> {
    let mut policy = load(checkpoint);
    let mut out = Vec::new();
    for &task in task_names {
        let variation = SEED as usize % tasks::by_name(task).unwrap().variation_count();
        let episode = expert(&policy, task, variation, SEED);
        let observation = Observation::from_episode(&episode, 0).unwrap();
        let predicted = first_keyframe(&mut policy, &observation);
        out.push((task, predicted, Observation::episode_action(&episode, 0)));
    }
    out
}

#[test]
fn the_shipped_checkpoint_predicts_what_it_predicted_when_shipped() {
    let predictions = shipped_first_keyframes();
    let names: Vec<&str> = predictions.iter().map(|p| p.0).collect();
    assert_eq!(names, SHIPPED_PREDICTIONS.map(|p| p.0));
    // Each first keyframe where it was when shipped (these single scenes are 1.9-16.1 mm off the
    // expert's; the model card has the held-out medians per task).
    assert_reproduces(&predictions, &SHIPPED_PREDICTIONS.map(|p| p.1), &SHIPPED_PREDICTIONS.map(|p| p.2));
}

/// The goal of the policy issue: every task's first keyframe within 2 cm. Met by the shipped
/// checkpoint at this seed from GUR (5.0-15.0 mm; with the posterior 4.0-9.4 mm) to session 32;
/// FT-X missed slide_block and stack_blocks (26 and 70 mm), so this test was run on demand until
/// GUR, and was again while LP5 was shipped (sessions 33-34: slide_block 107 mm, on the wrong
/// side of the block, and stack_blocks 20.2 mm). PB5 (session 35) meets it again: 1.9-16.1 mm.
#[test]
fn the_shipped_checkpoint_predicts_every_tasks_first_keyframe_within_2_cm() {
    let report: Vec<(&str, f64)> = shipped_first_keyframes()
        .iter()
        .map(|(task, predicted, expert)| (*task, distance_mm(predicted, expert)))
        .collect();
    let misses: Vec<_> = report.iter().filter(|(_, mm)| *mm > 20.0).collect();
    assert!(misses.is_empty(), "first keyframes further than 20 mm from the expert's: {misses:?} (all: {report:?})");
}

#[test]
fn changing_the_instruction_changes_the_drawer_the_policy_goes_to() {
    goes_to_the_drawer_it_is_told("five-tasks");
}

/// One held-out open_drawer scene: the same seed lays out the same cabinet whatever the
/// variation, and the variation only names the drawer to open. Told one drawer, then (same
/// scene) another, the checkpoint goes nearer the one it is told each time.
fn goes_to_the_drawer_it_is_told(checkpoint: &str) {
    let mut policy = load(checkpoint);
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
        "{checkpoint}: told {:?}, the policy went nearer the other drawer: {:?}",
        task.instruction(told),
        as_told.position
    );
    assert!(
        distance_mm(&as_swapped, &other_target) < distance_mm(&as_swapped, &told_target),
        "{checkpoint}: told {:?} in the same scene, the policy stayed nearer the first drawer: {:?}",
        task.instruction(other),
        as_swapped.position
    );
}

/// The ten-task checkpoint (the default for the tasks five-tasks was not trained on): each task's first keyframe at [`SEED`] as predicted when
/// it was shipped (world frame, m; 8 Euler steps, noise seed 0) and the expert's distance (mm;
/// stack_blocks' since its expert's right-to-left order, session 24: 368.1, was 310.5;
/// push_buttons' since its rings and colours, expert version 2, session 35: 281.4, was 259.7).
const TEN_TASK_PREDICTIONS: [[f32; 3]; 10] = [
    [0.4588564, 0.0090225935, 0.9868793],
    [0.5040264, 0.12719965, 0.8473029],
    [0.46374816, 0.037287593, 0.8641214],
    [0.48760766, 0.11482793, 0.8727117],
    [0.4185584, 0.13082051, 0.87970895],
    [0.47664893, -0.103936344, 0.95681745],
    [0.5104698, 0.13646221, 0.913029],
    [0.45658427, 0.010239124, 0.9932867],
    [0.41661796, -0.24974653, 0.88481104],
    [0.40696594, -0.40791106, 0.8853148],
];
const TEN_TASK_EXPERT_MM: [f64; 10] = [10.9, 281.4, 80.2, 132.3, 368.1, 93.6, 22.3, 7.2, 28.2, 13.7];

#[test]
fn the_ten_task_checkpoint_predicts_what_it_predicted_when_shipped() {
    let default = flowram::deps::models_dir().join("policy/pretrained/ten-tasks");
    assert!(default.join("ema.safetensors").is_file(), "the default checkpoint is missing");
    let predictions = first_keyframes("ten-tasks", &TEN_TASKS);
    assert_reproduces(&predictions, &TEN_TASK_PREDICTIONS, &TEN_TASK_EXPERT_MM);
    // where it is good it stays good: the drawers (open_drawer, put_item_in_drawer) within 2 cm
    for (task, predicted, expert) in &predictions {
        if task.contains("drawer") {
            assert!(
                distance_mm(predicted, expert) < 20.0,
                "{task}: {:.1} mm from the expert",
                distance_mm(predicted, expert)
            );
        }
    }
}

#[test]
fn the_ten_task_checkpoint_goes_to_the_drawer_it_is_told() {
    goes_to_the_drawer_it_is_told("ten-tasks");
}

/// `bench heldout`'s report: one row per held-out keyframe (tasks in name order, each task's
/// episodes and keyframes in order), whose expert positions, variations and seeds are the
/// episodes' own and whose errors the summaries (overall and per task, magnitude and signed
/// bias) are made of.
#[test]
fn the_heldout_report_lists_every_keyframe_with_the_errors_it_summarises() {
    use flowram::policy::training::data::TrainingData;
    use flowram::rollout::evaluation::heldout_errors;
    let mut policy = load("five-tasks");
    let train = vec![expert(&policy, "push_buttons", 0, 0), expert(&policy, "open_drawer", 0, 0)];
    let train = TrainingData::from_episodes(train).unwrap();
    let held = vec![
        expert(&policy, "push_buttons", 20, SEED),
        expert(&policy, "open_drawer", 1, SEED + 1),
        expert(&policy, "push_buttons", 0, SEED + 2),
    ];
    let held = TrainingData::from_episodes(held).unwrap();
    let report = heldout_errors(&mut policy, &train, &held, &SamplingOptions::new(2, 1, 0), &mut ()).unwrap();
    // Held out in the order push_buttons, open_drawer, push_buttons: the report goes by task name,
    // and within a task by the episodes' order (a stable sort keeps it).
    let mut expected: Vec<(String, usize, u64, usize, [f32; 3])> = held
        .episodes()
        .iter()
        .flat_map(|e| {
            (0..e.keyframes())
                .map(move |k| (e.task.clone(), e.variation, e.seed, k, Observation::episode_action(e, k).position))
        })
        .collect();
    expected.sort_by(|a, b| a.0.cmp(&b.0));
    assert_eq!(report.per_keyframe.len(), expected.len());
    assert_eq!(report.keyframes, expected.len());
    for (row, (task, variation, seed, k, position)) in report.per_keyframe.iter().zip(&expected) {
        assert_eq!(
            (&row.task, row.variation, row.seed, row.keyframe, row.expert_position),
            (task, *variation, *seed, *k, *position)
        );
        let d: f64 =
            (0..3).map(|i| f64::from(row.predicted_position[i] - row.expert_position[i]).powi(2)).sum::<f64>().sqrt();
        assert!((row.position_mm - d * 1e3).abs() < 1e-3, "{} mm against {} mm", row.position_mm, d * 1e3);
    }
    let rows: Vec<_> = report.per_keyframe.iter().collect();
    assert_summarises(&report.model, &rows, "all");
    assert_eq!(report.tasks.len(), 2);
    for task in &report.tasks {
        let rows: Vec<_> = report.per_keyframe.iter().filter(|r| r.task == task.task).collect();
        assert_summarises(&task.model, &rows, &task.task);
    }
}

/// `errors`' mean position error and signed bias are those of `rows`.
fn assert_summarises(
    errors: &flowram::rollout::evaluation::Errors,
    rows: &[&flowram::rollout::evaluation::HeldOutKeyframe],
    what: &str,
) {
    assert!(!rows.is_empty(), "{what}: no rows");
    let n = rows.len() as f64;
    let mean_mm = rows.iter().map(|r| r.position_mm).sum::<f64>() / n;
    assert!(
        (errors.position_mm_mean - mean_mm).abs() < 1e-6,
        "{what}: mean {} against {mean_mm}",
        errors.position_mm_mean
    );
    for i in 0..3 {
        let bias = rows.iter().map(|r| f64::from(r.predicted_position[i] - r.expert_position[i])).sum::<f64>() / n;
        assert!((errors.position_bias_mm[i] - bias * 1e3).abs() < 1e-3, "{what}: axis {i}");
    }
}
