//! Pinocchio (the controller's model) and MuJoCo (the simulator) describe the same robot.
use flowram::robot::{JointLimits, JointVector, Kinematics};
use flowram::sim::World;
use rand::{Rng, SeedableRng};

#[test]
fn pinocchio_and_mujoco_agree_over_random_configurations() {
    let mut world = World::load_named("default").unwrap();
    let description = world.arm_description().unwrap();
    let mut kin = Kinematics::new(&description).unwrap();
    let limits = JointLimits::panda().unwrap();
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let (mut worst_pos, mut worst_rot, mut worst_jac, mut worst_mass, mut worst_bias, mut worst_grav) =
        (0f64, 0f64, 0f64, 0f64, 0f64, 0f64);
    for _ in 0..1000 {
        let q = JointVector::from_fn(|i, _| rng.random_range(limits.position_min[i]..limits.position_max[i]));
        let dq = JointVector::from_fn(|i, _| rng.random_range(-limits.velocity[i]..limits.velocity[i]));
        world.set_arm_state(&q, &dq).unwrap();
        let mj = world.arm_dynamics_reference();
        let pin = kin.dynamics(&q, &dq).unwrap();
        let task = kin.task(&q, &dq).unwrap();
        assert!(
            (task.jacobian - pin.jacobian).abs().max() < 1e-12 && (task.jdot_qdot - pin.jdot_qdot).abs().max() < 1e-12
        );
        assert!((task.tcp.translation.vector - pin.tcp.translation.vector).norm() < 1e-12);
        worst_pos = worst_pos.max((pin.tcp.translation.vector - mj.tcp_in_base.translation.vector).norm());
        worst_rot = worst_rot.max(pin.tcp.rotation.angle_to(&mj.tcp_in_base.rotation));
        worst_jac = worst_jac.max((pin.jacobian - mj.jacobian).abs().max());
        worst_mass = worst_mass.max((pin.mass - mj.mass).abs().max());
        worst_bias = worst_bias.max((pin.coriolis + pin.gravity - mj.bias).abs().max());
        worst_grav = worst_grav.max((pin.gravity - mj.gravity_compensation).abs().max());
    }
    assert!(worst_pos < 1e-6, "TCP position differs by {worst_pos} m");
    assert!(worst_rot < 1e-6, "TCP orientation differs by {worst_rot} rad");
    assert!(worst_jac < 1e-6, "Jacobian differs by {worst_jac}");
    assert!(worst_mass < 1e-6, "mass matrix differs by {worst_mass} kg m^2");
    assert!(worst_bias < 1e-6, "bias forces differ by {worst_bias} Nm");
    assert!(worst_grav < 1e-6, "gravity differs from MuJoCo's gravity compensation by {worst_grav} Nm");
}
