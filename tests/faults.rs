//! Fault streams injected into the real stack (`flowram bench faults` with a few runs): bad
//! keyframes are refused and the arm holds, the watchdog ends stalled runs, QP time-outs fall
//! back to the damping torque, dropped and late backend cycles are survived, and no torque is
//! ever non-finite, over its rated value or faster than its rate limit, and nothing panics.
//!
//! Not asserted, because it does not hold yet: joint position and velocity limits when the TCP
//! is driven into the table (the `blocked_tcp` fault). Pressing on, the arm overpowers the wrist
//! (12 Nm joints against 87 Nm ones), which snaps past its velocity limit and rests ~2 mrad past
//! joint 6's datasheet limit; see docs/experiments.md and the hardware issue's note.
use flowram::rollout::faults::fault_runs;

#[test]
fn injected_faults_never_give_bad_torques_or_panics() {
    let report = fault_runs(12, 0, |_| {}).unwrap();
    assert_eq!(report.runs, 12);
    assert_eq!(report.panics, 0);
    assert_eq!(report.non_finite_torques, 0);
    assert_eq!(report.torque_violations, 0);
    assert_eq!(report.torque_rate_violations, 0);
    for kind in ["non_finite", "non_unit_quaternion", "outside_workspace", "unreachable", "policy_failure", "reachable"]
    {
        assert!(report.faults.get(kind).copied().unwrap_or(0) > 0, "no {kind} fault in 12 runs: {:?}", report.faults);
    }
    assert!(report.faults["dropped_cycles"] > 0 && report.faults["late_cycles"] > 0);
    assert!(report.holds_rejected > 0, "no bad keyframe was refused");
    assert!(report.keyframes_reached > 0, "no good keyframe was reached");
    assert!(report.qp_fallbacks > 0, "no QP time-out was survived");
}
