//! IK: reaches random reachable poses, rejects unreachable and malformed ones.
use flowram::control::ik::{IkConfig, IkError, InverseKinematics, target_pose};
use flowram::control::pose_error::pose_error;
use flowram::robot::{JointLimits, JointVector, Kinematics};
use flowram::sim::World;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use rand::{Rng, SeedableRng};

fn setup() -> (Kinematics, InverseKinematics, JointLimits) {
    let world = World::load_named("default").unwrap();
    let kin = Kinematics::new(&world.arm_description().unwrap()).unwrap();
    let limits = JointLimits::panda().unwrap();
    (kin, InverseKinematics::new(IkConfig::default(), limits), limits)
}

#[test]
fn solves_at_least_99_percent_of_random_reachable_poses() {
    let (mut kin, ik, limits) = setup();
    let mut rng = rand::rngs::StdRng::seed_from_u64(2025);
    let margin = ik.config.limit_margin;
    let home = ik.config.neutral;
    let (mut solved, mut worst_p, mut worst_r) = (0, 0f64, 0f64);
    for _ in 0..1000 {
        let q = JointVector::from_fn(|i, _| {
            rng.random_range(limits.position_min[i] + margin..limits.position_max[i] - margin)
        });
        let target = kin.tcp(&q).unwrap();
        if let Ok(s) = ik.solve(&mut kin, &target, &home) {
            // Check independently of the solver's own report.
            let e = pose_error(&target, &kin.tcp(&s.q).unwrap());
            let (ep, er) = (e.fixed_rows::<3>(0).norm(), e.fixed_rows::<3>(3).norm());
            assert!(ep <= 1e-3 && er <= 0.01, "reported success at {ep} m / {er} rad");
            assert!(limits.contains(&s.q, 0.0), "solution outside the joint limits: {:?}", s.q);
            worst_p = worst_p.max(ep);
            worst_r = worst_r.max(er);
            solved += 1;
        }
    }
    assert!(solved >= 990, "solved {solved} of 1000 (worst {worst_p} m, {worst_r} rad)");
}

#[test]
fn rejects_unreachable_and_malformed_poses() {
    let (mut kin, ik, _) = setup();
    let home = ik.config.neutral;
    let far = Isometry3::from_parts(Translation3::new(1.5, 0.0, 0.4), UnitQuaternion::identity());
    assert!(matches!(ik.solve(&mut kin, &far, &home), Err(IkError::OutOfReach { .. })));
    // Within the reach sphere but not reachable: at the base, pointing up through link 0.
    let inside_base = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.05), UnitQuaternion::identity());
    let err = ik.solve(&mut kin, &inside_base, &home).unwrap_err();
    assert!(matches!(err, IkError::Unreachable { .. }), "{err}");
    assert!(err.to_string().contains("mm"), "{err}");

    assert!(matches!(target_pose([f64::NAN, 0.0, 0.5], [1.0, 0.0, 0.0, 0.0]), Err(IkError::NonFinite(_))));
    assert!(matches!(target_pose([0.4, 0.0, 0.5], [1.0, 0.0, 0.0, f64::INFINITY]), Err(IkError::NonFinite(_))));
    let err = target_pose([0.4, 0.0, 0.5], [1.0, 1.0, 0.0, 0.0]).unwrap_err();
    assert!(matches!(err, IkError::NotUnitQuaternion { .. }) && err.to_string().contains("1.414"), "{err}");
    assert!(target_pose([0.4, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0]).is_ok());
}
