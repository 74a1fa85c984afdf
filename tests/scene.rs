//! The scene: the Panda is attached correctly, its actuators respect the rated torques, and the
//! World's state access does what it says.
mod common;

use flowram::sim::scene::CAMERAS;
use flowram::sim::{JointVector, SimError, World};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

fn default_world() -> World {
    World::load_named("default").expect("default scene loads")
}

#[test]
fn scene_has_the_arm_hand_actuators_and_cameras() {
    let world = default_world();
    let m = world.model().ffi();
    assert_eq!(m.nq, 9, "7 arm joints + 2 finger joints");
    assert_eq!(m.nv, 9);
    assert_eq!(m.nu, 8, "7 torque motors + the gripper actuator");
    assert_eq!(world.timestep(), 0.001, "1 kHz physics");
    let rig_names = world.camera_names();
    for c in CAMERAS {
        assert!(rig_names.iter().any(|n| n == c), "camera {c} missing from {rig_names:?}");
    }
}

#[test]
fn home_tcp_matches_the_panda_kinematics() {
    // Franka Panda at q_home with the Franka hand: TCP 0.1034 m beyond the flange lies at
    // (0.3069, 0, 0.4869) in the base frame, pointing down, fingers along the base y axis.
    let s = default_world().arm_state();
    let p = s.tcp_in_base.translation.vector;
    assert!((p - Vector3::new(0.30689, 0.0, 0.48688)).norm() < 1e-3, "TCP at {p:?}");
    let expected = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    let angle = s.tcp_in_base.rotation.angle_to(&expected);
    assert!(angle < 1e-3, "TCP rotation off by {angle} rad (hand mount must be -45 deg about z)");
    assert!((s.gripper_width - 0.08).abs() < 1e-9, "gripper starts open");
}

#[test]
fn motors_clamp_torques_to_the_panda_ratings() {
    let mut world = default_world();
    let limits = [87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0];
    for sign in [1.0, -1.0] {
        world.reset_to("home").unwrap();
        world.apply_torques(&JointVector::repeat(200.0 * sign)).unwrap();
        world.step();
        let tau = world.arm_state().tau;
        for i in 0..7 {
            assert!((tau[i] - sign * limits[i]).abs() < 1e-9, "joint {i}: applied {} for {}", tau[i], 200.0 * sign);
        }
    }
    world.reset_to("home").unwrap();
    let small = JointVector::from_column_slice(&[5.0, -4.0, 3.0, -2.0, 1.0, -0.5, 0.25]);
    world.apply_torques(&small).unwrap();
    world.step();
    assert!((world.arm_state().tau - small).norm() < 1e-12, "torques within limits pass unchanged");
}

#[test]
fn arm_holds_still_under_zero_torque_and_moves_under_torque() {
    let mut world = default_world();
    let q0 = world.arm_state().q;
    world.apply_torques(&JointVector::zeros()).unwrap();
    for _ in 0..1000 {
        world.step();
    }
    let s = world.arm_state();
    assert!((s.q - q0).norm() < 1e-3, "gravity-compensated arm drifted {:?}", s.q - q0);
    assert!((s.time - 1.0).abs() < 1e-9);
    let mut tau = JointVector::zeros();
    tau[0] = 5.0;
    world.apply_torques(&tau).unwrap();
    for _ in 0..200 {
        world.step();
    }
    assert!(world.arm_state().dq[0] > 0.05, "joint 1 accelerates under a positive torque");
}

#[test]
fn named_postures_and_unknown_names() {
    let mut world = default_world();
    world.reset_to("ready").unwrap();
    assert!((world.arm_state().q[3] + 2.2).abs() < 1e-12);
    match world.reset_to("nowhere") {
        Err(SimError::UnknownName { valid, .. }) => {
            assert!(valid.contains("home") && valid.contains("ready"), "{valid}")
        }
        other => panic!("expected UnknownName, got {other:?}"),
    }
    let bad = JointVector::repeat(f64::NAN);
    assert!(matches!(world.reset_to_configuration(&bad), Err(SimError::InvalidInput { .. })));
    assert!(matches!(world.apply_torques(&bad), Err(SimError::InvalidInput { .. })));
}

#[test]
fn gripper_closes_and_opens() {
    let mut world = default_world();
    world.set_gripper(0.0).unwrap();
    for _ in 0..1500 {
        world.step();
    }
    let closed = world.arm_state().gripper_width;
    assert!(closed < 0.005, "closed width {closed}");
    world.set_gripper(1.0).unwrap();
    for _ in 0..1500 {
        world.step();
    }
    let open = world.arm_state().gripper_width;
    assert!(open > 0.075, "open width {open}");
    let err = world.set_gripper(1.5).unwrap_err().to_string();
    assert!(err.contains("[0, 1]"), "{err}");
}

#[test]
fn object_poses_read_and_set() {
    let scene = common::scene_with(
        r#"<body name="cube" pos="0.5 0 0.8"><freejoint/><geom type="box" size="0.02 0.02 0.02" mass="0.1"/></body>"#,
    );
    let mut world = common::load(&scene);
    let pose =
        Isometry3::from_parts(Translation3::new(0.4, -0.1, 0.9), UnitQuaternion::from_euler_angles(0.1, -0.2, 0.7));
    world.set_body_pose("cube", &pose).unwrap();
    let read = world.body_pose("cube").unwrap();
    assert!((read.translation.vector - pose.translation.vector).norm() < 1e-12);
    assert!(read.rotation.angle_to(&pose.rotation) < 1e-9);
    // It falls onto the table (top at z = 0.75) and rests there.
    for _ in 0..1500 {
        world.step();
    }
    let z = world.body_pose("cube").unwrap().translation.z;
    assert!((z - 0.77).abs() < 2e-3, "cube centre at z = {z}, expected resting on the table at 0.77");

    assert!(matches!(world.set_body_pose("table", &pose), Err(SimError::NotFreeBody { .. })));
    let err = world.body_pose("no_such_body").unwrap_err().to_string();
    assert!(err.contains("cube") && err.contains("panda_link0"), "{err}");
}
