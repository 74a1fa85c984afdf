//! The control thread: it owns the backend, the controller, the gripper and the limit monitor,
//! and runs one tick per period. A tick takes a new plan if one is waiting (never waits for
//! one, except in the simulated-latency mode, where waiting costs no simulated time), drives
//! the keyframe's [`Execution`], computes the torques, applies them, and hands its timing,
//! events and state to the other threads through wait-free queues and a triple buffer. It does
//! not lock, allocate (checked with [`super::alloc_count`]), log or block.
use crate::control::backend::{Command, RobotBackend, RobotState};
use crate::control::controller::ArmController;
use crate::control::execution::Execution;
use crate::control::gripper::Gripper;
use crate::control::monitor::LimitMonitor;

use super::alloc_count::TickScope;
use super::messages::{Event, PlanMessage, PlanOutcome, Rejection, Request, Status, TickRecord};
use super::pacing::{Pacer, now_ns};
use super::watchdog::Watchdog;

/// How ticks are paced and when plans take effect.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pacing {
    /// One tick per period of wall-clock time; a plan takes effect at the first tick that finds it.
    WallClock,
    /// Ticks run as fast as the machine allows and the plan for a request made at tick `t`
    /// takes effect at tick `t + ticks` exactly, whatever the threads' timing: the asynchronous
    /// path, reproducible bit for bit as long as every answer arrives within the settings'
    /// `stall_timeout_s` of wall-clock time (a later one ends the run as `PolicySilent`, which
    /// depends on the machine's speed). The tick waits (costing wall-clock time only) if the
    /// plan is not there yet.
    SimulatedLatency { ticks: u64 },
}

/// When the control loop stops.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControlSettings {
    pub pacing: Pacing,
    /// Stop after this many ticks.
    pub max_ticks: u64,
    /// Stop once this many keyframes are done (`None`: keep asking until `max_ticks`).
    pub keyframes: Option<u64>,
    /// An unanswered request older than this many ticks stops the run (the arm holds).
    pub watchdog_ticks: u64,
    /// This many rejected keyframes in a row stop the run (the arm holds).
    pub max_rejections_in_a_row: u32,
    /// Longest time the gripper may take to open or close (s).
    pub gripper_timeout: f64,
    /// In the simulated-latency mode: the longest wall-clock time a tick waits for a plan (s).
    pub stall_timeout_s: f64,
}

/// Why the control loop stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    TickLimit,
    KeyframesDone,
    /// The policy or planner did not answer within the watchdog time.
    PolicySilent,
    /// The policy's keyframes were rejected too many times in a row.
    PolicyGarbage,
    /// The backend refused a command.
    BackendError,
    /// The keyframe source ended the episode.
    SourceFinished,
    /// Asked to stop from outside.
    Stopped,
}

/// The control thread's own figures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControlSummary {
    pub ticks: u64,
    pub stop: StopReason,
    /// Ticks whose compute ended after their deadline (release + period).
    pub deadline_misses: u64,
    /// The same misses by what took the time.
    pub miss_causes: MissCauses,
    /// Ticks that blocked waiting for a plan.
    pub waited_ticks: u64,
    pub keyframes_done: u64,
    pub rejections: u64,
    /// Timing records or events the logger's queues had no room for.
    pub dropped_records: u64,
    pub monitor: LimitMonitor,
    pub qp_fallbacks: u64,
    /// Ticks where OSQP ran (on the others no QP row was active: [`crate::control::osc`]).
    pub qp_solves: u64,
    pub final_state: RobotState,
}

/// Deadline misses by what took the tick's time (wall-clock pacing only). Each miss counts
/// once: against `overrun` if the tick could not start on time because the loop came back to
/// wait for its release only after that release (the previous iteration was still running),
/// otherwise against the largest of its three parts.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct MissCauses {
    /// The previous tick ran past this one's release (a stall longer than a period makes the
    /// ticks after it miss while the loop catches up).
    pub overrun: u64,
    /// The thread woke late after its release: the host did not run it in time.
    pub wake: u64,
    /// The backend's cycle (one MuJoCo step in simulation) took the most time.
    pub backend: u64,
    /// The tick's compute (hand-offs, keyframe execution, controller, limit check) took the most.
    pub compute: u64,
}

impl MissCauses {
    pub fn total(&self) -> u64 {
        self.overrun + self.wake + self.backend + self.compute
    }

    /// Counts one miss of a tick released at `release_ns` whose iteration reached the wait for
    /// that release at `arrived_ns` (both on the monotonic clock).
    fn count(&mut self, release_ns: u64, arrived_ns: u64, wake_ns: u64, compute_ns: u64, backend_ns: u64) {
        let cause = if arrived_ns > release_ns {
            &mut self.overrun
        } else if wake_ns >= compute_ns && wake_ns >= backend_ns {
            &mut self.wake
        } else if backend_ns >= compute_ns {
            &mut self.backend
        } else {
            &mut self.compute
        };
        *cause += 1;
    }
}

/// The control thread's ends of the hand-offs.
pub struct ControlPorts {
    pub requests: rtrb::Producer<Request>,
    pub plans: rtrb::Consumer<PlanMessage>,
    pub records: rtrb::Producer<TickRecord>,
    pub events: rtrb::Producer<Event>,
    pub status: triple_buffer::Input<Status>,
    pub stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

/// Called with the backend just before each request goes out (for a simulated robot: the
/// physics state copied into a preallocated buffer, so that the policy's cameras can render the
/// scene the request is about). It runs inside the tick: it must not allocate or block.
pub type RequestTap<B> = Box<dyn FnMut(&B, &Request) + Send>;

/// The control loop and everything it owns.
pub struct ControlLoop<B: RobotBackend> {
    pub backend: B,
    pub tap: Option<RequestTap<B>>,
    pub controller: ArmController,
    pub gripper: Gripper,
    pub monitor: LimitMonitor,
    pub settings: ControlSettings,
}

/// The request awaiting its plan.
#[derive(Debug, Clone, Copy)]
struct Outstanding {
    id: u64,
    tick: u64,
}

impl<B: RobotBackend> ControlLoop<B> {
    /// Runs ticks until a stop condition; returns the loop (backend included) and its figures.
    pub fn run(mut self, mut ports: ControlPorts) -> (Self, ControlSummary) {
        let period_ns = (self.backend.period() * 1e9).round() as u64;
        let pacer = Pacer::new(period_ns);
        let mut state = self.backend.read_state();
        let mut execution: Option<(u64, Execution)> = None;
        let mut outstanding: Option<Outstanding> = None;
        let mut early: Option<PlanMessage> = None;
        let mut watchdog = Watchdog::new(self.settings.watchdog_ticks);
        let mut next_id = 0u64;
        let mut s = Summary::default();
        let mut tick = 0u64;
        let stop = loop {
            if tick >= self.settings.max_ticks {
                break StopReason::TickLimit;
            }
            if ports.stop.load(std::sync::atomic::Ordering::Relaxed) {
                break StopReason::Stopped;
            }
            // When this iteration came to wait for its release: after it, the previous one overran.
            let arrived_ns = now_ns();
            let wake_late_ns = match self.settings.pacing {
                Pacing::WallClock => pacer.wait_for(tick),
                Pacing::SimulatedLatency { .. } => 0,
            };
            let started = now_ns();
            // Counted from the second tick: the first sizes the QP solver's workspace.
            let scope = (tick > 0).then(TickScope::enter);
            let mut waited = false;
            let mut stalled = false;
            let mut finish = false;
            // Ask for a keyframe when idle.
            if execution.is_none()
                && outstanding.is_none()
                && self.settings.keyframes.is_none_or(|k| s.keyframes_done < k)
            {
                let request = Request { id: next_id, tick, state, gripper_open: self.gripper.is_open_commanded() };
                if let Some(tap) = self.tap.as_mut() {
                    tap(&self.backend, &request);
                }
                if ports.requests.push(request).is_ok() {
                    outstanding = Some(Outstanding { id: next_id, tick });
                    watchdog.arm(tick);
                    s.event(&mut ports.events, Event::Requested { request: next_id, tick });
                    next_id += 1;
                }
            }
            // Take the plan if it is due.
            if let Some(o) = outstanding {
                let message = match self.settings.pacing {
                    Pacing::WallClock => ports.plans.pop().ok(),
                    Pacing::SimulatedLatency { ticks } => {
                        if early.is_none() {
                            early = ports.plans.pop().ok();
                        }
                        if tick >= o.tick + ticks && early.is_none() {
                            waited = true;
                            early = wait_for_plan(&mut ports.plans, self.settings.stall_timeout_s);
                            stalled = early.is_none();
                        }
                        if tick >= o.tick + ticks { early.take() } else { None }
                    }
                };
                if let Some(m) = message.filter(|m| m.request == o.id) {
                    outstanding = None;
                    watchdog.disarm();
                    let planned = match m.outcome {
                        PlanOutcome::Finish => None,
                        PlanOutcome::Plan(plan) => {
                            Some(plan.check(self.monitor.limits()).map(|()| plan).map_err(|_| Rejection::BadPlan))
                        }
                        PlanOutcome::Rejected(why) => Some(Err(why)),
                    };
                    match planned {
                        None => finish = true,
                        Some(Ok(plan)) => {
                            execution =
                                Some((m.request, Execution::start(plan, &self.gripper, self.settings.gripper_timeout)));
                            s.rejections_in_a_row = 0;
                            s.event(&mut ports.events, Event::PlanStarted { request: m.request, tick });
                        }
                        Some(Err(why)) => {
                            s.rejections += 1;
                            s.rejections_in_a_row += 1;
                            s.event(&mut ports.events, Event::Rejected { request: m.request, tick, why });
                        }
                    }
                }
            }
            if let Some((_, e)) = execution.as_mut() {
                e.before_tick(&mut self.controller, &mut self.gripper, &state);
            }
            let command: Command = self.controller.tick(&state);
            self.monitor.check(&state, &command.tau);
            let mut finished = None;
            if let Some((id, e)) = execution.as_mut()
                && e.after_tick(&self.controller, &mut self.gripper, &state)
            {
                finished = Some((*id, e.outcome()));
            }
            let computed_ns = now_ns();
            let cycled = self.backend.cycle(&command);
            drop(scope);
            let done_ns = now_ns();
            if let Some((request, outcome)) = finished {
                execution = None;
                s.keyframes_done += 1;
                s.event(&mut ports.events, Event::KeyframeDone { request, tick, outcome });
            }
            if let Pacing::WallClock = self.settings.pacing
                && done_ns > pacer.release_ns(tick) + period_ns
            {
                s.deadline_misses += 1;
                let release = pacer.release_ns(tick);
                s.miss_causes.count(release, arrived_ns, wake_late_ns, computed_ns - started, done_ns - computed_ns);
            }
            s.waited_ticks += u64::from(waited);
            let record = TickRecord {
                tick,
                compute_ns: clamp_u32(computed_ns - started),
                backend_ns: clamp_u32(done_ns - computed_ns),
                wake_late_ns: clamp_u32(wake_late_ns),
                waited,
            };
            if ports.records.push(record).is_err() {
                s.dropped += 1;
            }
            tick += 1;
            let backend_failed = match cycled {
                Ok(next) => {
                    state = next;
                    false
                }
                Err(_) => true,
            };
            ports.status.write(Status {
                tick,
                state,
                executing: execution.map(|(id, _)| id),
                keyframes_done: s.keyframes_done,
                finished: false,
            });
            if backend_failed {
                break StopReason::BackendError;
            }
            if let Some(o) = outstanding
                && let Some(ticks) = if stalled { Some(tick - o.tick) } else { watchdog.expired(tick) }
            {
                s.event(&mut ports.events, Event::WatchdogHold { request: o.id, tick, ticks });
                break StopReason::PolicySilent;
            }
            if finish {
                break StopReason::SourceFinished;
            }
            if s.rejections_in_a_row >= self.settings.max_rejections_in_a_row {
                break StopReason::PolicyGarbage;
            }
            if execution.is_none() && self.settings.keyframes.is_some_and(|k| s.keyframes_done >= k) {
                break StopReason::KeyframesDone;
            }
        };
        ports.status.write(Status { tick, state, executing: None, keyframes_done: s.keyframes_done, finished: true });
        let summary = ControlSummary {
            ticks: tick,
            stop,
            deadline_misses: s.deadline_misses,
            miss_causes: s.miss_causes,
            waited_ticks: s.waited_ticks,
            keyframes_done: s.keyframes_done,
            rejections: s.rejections,
            dropped_records: s.dropped,
            monitor: self.monitor,
            qp_fallbacks: self.controller.osc().stats().fallbacks,
            qp_solves: self.controller.osc().stats().qp_solves,
            final_state: state,
        };
        (self, summary)
    }
}

#[derive(Debug, Default)]
struct Summary {
    deadline_misses: u64,
    miss_causes: MissCauses,
    waited_ticks: u64,
    keyframes_done: u64,
    rejections: u64,
    rejections_in_a_row: u32,
    dropped: u64,
}

impl Summary {
    fn event(&mut self, events: &mut rtrb::Producer<Event>, event: Event) {
        if events.push(event).is_err() {
            self.dropped += 1;
        }
    }
}

fn clamp_u32(ns: u64) -> u32 {
    u32::try_from(ns).unwrap_or(u32::MAX)
}

/// Simulated-latency mode only: spins (yielding) until a plan arrives or `timeout_s` of
/// wall-clock time passes.
fn wait_for_plan(plans: &mut rtrb::Consumer<PlanMessage>, timeout_s: f64) -> Option<PlanMessage> {
    let deadline = now_ns() + (timeout_s * 1e9) as u64;
    loop {
        if let Ok(m) = plans.pop() {
            return Some(m);
        }
        if now_ns() > deadline || plans.is_abandoned() {
            return None;
        }
        std::thread::yield_now();
    }
}

#[cfg(test)]
mod tests {
    use super::MissCauses;

    #[test]
    fn each_miss_goes_to_one_cause_overrun_first_then_the_largest_part() {
        let mut causes = MissCauses::default();
        let release = 5_000_000;
        // An iteration that reached its wait after the release inherits a stall: an overrun, even
        // where the lateness it inherited (its wake) is the largest part.
        causes.count(release, release + 1, 2_000_000, 30_000, 60_000);
        // Reached in time: the largest part.
        causes.count(release, release - 200_000, 1_200_000, 30_000, 60_000);
        causes.count(release, release - 200_000, 10_000, 30_000, 1_100_000);
        causes.count(release, release, 10_000, 990_000, 60_000);
        assert_eq!(causes, MissCauses { overrun: 1, wake: 1, backend: 1, compute: 1 });
        assert_eq!(causes.total(), 4);
    }
}
