//! Tasks: instructions follow the paper's templates, experts solve their tasks closed loop,
//! doing nothing does not succeed, and demonstrations record what the arm really did.
use flowram::rollout::episode::{Actor, Observer, run_episode};
use flowram::sim::{CameraRig, Visuals};
use flowram::tasks::{self, Task};

fn matches_template(instruction: &str, template: &str, words: &[&str]) -> bool {
    let (head, tail) = template.split_once('_').expect("template has a blank");
    instruction.strip_prefix(head).and_then(|rest| rest.strip_suffix(tail)).is_some_and(|w| words.contains(&w))
}

#[test]
fn instructions_follow_the_templates() {
    let colors: Vec<&str> = flowram::tasks::colors::COLORS.iter().map(|c| c.0).collect();
    let drawers = tasks::by_name("open_drawer").unwrap();
    assert_eq!(drawers.variation_count(), 3);
    for v in 0..3 {
        assert!(
            matches_template(&drawers.instruction(v), "open the _ drawer", &["left", "middle", "right"]),
            "{}",
            drawers.instruction(v)
        );
    }
    let buttons = tasks::by_name("push_buttons").unwrap();
    assert_eq!(buttons.variation_count(), 50);
    let mut seen = std::collections::HashSet::new();
    for v in 0..50 {
        let text = buttons.instruction(v);
        let parts: Vec<&str> = text.split(", then ").collect();
        assert!((1..=3).contains(&parts.len()), "{text}");
        assert!(parts.iter().all(|p| matches_template(p, "push the _ button", &colors)), "{text}");
        // red and lime are the rings' colours (unpressed, pressed), never a button's name
        assert!(parts.iter().all(|p| !p.contains(" red ") && !p.contains(" lime ")), "{text}");
        assert!(seen.insert(text.clone()), "variation {v} repeats an instruction: {text}");
    }
    let jars = tasks::by_name("close_jar").unwrap();
    assert_eq!(jars.variation_count(), 20);
    assert!((0..20).all(|v| matches_template(&jars.instruction(v), "close the _ jar", &colors)));
    let slide = tasks::by_name("slide_block").unwrap();
    assert_eq!(slide.variation_count(), 4);
    assert!((0..4).all(|v| matches_template(
        &slide.instruction(v),
        "slide the block to _ target",
        &["green", "blue", "pink", "yellow"]
    )));
    let stack = tasks::by_name("stack_blocks").unwrap();
    assert_eq!(stack.variation_count(), 60);
    for v in 0..60 {
        let text = stack.instruction(v);
        let rest =
            text.strip_prefix("stack ").and_then(|r| r.strip_suffix(" blocks")).unwrap_or_else(|| panic!("{text}"));
        let (count, colour) = rest.split_once(' ').unwrap();
        assert!(["2", "3", "4"].contains(&count) && colors.contains(&colour), "{text}");
    }
    let grill = tasks::by_name("meat_off_grill").unwrap();
    assert_eq!(grill.variation_count(), 2);
    assert!((0..2).all(|v| matches_template(&grill.instruction(v), "take the _ off the grill", &["chicken", "steak"])));
    let tap = tasks::by_name("turn_tap").unwrap();
    assert_eq!(tap.variation_count(), 2);
    assert!((0..2).all(|v| matches_template(&tap.instruction(v), "turn _ tap", &["left", "right"])));
    let put = tasks::by_name("put_item_in_drawer").unwrap();
    assert_eq!(put.variation_count(), 3);
    assert!((0..3).all(|v| matches_template(
        &put.instruction(v),
        "put the item in the _ drawer",
        &["left", "middle", "right"]
    )));
    let drag = tasks::by_name("drag_stick").unwrap();
    assert_eq!(drag.variation_count(), 20);
    assert!((0..20).all(|v| matches_template(
        &drag.instruction(v),
        "use the stick to drag the cube onto the _ target",
        &colors
    )));
    let sweep = tasks::by_name("sweep_to_dustpan").unwrap();
    assert_eq!(sweep.variation_count(), 2);
    assert!((0..2).all(|v| matches_template(&sweep.instruction(v), "sweep dirt to the _ dustpan", &["short", "tall"])));
    let err = tasks::by_name("juggle").err().unwrap().to_string();
    assert!(err.contains("open_drawer") && err.contains("push_buttons"), "{err}");
}

fn success_rate(task: &dyn Task, actor: fn() -> Actor<'static>, episodes: u64) -> usize {
    let mut world = tasks::load_world(task).unwrap();
    (0..episodes)
        .filter(|&seed| {
            let variation = (seed as usize * 7) % task.variation_count();
            run_episode(task, &mut world, variation, seed, actor(), None).unwrap().success
        })
        .count()
}

#[test]
fn push_buttons_expert_succeeds_and_idling_does_not() {
    let task = tasks::by_name("push_buttons").unwrap();
    let expert = success_rate(task.as_ref(), || Actor::Expert, 10);
    assert!(expert >= 9, "expert solved {expert}/10");
    assert_eq!(success_rate(task.as_ref(), || Actor::Idle { seconds: 2 }, 10), 0);
}

/// A press counts once the cap is down 3 mm (RLBench's `JointCondition(.., 0.003)`), and the
/// presses must be the instructed colours in order. A pressed button's housing ring turns from
/// red to lime and stays lime, as RLBench's top plate and wrapper do, so the scene shows it.
#[test]
fn push_buttons_counts_presses_past_3_mm_in_the_instructed_order() {
    use rand::SeedableRng;
    const RED: [f32; 4] = [1.0, 0.0, 0.0, 1.0];
    const LIME: [f32; 4] = [0.0, 1.0, 0.0, 1.0];
    let task = tasks::by_name("push_buttons").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    world.reset_to("home").unwrap();
    // Variation 18: push colour 0, then colour 1.
    let mut state = task.reset(&mut world, 18, &mut rand::rngs::StdRng::seed_from_u64(3)).unwrap();
    assert_eq!(task.instruction(18), "push the maroon button, then push the green button");
    let [first, second] = [state.targets[0].clone(), state.targets[1].clone()];
    let press = |world: &mut flowram::sim::World, button: &str, depth_mm: f64| {
        world.set_joint_position(&format!("{button}_press"), -depth_mm * 1e-3).unwrap();
    };
    let ring = |world: &flowram::sim::World, button: &str| world.geom_rgba(&format!("{button}_housing")).unwrap();
    for i in 0..3 {
        assert_eq!(ring(&world, &format!("button_{i}")), RED, "button_{i} before any press");
    }
    press(&mut world, &first, 2.5);
    task.observe(&mut world, &mut state).unwrap();
    assert!(state.events.is_empty(), "2.5 mm is not a press: {:?}", state.events);
    assert_eq!(ring(&world, &first), RED, "2.5 mm does not turn the ring");
    press(&mut world, &first, 3.5);
    task.observe(&mut world, &mut state).unwrap();
    assert_eq!(state.events, std::slice::from_ref(&first));
    assert_eq!(ring(&world, &first), LIME);
    assert_eq!(ring(&world, &second), RED, "only the pressed button turns");
    assert!(!task.success(&world, &state), "one of two buttons pushed");
    press(&mut world, &first, 0.0);
    press(&mut world, &second, 3.5);
    task.observe(&mut world, &mut state).unwrap();
    assert!(task.success(&world, &state), "{:?}", state.events);
    assert_eq!([ring(&world, &first), ring(&world, &second)], [LIME, LIME], "a sprung-back button stays lime");
    // The same presses the other way round fail; a reset turns the rings red again.
    let mut state = task.reset(&mut world, 18, &mut rand::rngs::StdRng::seed_from_u64(3)).unwrap();
    assert_eq!([ring(&world, &first), ring(&world, &second)], [RED, RED], "reset");
    for button in [&second, &first] {
        press(&mut world, button, 8.0);
        task.observe(&mut world, &mut state).unwrap();
        press(&mut world, button, 0.0);
    }
    assert_eq!(state.events, [second, first]);
    assert!(!task.success(&world, &state));
}

#[test]
fn close_jar_expert_succeeds_and_idling_does_not() {
    let task = tasks::by_name("close_jar").unwrap();
    let expert = success_rate(task.as_ref(), || Actor::Expert, 10);
    assert!(expert >= 9, "expert solved {expert}/10");
    assert_eq!(success_rate(task.as_ref(), || Actor::Idle { seconds: 2 }, 10), 0);
}

#[test]
fn stack_blocks_expert_succeeds_and_idling_does_not() {
    let task = tasks::by_name("stack_blocks").unwrap();
    let expert = success_rate(task.as_ref(), || Actor::Expert, 10);
    assert!(expert >= 9, "expert solved {expert}/10");
    assert_eq!(success_rate(task.as_ref(), || Actor::Idle { seconds: 2 }, 10), 0);
}

#[test]
fn stack_blocks_takes_the_target_colour_blocks_right_to_left() {
    use rand::SeedableRng;
    let task = tasks::by_name("stack_blocks").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    let y = |world: &flowram::sim::World, name: &str| world.body_pose(name).unwrap().translation.y;
    for seed in 0..30u64 {
        let variation = (seed as usize * 7) % 60;
        let state = task.reset(&mut world, variation, &mut rand::rngs::StdRng::seed_from_u64(seed)).unwrap();
        assert_eq!(state.targets.len(), variation % 3 + 2, "the instruction's count");
        // block_0..block_3 carry the target colour (the task's reset)
        let same_colour: Vec<String> = (0..4).map(|i| format!("block_{i}")).collect();
        assert!(state.targets.iter().all(|t| same_colour.contains(t)), "{:?}", state.targets);
        let ys: Vec<f64> = state.targets.iter().map(|t| y(&world, t)).collect();
        // right to left, y compared to the rule's 0.1 mm
        assert!(ys.windows(2).all(|w| w[0] < w[1] + 1e-4), "seed {seed}: targets not right to left: {ys:?}");
        let last = *ys.last().unwrap();
        for rest in same_colour.iter().filter(|b| !state.targets.contains(b)) {
            assert!(y(&world, rest) > last - 1e-4, "seed {seed}: {rest} is right of a block that is stacked before it");
        }
    }
}

#[test]
fn world_objects_are_the_loose_blocks_where_they_lie_with_their_colours() {
    use rand::SeedableRng;
    let task = tasks::by_name("stack_blocks").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    task.reset(&mut world, 7, &mut rand::rngs::StdRng::seed_from_u64(3)).unwrap();
    let objects = world.objects();
    let names: Vec<&str> = objects.iter().map(|o| o.name.as_str()).collect();
    // the platform and the robot are fixed: only the six blocks have free joints
    assert_eq!(names, ["block_0", "block_1", "block_2", "block_3", "block_4", "block_5"]);
    for o in &objects {
        let p = world.body_pose(&o.name).unwrap().translation.vector;
        assert!((p - nalgebra::Vector3::from(o.position)).norm() < 1e-12, "{}: {:?} vs {p}", o.name, o.position);
    }
    // block_0..block_3 carry the target colour, block_4 and block_5 others
    assert!(objects[..4].iter().all(|o| o.rgba == objects[0].rgba), "{objects:?}");
    assert!(objects[4..].iter().all(|o| o.rgba != objects[0].rgba), "{objects:?}");
}

#[test]
fn slide_block_expert_succeeds_and_idling_does_not() {
    let task = tasks::by_name("slide_block").unwrap();
    let expert = success_rate(task.as_ref(), || Actor::Expert, 10);
    assert!(expert >= 9, "expert solved {expert}/10");
    assert_eq!(success_rate(task.as_ref(), || Actor::Idle { seconds: 2 }, 10), 0);
}

#[test]
fn open_drawer_expert_succeeds_and_idling_does_not() {
    let task = tasks::by_name("open_drawer").unwrap();
    let expert = success_rate(task.as_ref(), || Actor::Expert, 10);
    assert!(expert >= 9, "expert solved {expert}/10");
    assert_eq!(success_rate(task.as_ref(), || Actor::Idle { seconds: 2 }, 10), 0);
}

#[test]
fn meat_off_grill_expert_succeeds_and_idling_does_not() {
    let task = tasks::by_name("meat_off_grill").unwrap();
    let expert = success_rate(task.as_ref(), || Actor::Expert, 10);
    assert!(expert >= 9, "expert solved {expert}/10");
    assert_eq!(success_rate(task.as_ref(), || Actor::Idle { seconds: 2 }, 10), 0);
}

#[test]
fn meat_off_grill_success_rejects_near_misses() {
    use nalgebra::{Isometry3, Translation3};
    use rand::SeedableRng;
    let task = tasks::by_name("meat_off_grill").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    world.reset_to("home").unwrap();
    let state = task.reset(&mut world, 0, &mut rand::rngs::StdRng::seed_from_u64(3)).unwrap();
    assert_eq!(state.targets, ["chicken", "steak"]);
    assert!(!task.success(&world, &state), "nothing moved yet");
    let plate = world.body_pose("plate").unwrap().translation.vector;
    let at = |x: f64, y: f64, z: f64| Isometry3::from(Translation3::new(x, y, z));
    // The chicken (3 cm high) resting on the plate's top (1 cm above the table at 0.75 m).
    world.set_body_pose("chicken", &at(plate.x + 0.02, plate.y, 0.775)).unwrap();
    assert!(task.success(&world, &state), "the named item on the plate, the other on the grill");
    // Held 5 cm above the plate: not resting on it.
    world.set_body_pose("chicken", &at(plate.x, plate.y, 0.825)).unwrap();
    assert!(!task.success(&world, &state));
    // On the table beside the plate.
    world.set_body_pose("chicken", &at(plate.x, plate.y + 0.12, 0.765)).unwrap();
    assert!(!task.success(&world, &state));
    // On the plate, but the steak came off the grill too.
    world.set_body_pose("chicken", &at(plate.x, plate.y, 0.775)).unwrap();
    world.set_body_pose("steak", &at(plate.x + 0.3, plate.y, 0.76)).unwrap();
    assert!(!task.success(&world, &state));
    // The other item taken off instead.
    let wrong = task.reset(&mut world, 1, &mut rand::rngs::StdRng::seed_from_u64(3)).unwrap();
    let plate = world.body_pose("plate").unwrap().translation.vector;
    world.set_body_pose("chicken", &at(plate.x, plate.y, 0.775)).unwrap();
    assert!(!task.success(&world, &wrong), "told to take the steak, the chicken is on the plate");
}

#[test]
fn turn_tap_expert_succeeds_and_idling_does_not() {
    let task = tasks::by_name("turn_tap").unwrap();
    let expert = success_rate(task.as_ref(), || Actor::Expert, 10);
    assert!(expert >= 9, "expert solved {expert}/10");
    assert_eq!(success_rate(task.as_ref(), || Actor::Idle { seconds: 2 }, 10), 0);
}

#[test]
fn turn_tap_success_needs_the_named_handle_turned_past_85_degrees() {
    use rand::SeedableRng;
    let task = tasks::by_name("turn_tap").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    world.reset_to("home").unwrap();
    let state = task.reset(&mut world, 1, &mut rand::rngs::StdRng::seed_from_u64(5)).unwrap();
    assert_eq!(state.targets, ["right"]);
    for (left, right, expected) in [(0.0, 30.0, false), (0.0, 80.0, false), (100.0, 0.0, false), (0.0, 95.0, true)] {
        world.set_joint_position("left_tap_hinge", f64::to_radians(left)).unwrap();
        world.set_joint_position("right_tap_hinge", f64::to_radians(right)).unwrap();
        assert_eq!(task.success(&world, &state), expected, "left {left} deg, right {right} deg");
    }
}

#[test]
fn put_item_in_drawer_expert_succeeds_and_idling_does_not() {
    let task = tasks::by_name("put_item_in_drawer").unwrap();
    let expert = success_rate(task.as_ref(), || Actor::Expert, 10);
    assert!(expert >= 9, "expert solved {expert}/10");
    assert_eq!(success_rate(task.as_ref(), || Actor::Idle { seconds: 2 }, 10), 0);
}

#[test]
fn put_item_in_drawer_success_needs_the_item_inside_the_named_drawer() {
    use nalgebra::{Isometry3, Point3, Translation3};
    use rand::SeedableRng;
    let task = tasks::by_name("put_item_in_drawer").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    world.reset_to("home").unwrap();
    let state = task.reset(&mut world, 0, &mut rand::rngs::StdRng::seed_from_u64(2)).unwrap();
    assert_eq!(state.targets, ["left"]);
    assert!(!task.success(&world, &state), "the item starts on the cabinet");
    for drawer in ["left", "middle"] {
        world.set_joint_position(&format!("{drawer}_drawer_slide"), 0.15).unwrap();
    }
    let place = |world: &mut flowram::sim::World, drawer: &str, local: [f64; 3]| {
        let frame = world.body_pose(&format!("{drawer}_drawer")).unwrap();
        let p = frame * Point3::from(local);
        world.set_body_pose("item", &Isometry3::from(Translation3::from(p.coords))).unwrap();
    };
    // On the floor of the open left drawer (floor top at z = -0.051 in the drawer's frame).
    place(&mut world, "left", [-0.09, 0.0, -0.031]);
    assert!(task.success(&world, &state));
    // In the middle drawer instead.
    place(&mut world, "middle", [-0.09, 0.0, -0.031]);
    assert!(!task.success(&world, &state));
    // On the cabinet's top right above the left drawer, not inside it.
    place(&mut world, "left", [0.05, 0.0, 0.095]);
    assert!(!task.success(&world, &state));
    // In front of the drawer, on the table.
    place(&mut world, "left", [-0.25, 0.0, -0.105]);
    assert!(!task.success(&world, &state));
}

#[test]
fn drag_stick_expert_succeeds_and_idling_does_not() {
    let task = tasks::by_name("drag_stick").unwrap();
    let expert = success_rate(task.as_ref(), || Actor::Expert, 10);
    assert!(expert >= 9, "expert solved {expert}/10");
    assert_eq!(success_rate(task.as_ref(), || Actor::Idle { seconds: 2 }, 10), 0);
}

#[test]
fn drag_stick_success_needs_the_cube_on_the_named_target() {
    use nalgebra::{Isometry3, Translation3};
    use rand::SeedableRng;
    let task = tasks::by_name("drag_stick").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    world.reset_to("home").unwrap();
    let state = task.reset(&mut world, 4, &mut rand::rngs::StdRng::seed_from_u64(8)).unwrap();
    assert!(!task.success(&world, &state), "the cube starts off the targets");
    let named = world.body_pose(&state.targets[0]).unwrap().translation.vector;
    let other = if state.targets[0] == "target_0" { "target_1" } else { "target_0" };
    let other = world.body_pose(other).unwrap().translation.vector;
    let put = |world: &mut flowram::sim::World, x: f64, y: f64, z: f64| {
        world.set_body_pose("cube", &Isometry3::from(Translation3::new(x, y, z))).unwrap();
    };
    put(&mut world, named.x + 0.03, named.y - 0.02, 0.77);
    assert!(task.success(&world, &state));
    put(&mut world, other.x, other.y, 0.77);
    assert!(!task.success(&world, &state), "on the other colour's target");
    put(&mut world, (named.x + other.x) / 2.0, named.y, 0.77);
    assert!(!task.success(&world, &state), "between the targets");
    put(&mut world, named.x, named.y, 0.85);
    assert!(!task.success(&world, &state), "above the target, not on the table");
}

#[test]
fn sweep_to_dustpan_expert_succeeds_and_idling_does_not() {
    let task = tasks::by_name("sweep_to_dustpan").unwrap();
    let expert = success_rate(task.as_ref(), || Actor::Expert, 10);
    assert!(expert >= 9, "expert solved {expert}/10");
    assert_eq!(success_rate(task.as_ref(), || Actor::Idle { seconds: 2 }, 10), 0);
}

#[test]
fn sweep_to_dustpan_success_needs_all_the_dirt_in_the_named_pan() {
    use nalgebra::{Isometry3, Point3, Translation3};
    use rand::SeedableRng;
    let task = tasks::by_name("sweep_to_dustpan").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    world.reset_to("home").unwrap();
    let state = task.reset(&mut world, 1, &mut rand::rngs::StdRng::seed_from_u64(6)).unwrap();
    assert_eq!(state.targets[0], "tall_dustpan");
    assert!(!task.success(&world, &state), "the dirt starts between the pans");
    let fill = |world: &mut flowram::sim::World, pan: &str, pieces: std::ops::Range<usize>| {
        let frame = world.body_pose(pan).unwrap();
        for i in pieces {
            let p = frame * Point3::new(-0.04 + 0.02 * i as f64, 0.0, 0.006);
            world.set_body_pose(&format!("dirt_{i}"), &Isometry3::from(Translation3::from(p.coords))).unwrap();
        }
    };
    fill(&mut world, "short_dustpan", 0..5);
    assert!(!task.success(&world, &state), "all in the other pan");
    fill(&mut world, "tall_dustpan", 0..4);
    assert!(!task.success(&world, &state), "one piece still in the short pan");
    fill(&mut world, "tall_dustpan", 4..5);
    assert!(task.success(&world, &state));
    let frame = world.body_pose("tall_dustpan").unwrap();
    let outside = frame * Point3::new(0.0, -0.07, 0.006);
    world.set_body_pose("dirt_2", &Isometry3::from(Translation3::from(outside.coords))).unwrap();
    assert!(!task.success(&world, &state), "one piece just in front of the pan");
}

/// The lime rings reach the cameras: pressing the buttons adds lime pixels to the front camera's
/// frame (the palette has no lime cap, so a fresh scene has none).
#[test]
fn pressed_buttons_show_lime_rings_to_the_front_camera() {
    use rand::SeedableRng;
    let task = tasks::by_name("push_buttons").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    let mut rig = CameraRig::new(&world, 128, Visuals::Fast).unwrap();
    let front = rig.camera_index("front").unwrap();
    let lime_pixels = |rgb: &[u8]| {
        rgb.chunks_exact(3).filter(|p| p[1] > 170 && u16::from(p[0]) + u16::from(p[2]) < u16::from(p[1]) / 2).count()
    };
    let mut state = None;
    for v in 0..50 {
        world.reset_to("home").unwrap();
        let s = task.reset(&mut world, v, &mut rand::rngs::StdRng::seed_from_u64(v as u64)).unwrap();
        let before = lime_pixels(&rig.render(&mut world, front).unwrap().rgb);
        assert_eq!(before, 0, "variation {v}: lime before any press");
        state = Some(s);
    }
    let mut state = state.unwrap();
    for i in 0..3 {
        world.set_joint_position(&format!("button_{i}_press"), -0.005).unwrap();
        task.observe(&mut world, &mut state).unwrap();
        world.set_joint_position(&format!("button_{i}_press"), 0.0).unwrap();
    }
    let after = lime_pixels(&rig.render(&mut world, front).unwrap().rgb);
    assert!(after >= 30, "three pressed rings show {after} lime pixels at 128 px");
}

#[test]
fn recorded_actions_are_the_poses_the_arm_reached() {
    let task = tasks::by_name("push_buttons").unwrap();
    let mut world = tasks::load_world(task.as_ref()).unwrap();
    let mut rig = CameraRig::new(&world, 64, Visuals::Fast).unwrap();
    let cameras = vec![rig.camera_index("front").unwrap(), rig.camera_index("wrist").unwrap()];
    let mut observer = Observer { rig: &mut rig, cameras };
    let result = run_episode(task.as_ref(), &mut world, 27, 4, Actor::Expert, Some(&mut observer)).unwrap();
    assert!(result.success);
    let k = result.keyframes;
    assert!(k >= 5 && result.observations.len() == k && result.actions.len() == k);
    for i in 0..k {
        let (a, r) = (&result.actions[i], &result.reached_poses[i]);
        let dp = ((a[0] - r[0]).powi(2) + (a[1] - r[1]).powi(2) + (a[2] - r[2]).powi(2)).sqrt();
        let dot = (a[3] * r[3] + a[4] * r[4] + a[5] * r[5] + a[6] * r[6]).abs().min(1.0);
        let angle = 2.0 * dot.acos();
        assert!(
            dp <= 1.5e-3 && angle <= 0.5f32.to_radians() * 1.5,
            "keyframe {i}: reached {dp} m / {angle} rad from the recorded action"
        );
        assert_eq!(a[7], r[7], "gripper state of keyframe {i}");
        if i + 1 < k {
            assert_eq!(
                &result.observations[i + 1].proprio,
                r,
                "observation {} is the state keyframe {i} reached",
                i + 1
            );
        }
    }
    let episode = result.to_dataset_episode().unwrap();
    episode.validate().unwrap();
    assert_eq!(episode.cameras, vec!["front".to_string(), "wrist".to_string()]);
    assert_eq!(episode.rgb.len(), k * 2 * 64 * 64 * 3);
}
