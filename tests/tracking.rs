//! Closed-loop tracking on the simulated Panda: keyframes are reached to 1 mm / 0.5 deg, and no
//! torque, torque-rate, joint-position or joint-velocity limit is exceeded anywhere in a run
//! (checked on every logged tick, not only by the runner's own monitor).
use flowram::control::backend::{Cycle, RobotBackend};
use flowram::control::keyframe::Keyframe;
use flowram::control::monitor::LogRow;
use flowram::control::osc_config::OscConfig;
use flowram::control::runner::Runner;
use flowram::robot::JointLimits;
use flowram::rollout::stack::build_runner;
use flowram::sim::World;
use nalgebra::{Translation3, UnitQuaternion, Vector3};

fn stack(world: &World) -> (Runner, JointLimits) {
    let limits = JointLimits::panda().unwrap();
    let config = OscConfig::default_profile().unwrap();
    let mut runner = build_runner(world, config).unwrap();
    runner.enable_log(60.0, world.timestep());
    (runner, limits)
}

/// Every tick of a log within every limit (independent of the runner's monitor).
fn assert_log_within_limits(log: &[LogRow], limits: &JointLimits, dt: f64) {
    assert!(!log.is_empty());
    for (k, row) in log.iter().enumerate() {
        for i in 0..7 {
            assert!(row.tau[i].abs() <= limits.torque[i] + 1e-9, "tick {k}: joint {i} torque {}", row.tau[i]);
            assert!(row.dq[i].abs() <= limits.velocity[i], "tick {k}: joint {i} velocity {}", row.dq[i]);
            assert!(
                row.q[i] >= limits.position_min[i] && row.q[i] <= limits.position_max[i],
                "tick {k}: joint {i} position {}",
                row.q[i]
            );
            if k > 0 {
                let rate = (row.tau[i] - log[k - 1].tau[i]).abs();
                assert!(
                    rate <= limits.torque_rate[i] * dt + 1e-9,
                    "tick {k}: joint {i} torque rate {rate} Nm per tick"
                );
            }
        }
    }
}

#[test]
fn a_20_cm_move_ends_within_1_mm_and_half_a_degree() {
    let mut world = World::load_named("default").unwrap();
    let (mut runner, limits) = stack(&world);
    let home = world.arm_state().tcp_in_base;
    let moved = Translation3::new(0.12, -0.16, 0.0) * home; // 20 cm
    let turned = Translation3::new(0.0, 0.0, -0.1) * home * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.4);
    let keyframes = [Keyframe::at(&moved, true), Keyframe::at(&turned, true), Keyframe::at(&home, true)];
    let report = runner.run(&mut world, &keyframes).unwrap();
    for (i, k) in report.keyframes.iter().enumerate() {
        assert!(k.reached, "keyframe {i}: {k:?}");
        assert!(k.pos_err_mm <= 1.0 && k.rot_err_deg <= 0.5, "keyframe {i}: {k:?}");
    }
    // The simulator's own TCP agrees with the controller's measurement at the end.
    let final_tcp = world.arm_state().tcp_in_base;
    assert!((final_tcp.translation.vector - home.translation.vector).norm() < 1e-3);
    assert_eq!(report.limit_violations, 0, "{report:?}");
    assert_eq!(report.qp_fallbacks, 0, "{report:?}");
    assert!(report.max_torque_rate_ratio <= 1.0 + 1e-9);
    assert_log_within_limits(runner.log().unwrap(), &limits, world.timestep());
}

#[test]
fn unreachable_keyframes_are_reported_and_the_run_continues() {
    let mut world = World::load_named("default").unwrap();
    let (mut runner, limits) = stack(&world);
    let home = world.arm_state().tcp_in_base;
    let near = Translation3::new(0.05, 0.05, 0.05) * home;
    let far = Keyframe { position: [1.4, 0.0, 0.5], quat_wxyz: [0.0, 1.0, 0.0, 0.0], gripper_open: true };
    let bad_quat = Keyframe { position: [0.4, 0.0, 0.4], quat_wxyz: [0.5, 0.5, 0.0, 0.0], gripper_open: true };
    let report = runner.run(&mut world, &[far, bad_quat, Keyframe::at(&near, true)]).unwrap();
    assert!(!report.keyframes[0].reached && report.keyframes[0].error.as_deref().unwrap().contains("reaches at most"));
    assert!(!report.keyframes[1].reached && report.keyframes[1].error.as_deref().unwrap().contains("unit quaternion"));
    assert!(report.keyframes[2].reached, "{:?}", report.keyframes[2]);
    assert_log_within_limits(runner.log().unwrap(), &limits, world.timestep());
}

#[test]
fn an_interrupted_motion_stays_continuous() {
    // A new goal arrives while the arm moves fast: the joint reference keeps continuous velocity
    // and acceleration, and the measured joint velocities have no jumps.
    let mut world = World::load_named("default").unwrap();
    let (mut runner, limits) = stack(&world);
    let mut kin = flowram::robot::Kinematics::new(&world.arm_description().unwrap()).unwrap();
    let q0 = world.read_state().q;
    let home = kin.tcp(&q0).unwrap();
    let first = runner.ik.solve(&mut kin, &(Translation3::new(0.15, 0.2, -0.1) * home), &q0).unwrap().q;
    let second = runner.ik.solve(&mut kin, &(Translation3::new(0.1, -0.2, 0.05) * home), &first).unwrap().q;
    runner.controller.set_goal(&first);
    let (mut refs, mut measured) = (Vec::new(), Vec::new());
    let mut ticks = 0;
    world
        .control(|state| {
            ticks += 1;
            if ticks == 400 {
                runner.controller.set_goal(&second);
            }
            let command = runner.controller.tick(state);
            refs.push(*runner.controller.reference());
            measured.push(*state);
            if ticks > 400 && runner.controller.trajectory_finished() {
                Cycle::Finish(command)
            } else {
                Cycle::Continue(command)
            }
        })
        .unwrap();
    let at_switch = refs[399].dq.norm();
    assert!(at_switch > 0.2, "the switch happens mid-motion ({at_switch} rad/s)");
    let c = OscConfig::default_profile().unwrap();
    let motion = flowram::control::trajectory::MotionLimits::scaled(
        &limits,
        c.velocity_scale,
        c.acceleration_scale,
        c.jerk_scale,
    );
    let dt = world.timestep();
    for k in 1..refs.len() {
        for i in 0..7 {
            let dddq = (refs[k].ddq[i] - refs[k - 1].ddq[i]).abs() / dt;
            assert!(
                dddq <= motion.jerk[i] * (1.0 + 1e-6) + 1e-9,
                "tick {k}: reference acceleration jumps on joint {i}"
            );
            let expected = 0.5 * (refs[k].ddq[i] + refs[k - 1].ddq[i]) * dt;
            assert!(
                (refs[k].dq[i] - refs[k - 1].dq[i] - expected).abs() <= motion.jerk[i] * dt * dt,
                "tick {k}: reference velocity jumps on joint {i}"
            );
            // The arm itself: velocity changes per tick stay small (no torque spikes at the switch).
            assert!(
                (measured[k].dq[i] - measured[k - 1].dq[i]).abs() < 0.05,
                "tick {k}: measured velocity jumps on joint {i}"
            );
        }
    }
    assert!((refs.last().unwrap().q - second).norm() < 1e-9);
}

#[test]
fn with_the_contact_guards_a_keyframe_inside_the_table_is_not_reached_and_no_limit_is_exceeded() {
    // The fault bench's blocked TCP: a pose 4 cm below the table top, straight down from home,
    // with the contact guards of controllers/osc.toml. The arm presses compliantly and settles short
    // (below the collision reflex); the joint-limit constraints, which count the table's push,
    // keep every joint inside its limits, and the next keyframe is reached as usual.
    let mut world = World::load_named("default").unwrap();
    let limits = JointLimits::panda().unwrap();
    let guard = OscConfig::default_profile().unwrap();
    assert!(guard.external_torque_in_limits && guard.reflex_enabled);
    let mut runner = build_runner(&world, guard).unwrap();
    runner.enable_log(60.0, world.timestep());
    let home = world.arm_state().tcp_in_base;
    let table_top_in_base = 0.0; // the base stands on the table (world z 0.75)
    let inside = Translation3::new(0.0, 0.0, table_top_in_base - 0.04 - home.translation.z) * home;
    let report = runner.run(&mut world, &[Keyframe::at(&inside, true), Keyframe::at(&home, true)]).unwrap();
    assert!(!report.keyframes[0].reached, "{:?}", report.keyframes[0]);
    assert!(report.keyframes[0].pos_err_mm > 30.0, "the table stopped it: {:?}", report.keyframes[0]);
    assert!(report.keyframes[1].reached, "{:?}", report.keyframes[1]);
    assert_eq!(report.limit_violations, 0, "{report:?}");
    assert_log_within_limits(runner.log().unwrap(), &limits, world.timestep());
}
