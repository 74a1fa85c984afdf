//! The real-time runtime: a run where the 1 kHz control tick never waits for the policy.
//!
//! - `control`: the control thread (owns the backend, controller, gripper and limit monitor;
//!   one tick per period, wait-free hand-offs only).
//! - `planner`: the planner thread (keyframe checks, IK, straight-line joint goals).
//! - `session`: the threads of a run (control, planner, policy, logger) and their queues.
//! - `messages`: the fixed-size values the threads hand each other.
//! - `pacing`: absolute-deadline sleeping, SCHED_FIFO / mlockall / pinning where permitted.
//! - `watchdog`: gives up on a silent policy or planner while the arm holds.
//! - `alloc_count`: counts heap allocations inside ticks.
//!
//! Lock-step runs (`control::runner`) stay the deterministic default for simulation and
//! datasets; both execute a keyframe with the same `control::execution::Execution`.
pub mod alloc_count;
pub mod control;
pub mod messages;
pub mod pacing;
pub mod planner;
pub mod session;
pub mod watchdog;
