//! Fault streams injected into the real stack (`flowram bench faults` with a few runs): bad
//! keyframes are refused and the arm holds, the watchdog ends stalled runs, QP time-outs fall
//! back to the damping torque, dropped and late backend cycles are survived, TCPs driven into
//! the table trip the collision reflex, no torque is ever non-finite, over its rated value or
//! faster than its rate limit, no joint leaves its position limits, and nothing panics.
//!
//! Velocity limits are asserted as bounded, not held: in a few runs the table drives a joint
//! faster than the 1 Nm/ms torque rate lets it brake (README, "bench faults").
use flowram::rollout::faults::fault_runs;

#[test]
fn injected_faults_never_give_bad_torques_or_panics() {
    let report = fault_runs(12, 0, |_| {}).unwrap();
    assert_eq!(report.runs, 12);
    assert_eq!(report.panics, 0);
    assert_eq!(report.non_finite_torques, 0);
    assert_eq!(report.torque_violations, 0);
    assert_eq!(report.torque_rate_violations, 0);
    assert_eq!(report.position_violations, 0, "{report:?}");
    // A table that drives a joint faster than the torque rate lets it brake can still exceed a
    // velocity limit for a few ticks (the QP time-limit faults are wall-clock, so the runs are
    // not exactly reproducible): bounded, not zero.
    assert!(report.velocity_violations * 1000 < report.ticks, "{report:?}");
    assert!(report.faults.get("blocked_tcp").copied().unwrap_or(0) > 0);
    assert!(report.holds_reflex > 0, "no blocked TCP tripped the collision reflex: {report:?}");
    for kind in ["non_finite", "non_unit_quaternion", "outside_workspace", "unreachable", "policy_failure", "reachable"]
    {
        assert!(report.faults.get(kind).copied().unwrap_or(0) > 0, "no {kind} fault in 12 runs: {:?}", report.faults);
    }
    assert!(report.faults["dropped_cycles"] > 0 && report.faults["late_cycles"] > 0);
    assert!(report.holds_rejected > 0, "no bad keyframe was refused");
    assert!(report.keyframes_reached > 0, "no good keyframe was reached");
    assert!(report.qp_fallbacks > 0, "no QP time-out was survived");
}
