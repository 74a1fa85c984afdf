//! The jerk-limited planner: it agrees with the official ruckig library, stays within its
//! limits, and re-plans mid-motion without jumps in velocity or acceleration.
use flowram::control::trajectory::{JointSetpoint, JointTrajectory, MotionLimits};
use flowram::robot::{JointLimits, JointVector};

const DT: f64 = 0.001;

fn limits() -> MotionLimits {
    MotionLimits::scaled(&JointLimits::panda().unwrap(), 0.5, 0.3, 0.1)
}

fn v(a: [f64; 7]) -> JointVector {
    JointVector::from_column_slice(&a)
}

/// The official library's offline plan from `from` (position, velocity, acceleration) to `goal`.
fn official(from: &JointSetpoint, goal: &JointVector, l: &MotionLimits) -> ruckig::Trajectory {
    let mut otg = ruckig::Ruckig::new_offline(7, 0);
    let mut input = ruckig::InputParameter::new(7);
    input.current_position = from.q.as_slice().to_vec();
    input.current_velocity = from.dq.as_slice().to_vec();
    input.current_acceleration = from.ddq.as_slice().to_vec();
    input.target_position = goal.as_slice().to_vec();
    input.target_velocity = vec![0.0; 7];
    input.target_acceleration = vec![0.0; 7];
    input.max_velocity = l.velocity.as_slice().to_vec();
    input.max_acceleration = l.acceleration.as_slice().to_vec();
    input.max_jerk = l.jerk.as_slice().to_vec();
    let mut traj = ruckig::Trajectory::new_direct(7);
    let _ = otg.calculate(&mut input, &mut traj);
    traj
}

fn assert_follows(ours: &mut JointTrajectory, theirs: &ruckig::Trajectory, label: &str) {
    assert!(
        (ours.duration() - theirs.get_duration()).abs() < 1e-9,
        "{label}: duration {} vs official {}",
        ours.duration(),
        theirs.get_duration()
    );
    let mut k = 2; // the first tick of the plan was taken by the caller
    while !ours.is_finished() {
        let s = ours.step().unwrap();
        let (p, vel, _) = theirs.at_time(k as f64 * DT);
        for i in 0..7 {
            assert!((s.q[i] - p[i]).abs() < 1e-9 && (s.dq[i] - vel[i]).abs() < 1e-8, "{label}: tick {k} joint {i}");
        }
        k += 1;
    }
}

#[test]
fn agrees_with_the_official_ruckig_library() {
    let l = limits();
    let home = v([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]);
    for goal in [v([0.6, -0.3, 0.4, -1.8, 0.5, 2.0, 1.3]), v([-0.4, 0.2, -0.3, -2.6, -0.7, 1.2, 0.1])] {
        let mut ours = JointTrajectory::new(&l, DT, &home);
        ours.set_goal(&goal);
        let start = ours.current();
        let first = ours.step().unwrap(); // plans and takes the first tick
        let theirs = official(&start, &goal, &l);
        let (p, _, _) = theirs.at_time(DT);
        assert!((first.q - v(p.try_into().unwrap())).norm() < 1e-9);
        assert_follows(&mut ours, &theirs, "rest to rest");
    }
    // From a moving state: interrupt a motion and compare the new plan.
    let mut ours = JointTrajectory::new(&l, DT, &home);
    ours.set_goal(&v([0.6, -0.3, 0.4, -1.8, 0.5, 2.0, 1.3]));
    for _ in 0..150 {
        ours.step().unwrap();
    }
    let moving = ours.current();
    assert!(moving.dq.norm() > 0.1 && moving.ddq.norm() > 0.1, "interrupted mid-motion");
    let new_goal = v([-0.2, -0.5, 0.1, -2.0, 0.3, 1.8, 0.5]);
    ours.set_goal(&new_goal);
    ours.step().unwrap();
    let theirs = official(&moving, &new_goal, &l);
    assert_follows(&mut ours, &theirs, "re-plan from a moving state");
}

#[test]
fn replanning_mid_motion_keeps_velocity_and_acceleration_continuous() {
    let l = limits();
    let mut traj = JointTrajectory::new(&l, DT, &v([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]));
    traj.set_goal(&v([0.8, -0.2, 0.5, -1.6, 0.6, 2.2, 1.5]));
    let mut previous = traj.current();
    let mut ticks = 0;
    let mut replans = 0;
    while !traj.is_finished() || ticks < 10 {
        if ticks == 120 || ticks == 260 {
            // New goals arrive while the arm is moving fast.
            let goal = if ticks == 120 {
                [-0.5, 0.3, -0.4, -2.5, -0.6, 1.0, 0.0]
            } else {
                [0.3, -0.6, 0.2, -2.0, 0.2, 1.9, 0.9]
            };
            traj.set_goal(&v(goal));
            replans += 1;
        }
        let s = traj.step().unwrap();
        for i in 0..7 {
            assert!(s.dq[i].abs() <= l.velocity[i] * (1.0 + 1e-9), "tick {ticks}: velocity limit of joint {i}");
            assert!(
                s.ddq[i].abs() <= l.acceleration[i] * (1.0 + 1e-9),
                "tick {ticks}: acceleration limit of joint {i}"
            );
            // Continuity: per tick the acceleration changes by at most jerk * dt, and velocity
            // by the mean acceleration over the tick.
            assert!(
                (s.ddq[i] - previous.ddq[i]).abs() <= l.jerk[i] * DT * (1.0 + 1e-6),
                "tick {ticks}: acceleration jump on joint {i}"
            );
            let expected_dv = 0.5 * (s.ddq[i] + previous.ddq[i]) * DT;
            assert!(
                (s.dq[i] - previous.dq[i] - expected_dv).abs() <= l.jerk[i] * DT * DT,
                "tick {ticks}: velocity jump on joint {i}"
            );
        }
        previous = s;
        ticks += 1;
        assert!(ticks < 20_000, "the trajectory finishes");
    }
    assert_eq!(replans, 2);
    assert!((traj.current().q - v([0.3, -0.6, 0.2, -2.0, 0.2, 1.9, 0.9])).norm() < 1e-9, "ends at the last goal");
    assert!(traj.current().dq.norm() < 1e-9);
}
