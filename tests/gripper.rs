//! The gripper closes on an object and the grasp check tells a grasp from an empty close.
mod common;

use flowram::control::keyframe::Keyframe;
use flowram::control::osc_config::OscConfig;
use flowram::rollout::stack::build_runner;
use flowram::sim::World;

fn close_at_home(world: &mut World) -> String {
    let mut runner = build_runner(world, OscConfig::default_profile().unwrap()).unwrap();
    let home = world.arm_state().tcp_in_base;
    let report = runner.run(world, &[Keyframe::at(&home, false)]).unwrap();
    assert_eq!(report.limit_violations, 0);
    report.keyframes[0].gripper.expect("the gripper was actuated").to_string()
}

#[test]
fn closing_on_a_block_is_a_grasp() {
    // A fixed 3 cm block where the fingertips meet at the home pose (TCP at world 0.307, 0, 1.237).
    let scene = common::scene_with(
        r#"<body name="block" pos="0.30689 0 1.2369"><geom type="box" size="0.012 0.015 0.012" rgba="0.2 0.8 0.2 1"/></body>"#,
    );
    let mut world = common::load(&scene);
    let outcome = close_at_home(&mut world);
    assert!(outcome.starts_with("grasped"), "{outcome}");
    let width = world.arm_state().gripper_width;
    assert!((width - 0.030).abs() < 0.003, "fingers stopped on the 30 mm block at {width}");
}

#[test]
fn closing_on_nothing_is_reported_empty() {
    let mut world = World::load_named("default").unwrap();
    let outcome = close_at_home(&mut world);
    assert_eq!(outcome, "closed on nothing");
}
