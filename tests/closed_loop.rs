//! A learned policy closed loop: the episode loop that lets a policy choose keyframes from
//! rendered observations (replaying the expert through it succeeds and stops at success), the
//! conversion of rendered frames to the policy's observation (identical to the dataset path the
//! policy was trained on), and FlowRAM itself acting through the real control stack.
mod common;

use flowram::control::keyframe::Keyframe;
use flowram::policy::inference::{Policy, SamplingOptions};
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::policy::scene::observation::{Observation, is_detour, keyframe_index};
use flowram::rollout::RolloutError;
use flowram::rollout::episode::{
    Actor, KeyframeObservation, KeyframePolicy, Observer, Perturbation, RecoveryTarget, run_episode,
};
use flowram::rollout::learned::{FlowRamActor, policy_observation};
use flowram::sim::{CameraRig, Visuals};
use flowram::tasks::{self, TaskError};

/// Plays back recorded keyframes, and remembers what it was shown.
struct Replay {
    keyframes: Vec<[f32; 8]>,
    seen: Vec<[f32; 8]>,
}

impl KeyframePolicy for Replay {
    fn next_keyframe(
        &mut self,
        _instruction: &str,
        k: usize,
        observation: &KeyframeObservation,
    ) -> Result<Keyframe, RolloutError> {
        assert_eq!(k, self.seen.len(), "keyframes are asked for in order");
        self.seen.push(observation.proprio);
        let a = self.keyframes.get(k).ok_or(RolloutError::NoKeyframe)?;
        Ok(Keyframe {
            position: [a[0], a[1], a[2]].map(f64::from),
            quat_wxyz: [a[3], a[4], a[5], a[6]].map(f64::from),
            gripper_open: a[7] > 0.5,
        })
    }
}

#[test]
fn expert_keyframes_replayed_through_the_policy_loop_succeed_and_stop_there() {
    let task = tasks::by_name("push_buttons").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    let expert = run_episode(task.as_ref(), &mut world, 3, 7, Actor::Expert, None).unwrap();
    assert!(expert.success);
    let mut replay = Replay { keyframes: expert.actions.clone(), seen: Vec::new() };
    let mut rig = CameraRig::new(&world, 32, Visuals::Fast).unwrap();
    let mut observer = Observer { rig: &mut rig, cameras: vec![0] };
    // more keyframes allowed than recorded: the loop must stop at success, not ask for more
    let actor = Actor::Policy { policy: &mut replay, max_keyframes: expert.keyframes + 3 };
    let result = run_episode(task.as_ref(), &mut world, 3, 7, actor, Some(&mut observer)).unwrap();
    assert!(result.success, "problems: {:?}", result.problems);
    // the expert's last keyframe retreats after the last press: the loop stops before it
    assert_eq!(result.keyframes, expert.keyframes - 1);
    assert_eq!(replay.seen.len(), result.keyframes, "asked for keyframes after success");
    assert_eq!(result.observations.len(), result.keyframes);
    assert_eq!(result.actions[..], expert.actions[..result.keyframes]);
    assert!(result.observations.iter().all(|o| o.frames.len() == 1));
    // the policy saw the proprioception of each observation, and it changed as the arm moved
    assert_eq!(replay.seen, result.observations.iter().map(|o| o.proprio).collect::<Vec<_>>());
    assert_ne!(replay.seen[0], replay.seen[1]);
    // a bad variation is refused before anything runs
    let actor = Actor::Policy { policy: &mut replay, max_keyframes: 3 };
    assert!(matches!(
        run_episode(task.as_ref(), &mut world, 999, 7, actor, Some(&mut observer)),
        Err(RolloutError::Task(TaskError::BadVariation { .. }))
    ));
}

#[test]
fn perturbed_expert_adds_a_recovery_sample_before_each_approach_and_still_succeeds() {
    let task = tasks::by_name("push_buttons").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    // variation 20: two buttons, so the plan has two approaches (above each cap)
    let clean = run_episode(task.as_ref(), &mut world, 20, 5, Actor::Expert, None).unwrap();
    assert!(clean.success);
    let plan = &clean.actions;
    let approaches: Vec<usize> =
        (0..plan.len()).filter(|&k| k + 1 < plan.len() && plan[k][2] - plan[k + 1][2] >= 0.04).collect();
    assert_eq!(approaches, vec![0, 2], "above each cap, then the press");
    let always = |target| Perturbation {
        probability: 1.0,
        sigma_m: 0.03,
        target,
        grasp_probability: 0.0,
        detours: 1,
        yaw_sigma_deg: 0.0,
        shuffle_targets: false,
    };
    let run = |world: &mut _, target| {
        run_episode(task.as_ref(), world, 20, 5, Actor::PerturbedExpert(always(target)), None).unwrap()
    };
    let next = run(&mut world, RecoveryTarget::Next);
    assert!(next.success, "problems: {:?}", next.problems);
    assert_eq!(next.keyframes, clean.keyframes + approaches.len());
    assert_eq!(next.observations.len(), next.actions.len());
    // step j = approach k + (detours before it): the clean observation goes to the approach, the
    // detour's observation (off the approach, above it) goes on to the press, as the clean
    // observation at the approach does
    for (i, &k) in approaches.iter().enumerate() {
        let j = k + i;
        assert_eq!(next.actions[j], plan[k]);
        assert_eq!(next.actions[j + 1], plan[k + 1], "the detour's action is the keyframe after the approach");
        assert_eq!(next.actions[j + 2], plan[k + 1]);
        let seen = next.observations[j + 1].proprio;
        let off = (0..3).map(|d| (seen[d] - plan[k][d]).powi(2)).sum::<f32>().sqrt();
        assert!(off > 0.002 && off < 0.2, "the detour is {off} m from the approach keyframe");
        assert!(seen[2] >= plan[k][2] - 0.005, "detours go up, not down into the scene: {} vs {}", seen[2], plan[k][2]);
    }
    // without the detours' steps, the clean episode
    let mut undetoured = next.actions.clone();
    undetoured.dedup();
    assert_eq!(undetoured, clean.actions);
    // the detours are recognised from the actions alone (the keyframe index skips them)
    let flat: Vec<f32> = next.actions.iter().flatten().copied().collect();
    let detours: Vec<usize> = (0..next.actions.len()).filter(|&j| is_detour(&flat, j)).collect();
    assert_eq!(detours, approaches.iter().enumerate().map(|(i, &k)| k + i + 1).collect::<Vec<_>>());
    // a detour's sample stands in for the state after its approach: the same index as the
    // clean sample at the approach (start, detour near cap 1, above cap 1, pressed 1, detour near cap 2, above cap 2, pressed 2)
    let indices: Vec<usize> = (0..next.actions.len()).map(|j| keyframe_index(&flat, j)).collect();
    assert_eq!(indices, [0, 1, 1, 2, 3, 3, 4]);
    let clean_flat: Vec<f32> = clean.actions.iter().flatten().copied().collect();
    assert!((0..clean.actions.len()).all(|j| !is_detour(&clean_flat, j)), "no detour in the clean episode");
    // the approach target: the same detours (drawn from the episode seed), the approach as action
    let approach = run(&mut world, RecoveryTarget::Approach);
    assert!(approach.success);
    let seen =
        |r: &flowram::rollout::episode::EpisodeResult| r.observations.iter().map(|o| o.proprio).collect::<Vec<_>>();
    assert_eq!(seen(&approach), seen(&next));
    for (i, &k) in approaches.iter().enumerate() {
        assert_eq!(approach.actions[k + i + 1], plan[k]);
    }
    // never: the plain expert
    let never = Perturbation {
        probability: 0.0,
        sigma_m: 0.03,
        target: RecoveryTarget::Next,
        grasp_probability: 0.0,
        detours: 1,
        yaw_sigma_deg: 0.0,
        shuffle_targets: false,
    };
    let plain = run_episode(task.as_ref(), &mut world, 20, 5, Actor::PerturbedExpert(never), None).unwrap();
    assert_eq!(plain.actions, clean.actions);
    // out of range: a clear error, before anything runs
    for (probability, sigma_m, grasp_probability) in [(1.5, 0.03, 0.0), (0.5, f64::NAN, 0.0), (0.5, 0.03, -0.1)] {
        let bad = Perturbation {
            probability,
            sigma_m,
            target: RecoveryTarget::Next,
            grasp_probability,
            detours: 1,
            yaw_sigma_deg: 0.0,
            shuffle_targets: false,
        };
        let err =
            run_episode(task.as_ref(), &mut world, 20, 5, Actor::PerturbedExpert(bad), None).unwrap_err().to_string();
        assert!(err.contains("expected"), "{err}");
    }
}

#[test]
fn several_detours_per_approach_share_the_first_and_all_go_on_to_the_next_keyframe() {
    let task = tasks::by_name("push_buttons").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    let clean = run_episode(task.as_ref(), &mut world, 20, 5, Actor::Expert, None).unwrap();
    let plan = &clean.actions;
    let approaches = [0usize, 2]; // above each cap (the test above checks it)
    let with = |detours| Perturbation {
        probability: 1.0,
        sigma_m: 0.03,
        target: RecoveryTarget::Next,
        grasp_probability: 0.0,
        detours,
        yaw_sigma_deg: 0.0,
        shuffle_targets: false,
    };
    let one = run_episode(task.as_ref(), &mut world, 20, 5, Actor::PerturbedExpert(with(1)), None).unwrap();
    let three = run_episode(task.as_ref(), &mut world, 20, 5, Actor::PerturbedExpert(with(3)), None).unwrap();
    assert!(three.success, "problems: {:?}", three.problems);
    assert_eq!(three.keyframes, clean.keyframes + 3 * approaches.len());
    assert_eq!(three.observations.len(), three.actions.len());
    for (i, &k) in approaches.iter().enumerate() {
        // step j: the clean observation going to the approach, then three detours, then the
        // approach pose; every detour's action is the keyframe after the approach
        let j = k + 3 * i;
        assert_eq!(three.actions[j], plan[k]);
        for d in 1..=3 {
            assert_eq!(three.actions[j + d], plan[k + 1], "detour {d} of approach {k}");
            let seen = three.observations[j + d].proprio;
            let off = (0..3).map(|a| (seen[a] - plan[k][a]).powi(2)).sum::<f32>().sqrt();
            assert!(off > 0.002 && off < 0.2, "detour {d} of approach {k} is {off} m from it");
        }
        // the detours differ from each other
        assert_ne!(three.observations[j + 1].proprio, three.observations[j + 2].proprio);
        assert_ne!(three.observations[j + 2].proprio, three.observations[j + 3].proprio);
        // the first detour is the one a single-detour collection makes
        let first = |r: &flowram::rollout::episode::EpisodeResult, j: usize| r.observations[j].proprio;
        let reached = |p: [f32; 8], q: [f32; 8]| (0..3).all(|a| (p[a] - q[a]).abs() < 2e-3);
        assert!(reached(first(&three, j + 1), first(&one, k + i + 1)), "the first detour is drawn as before");
    }
    // the keyframe index skips every detour
    let flat: Vec<f32> = three.actions.iter().flatten().copied().collect();
    let indices: Vec<usize> = (0..three.actions.len()).map(|j| keyframe_index(&flat, j)).collect();
    assert_eq!(indices, [0, 1, 1, 1, 1, 2, 3, 3, 3, 3, 4]);
    // out of range: a clear error
    for detours in [0, Perturbation::MAX_DETOURS + 1] {
        let err = run_episode(task.as_ref(), &mut world, 20, 5, Actor::PerturbedExpert(with(detours)), None)
            .unwrap_err()
            .to_string();
        assert!(err.contains("detours") && err.contains("expected"), "{err}");
    }
}

#[test]
fn turned_detours_keep_their_positions_and_go_on_to_the_experts_yaw() {
    // stack_blocks variation 0, seed 7 (the missed-grasp test below): approaches above blocks
    let task = tasks::by_name("stack_blocks").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    let with = |yaw_sigma_deg| Perturbation {
        probability: 1.0,
        sigma_m: 0.03,
        target: RecoveryTarget::Next,
        grasp_probability: 0.0,
        detours: 1,
        yaw_sigma_deg,
        shuffle_targets: false,
    };
    let straight = run_episode(task.as_ref(), &mut world, 0, 7, Actor::PerturbedExpert(with(0.0)), None).unwrap();
    let turned = run_episode(task.as_ref(), &mut world, 0, 7, Actor::PerturbedExpert(with(15.0)), None).unwrap();
    assert!(turned.success, "problems: {:?}", turned.problems);
    // the same samples and actions: the turn changes what the detours see, not what is taught
    assert_eq!(turned.actions, straight.actions);
    let flat: Vec<f32> = turned.actions.iter().flatten().copied().collect();
    let detours: Vec<usize> = (0..turned.actions.len()).filter(|&j| is_detour(&flat, j)).collect();
    assert!(detours.len() >= 2, "a detour before each approach: {detours:?}");
    let yaw = |p: [f32; 8]| {
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(p[3], p[4], p[5], p[6]));
        (q * nalgebra::Vector3::x()).y.atan2((q * nalgebra::Vector3::x()).x).to_degrees()
    };
    let mut turns = Vec::new();
    for &j in &detours {
        let (a, b) = (straight.observations[j].proprio, turned.observations[j].proprio);
        let apart = (0..3).map(|d| (a[d] - b[d]).powi(2)).sum::<f32>().sqrt();
        assert!(apart < 0.003, "detour {j}: the turned detour is {apart} m from the straight one");
        let turn = (yaw(b) - yaw(a) + 540.0).rem_euclid(360.0) - 180.0;
        assert!(turn.abs() <= 2.5 * 15.0 + 2.0, "detour {j} turned {turn} deg, past 2.5 sigma");
        turns.push(turn);
        // the hand still points down
        let down = |p: [f32; 8]| {
            let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(p[3], p[4], p[5], p[6]));
            (q * nalgebra::Vector3::z()).z
        };
        assert!((down(a) - down(b)).abs() < 0.01, "detour {j}: a turn about the vertical only");
    }
    assert!(turns.iter().any(|t| t.abs() > 1.0), "some detour is turned: {turns:?}");
    // out of range: a clear error
    for bad in [-1.0, 30.0, f64::NAN] {
        let err = run_episode(task.as_ref(), &mut world, 0, 7, Actor::PerturbedExpert(with(bad)), None)
            .unwrap_err()
            .to_string();
        assert!(err.contains("turn") && err.contains("expected"), "{err}");
    }
}

#[test]
fn missed_grasps_are_recorded_with_a_reopening_and_the_episode_still_succeeds() {
    let task = tasks::by_name("stack_blocks").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    // variation 0: two blocks, so two grasps (the second keyframe of each block's six)
    let clean = run_episode(task.as_ref(), &mut world, 0, 7, Actor::Expert, None).unwrap();
    assert!(clean.success);
    let plan = &clean.actions;
    let grasps: Vec<usize> = (1..plan.len())
        .filter(|&k| plan[k - 1][2] - plan[k][2] >= 0.04 && plan[k - 1][7] == 1.0 && plan[k][7] == 0.0)
        .collect();
    assert_eq!(grasps, vec![1, 7], "down and close, at each block");
    let misses = Perturbation {
        probability: 0.0,
        sigma_m: 0.03,
        target: RecoveryTarget::Next,
        grasp_probability: 1.0,
        detours: 1,
        yaw_sigma_deg: 0.0,
        shuffle_targets: false,
    };
    let run = |world: &mut _| run_episode(task.as_ref(), world, 0, 7, Actor::PerturbedExpert(misses), None).unwrap();
    let missed = run(&mut world);
    assert!(missed.success, "problems: {:?}", missed.problems);
    assert!(missed.problems.is_empty(), "every keyframe reached, the missed grasps too: {:?}", missed.problems);
    assert_eq!(missed.keyframes, clean.keyframes + 2 * grasps.len());
    assert_eq!(missed.observations.len(), missed.actions.len());
    for (i, &k) in grasps.iter().enumerate() {
        let j = k + 2 * i;
        assert_eq!(missed.actions[j], plan[k], "from above the block: the grasp");
        assert_eq!(missed.actions[j + 1], plan[k - 1], "from the missed grasp: re-open above the block");
        assert_eq!(missed.actions[j + 2], plan[k], "then the grasp again");
        let seen = missed.observations[j + 1].proprio;
        assert_eq!(seen[7], 0.0, "the gripper is closed at the missed grasp");
        let beside = ((seen[0] - plan[k][0]).powi(2) + (seen[1] - plan[k][1]).powi(2)).sqrt();
        assert!((0.04..0.06).contains(&beside), "the missed grasp is {beside} m beside the grasp");
        assert!((seen[2] - plan[k][2]).abs() < 0.01, "at the grasp's height: {} vs {}", seen[2], plan[k][2]);
    }
    // a missed grasp's samples are keyframes (closed loop the policy makes them), not detours
    let flat: Vec<f32> = missed.actions.iter().flatten().copied().collect();
    assert!((0..missed.actions.len()).all(|j| !is_detour(&flat, j)));
    assert!((0..missed.actions.len()).all(|j| keyframe_index(&flat, j) == j));
    // the same misses again (drawn from the episode seed), and none without the option
    assert_eq!(run(&mut world).actions, missed.actions);
    let none = Perturbation { grasp_probability: 0.0, ..misses };
    let plain = run_episode(task.as_ref(), &mut world, 0, 7, Actor::PerturbedExpert(none), None).unwrap();
    assert_eq!(plain.actions, clean.actions);
    // seed 2 (seed 1 before the expert's right-to-left order): a missed grasp comes down beside
    // a neighbouring block and does not close on nothing; the episode is then no
    // demonstration, though the expert alone succeeds there
    assert!(run_episode(task.as_ref(), &mut world, 1, 2, Actor::Expert, None).unwrap().success);
    let touched = run_episode(task.as_ref(), &mut world, 1, 2, Actor::PerturbedExpert(misses), None).unwrap();
    assert!(!touched.success);
    assert!(touched.problems.iter().any(|(_, p)| p.contains("not closed on nothing")), "{:?}", touched.problems);
}

#[test]
fn shuffled_targets_stack_the_same_blocks_in_another_order_and_are_refused_where_order_matters() {
    let task = tasks::by_name("stack_blocks").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    // variation 2: four red blocks; no detours, so only the order differs from the expert's
    let shuffled = Perturbation {
        probability: 0.0,
        sigma_m: 0.03,
        target: RecoveryTarget::Next,
        grasp_probability: 0.0,
        detours: 1,
        yaw_sigma_deg: 0.0,
        shuffle_targets: true,
    };
    let picks = |actions: &[[f32; 8]]| -> Vec<[f32; 2]> {
        // above each block: keyframes 0, 6, 12, 18 of the pick-and-place plan
        actions.iter().step_by(6).map(|a| [a[0], a[1]]).collect()
    };
    // seed 12: a shuffled order can fail its expert run (collections need about 1 attempt in 60-300
    // more than their episodes); seed 11, used until session 39, is such a seed since the OSC
    // skips OSQP where no row is active (its first grasp settles 2 cm off), seeds 12-30 are not
    let clean = run_episode(task.as_ref(), &mut world, 2, 12, Actor::Expert, None).unwrap();
    let other = run_episode(task.as_ref(), &mut world, 2, 12, Actor::PerturbedExpert(shuffled), None).unwrap();
    assert!(clean.success && other.success, "problems: {:?} {:?}", clean.problems, other.problems);
    assert_eq!(clean.keyframes, 24);
    assert_eq!(other.keyframes, clean.keyframes);
    let (a, b) = (picks(&clean.actions), picks(&other.actions));
    assert_ne!(a, b, "seed 12's draw takes the blocks in another order");
    let sorted = |mut v: Vec<[f32; 2]>| {
        v.sort_by(|p, q| p[1].total_cmp(&q[1]));
        v
    };
    for (p, q) in sorted(a).iter().zip(sorted(b)) {
        assert!((p[0] - q[0]).abs() < 1e-3 && (p[1] - q[1]).abs() < 1e-3, "the same four blocks: {p:?} {q:?}");
    }
    // the same seed shuffles the same way
    let again = run_episode(task.as_ref(), &mut world, 2, 12, Actor::PerturbedExpert(shuffled), None).unwrap();
    assert_eq!(again.actions, other.actions);
    // push_buttons' order is the instruction's: refused, with what to do
    let buttons = tasks::by_name("push_buttons").unwrap();
    let mut world = tasks::load_world(buttons.as_ref()).unwrap();
    let err = run_episode(buttons.as_ref(), &mut world, 20, 5, Actor::PerturbedExpert(shuffled), None).unwrap_err();
    assert!(matches!(err, RolloutError::Perturbation { .. }));
    assert!(err.to_string().contains("without --shuffle-targets"), "{err}");
}

#[test]
fn rendered_frames_become_the_same_observation_as_the_dataset_path() {
    let task = tasks::by_name("open_drawer").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    let mut rig = CameraRig::new(&world, 48, Visuals::Fast).unwrap();
    let cameras = vec![rig.camera_index("front").unwrap(), rig.camera_index("wrist").unwrap()];
    let mut observer = Observer { rig: &mut rig, cameras };
    let result = run_episode(task.as_ref(), &mut world, 1, 2, Actor::Expert, Some(&mut observer)).unwrap();
    let episode = result.to_dataset_episode().unwrap();
    for k in [0, result.observations.len() - 1] {
        let from_dataset = Observation::from_episode(&episode, k).unwrap();
        let history: Vec<[f32; 8]> = result.observations[..k].iter().rev().map(|o| o.proprio).collect();
        let live = policy_observation(&result.episode.instruction, k, &result.observations[k], &history).unwrap();
        assert_eq!(live.size, from_dataset.size);
        assert_eq!(live.proprio, from_dataset.proprio);
        assert_eq!(live.instruction, from_dataset.instruction);
        assert_eq!(live.keyframe, from_dataset.keyframe);
        assert_eq!(live.history, from_dataset.history);
        assert_eq!(live.history.len(), k);
        assert_eq!(live.cameras.len(), 2);
        for (a, b) in live.cameras.iter().zip(&from_dataset.cameras) {
            assert_eq!(a.rgb, b.rgb);
            assert_eq!(a.depth, b.depth);
            assert_eq!(a.intrinsics, b.intrinsics);
            assert_eq!(a.camera_to_world, b.camera_to_world);
        }
    }
    let empty = KeyframeObservation { frames: Vec::new(), proprio: [0.0; 8] };
    let err = policy_observation("open the top drawer", 0, &empty, &[]).unwrap_err().to_string();
    assert!(err.contains("camera"), "{err}");
}

#[test]
fn flowram_acts_closed_loop_through_the_control_stack() {
    let config = common::tiny_policy_config();
    let text = TextEncoder::load_installed().unwrap();
    let policy = Policy::random(&config, text).unwrap();
    let options = SamplingOptions::new(2, 1, 5);
    let mut actor = FlowRamActor::new(policy, options);
    let task = tasks::by_name("slide_block").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    let mut rig = CameraRig::new(&world, 48, Visuals::Fast).unwrap();
    let cameras = vec![rig.camera_index("front").unwrap(), rig.camera_index("left_shoulder").unwrap()];
    let mut observer = Observer { rig: &mut rig, cameras };
    let result = run_episode(
        task.as_ref(),
        &mut world,
        0,
        1,
        Actor::Policy { policy: &mut actor, max_keyframes: 2 },
        Some(&mut observer),
    )
    .unwrap();
    // an untrained policy does not slide the block: both keyframes were asked for and executed
    assert!(!result.success);
    assert_eq!(result.keyframes, 2);
    assert_eq!(actor.inference_ms.len(), 2);
    assert_eq!(result.actions.len(), 2);
    for a in &result.actions {
        assert!(a.iter().all(|v| v.is_finite()), "{a:?}");
        let q_norm: f32 = a[3..7].iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!((q_norm - 1.0).abs() < 1e-3, "quaternion norm {q_norm}");
    }
    // the noise seed advances per keyframe, so two predictions from similar observations differ
    assert_ne!(result.actions[0], result.actions[1]);
    // and restarts per episode: the same seeded episode again gives the same keyframes
    let again = run_episode(
        task.as_ref(),
        &mut world,
        0,
        1,
        Actor::Policy { policy: &mut actor, max_keyframes: 2 },
        Some(&mut observer),
    )
    .unwrap();
    assert_eq!(again.actions, result.actions);
    // the gripper history restarts per episode too: the second episode's two observations only
    let seen: Vec<[f32; 8]> = again.observations[..2].iter().rev().map(|o| o.proprio).collect();
    assert_eq!(actor.history(), &seen[..]);
}

#[test]
fn no_expert_repeats_a_keyframe_so_a_repeat_marks_a_detour() {
    use rand::SeedableRng;
    // `is_detour` tells a recovery detour by an action equal to the next sample's: every
    // task's expert plan must be free of consecutive repeats for that to hold
    for task in tasks::all() {
        let mut world = tasks::load_world(task.as_ref()).unwrap();
        let count = task.variation_count();
        for (seed, variation) in (0..6u64).zip([0, count / 3, count / 2, 2 * count / 3, count - 1, 1 % count]) {
            world.reset_to("home").unwrap();
            let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
            let state = task.reset(&mut world, variation, &mut rng).unwrap();
            let plan = task.expert(&world, &state).unwrap();
            for pair in plan.windows(2) {
                assert_ne!(pair[0], pair[1], "{} variation {variation} seed {seed} repeats a keyframe", task.name());
            }
        }
    }
}
