//! A real-time run: the control thread (real-time where permitted), the planner, the policy and
//! the logger, each on its own thread, connected by wait-free single-producer/single-consumer
//! queues sized when the run starts. The policy and the planner may take as long as they like:
//! the control thread keeps ticking and the arm holds until their plan arrives.
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use crate::control::backend::RobotBackend;
use crate::stats::percentile_sorted;

use super::control::{ControlLoop, ControlPorts, ControlSummary};
use super::messages::{Answer, Event, PlanMessage, PlanOutcome, Proposal, Rejection, Request, Status, TickRecord};
use super::pacing::{RtSettings, make_current_thread_background, make_current_thread_realtime, release_memory_lock};
use super::planner::Planner;

/// Where keyframes come from: a policy, a file, a test's script. It runs on the thread that
/// calls [`run_session`] (the policy thread: it may block and allocate, and it may hold things
/// bound to that thread, such as an EGL renderer).
pub trait KeyframeSource {
    /// What to do for the arm in `request.state`: a keyframe (base frame), or the end of the
    /// episode; an error is reported and the arm holds.
    fn propose(&mut self, request: &Request) -> Result<Answer, String>;

    /// Called while no request is waiting; a policy that infers continuously works here.
    fn idle(&mut self) {
        std::thread::sleep(std::time::Duration::from_micros(200));
    }
}

/// Stops the control loop and releases the background threads when dropped.
struct Release<'a> {
    stop: &'a AtomicBool,
    done: &'a AtomicBool,
}

impl Drop for Release<'_> {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.done.store(true, Ordering::Release);
    }
}

/// How a real-time run is set up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SessionSettings {
    /// Ask for mlockall, SCHED_FIFO and a pinned core for the control thread (and lower the
    /// other threads' priority).
    pub realtime_scheduling: bool,
    /// Room in the timing queue (ticks); the logger drains it continuously.
    pub record_capacity: usize,
}

impl Default for SessionSettings {
    fn default() -> Self {
        Self { realtime_scheduling: false, record_capacity: 1 << 16 }
    }
}

/// p50 / p99 / p99.99 / max of a set of durations (us).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct Percentiles {
    pub p50: f64,
    pub p99: f64,
    pub p9999: f64,
    pub max: f64,
}

impl Percentiles {
    pub fn of_ns(values: &[u32]) -> Self {
        let mut v: Vec<f64> = values.iter().map(|&ns| f64::from(ns) * 1e-3).collect();
        v.sort_by(f64::total_cmp);
        Self {
            p50: percentile_sorted(&v, 0.5),
            p99: percentile_sorted(&v, 0.99),
            p9999: percentile_sorted(&v, 0.9999),
            max: v.last().copied().unwrap_or(0.0),
        }
    }
}

/// What a real-time run produced.
pub struct SessionOutcome<B: RobotBackend> {
    pub control: ControlLoop<B>,
    pub summary: ControlSummary,
    /// Tick compute without the backend (what runs on hardware), the backend's cycle (a MuJoCo
    /// step in simulation), and how late the thread woke (us).
    pub compute: Percentiles,
    pub backend: Percentiles,
    pub wake_latency: Percentiles,
    /// Every event in order.
    pub events: Vec<Event>,
    /// Requests the keyframe source answered, and its errors.
    pub proposals: u64,
    pub source_errors: Vec<String>,
    /// The real-time settings the control thread got (`None`: not asked for).
    pub rt: Option<RtSettings>,
}

/// Runs `control` (on a new real-time thread), `planner` and a logger (on new background
/// threads) and `source` (on this thread) until the control loop stops.
pub fn run_session<B: RobotBackend + Send>(
    control: ControlLoop<B>,
    mut planner: Planner,
    source: &mut dyn KeyframeSource,
    settings: SessionSettings,
) -> std::io::Result<SessionOutcome<B>> {
    let (request_tx, mut request_rx) = rtrb::RingBuffer::<Request>::new(4);
    let (mut proposal_tx, mut proposal_rx) = rtrb::RingBuffer::<Proposal>::new(4);
    let (mut plan_tx, plan_rx) = rtrb::RingBuffer::<PlanMessage>::new(4);
    let (record_tx, mut record_rx) = rtrb::RingBuffer::<TickRecord>::new(settings.record_capacity);
    let (event_tx, mut event_rx) = rtrb::RingBuffer::<Event>::new(1024);
    let initial =
        Status { tick: 0, state: control.backend.read_state(), executing: None, keyframes_done: 0, finished: false };
    let (status_tx, _status_rx) = triple_buffer::triple_buffer(&initial);
    let stop = Arc::new(AtomicBool::new(false));
    let done = AtomicBool::new(false);
    let ports = ControlPorts {
        requests: request_tx,
        plans: plan_rx,
        records: record_tx,
        events: event_tx,
        status: status_tx,
        stop: stop.clone(),
    };
    let rt_wanted = settings.realtime_scheduling;
    std::thread::scope(|scope| {
        let control_thread =
            std::thread::Builder::new().name("flowram-control".into()).spawn_scoped(scope, move || {
                let rt = rt_wanted.then(make_current_thread_realtime);
                let out = control.run(ports);
                if rt.as_ref().is_some_and(|r| r.memory_locked) {
                    release_memory_lock();
                }
                (out, rt)
            })?;
        let done = &done;
        let planner_thread = scope.spawn(move || {
            if rt_wanted {
                make_current_thread_background();
            }
            while !done.load(Ordering::Acquire) {
                let Ok(p) = proposal_rx.pop() else {
                    std::thread::sleep(std::time::Duration::from_micros(100));
                    continue;
                };
                let outcome = match p.answer {
                    Answer::Keyframe(k) => {
                        planner.plan(&k, &p.from).map_or_else(PlanOutcome::Rejected, PlanOutcome::Plan)
                    }
                    Answer::Failed => PlanOutcome::Rejected(Rejection::PolicyFailed),
                    Answer::Finish => PlanOutcome::Finish,
                };
                let mut message = PlanMessage { request: p.request, outcome };
                while let Err(rtrb::PushError::Full(m)) = plan_tx.push(message) {
                    if done.load(Ordering::Acquire) {
                        break;
                    }
                    message = m;
                    std::thread::sleep(std::time::Duration::from_micros(100));
                }
            }
        });
        let logger_thread = scope.spawn(move || {
            if rt_wanted {
                make_current_thread_background();
            }
            let (mut compute, mut backend, mut wake, mut events) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            loop {
                let finished = record_rx.is_abandoned();
                while let Ok(r) = record_rx.pop() {
                    compute.push(r.compute_ns);
                    backend.push(r.backend_ns);
                    wake.push(r.wake_late_ns);
                }
                while let Ok(e) = event_rx.pop() {
                    events.push(e);
                }
                if finished {
                    break;
                }
                std::thread::sleep(std::time::Duration::from_millis(2));
            }
            (compute, backend, wake, events)
        });
        // The policy loop, on this thread, until the control thread ends. If the source panics,
        // the guard stops the control loop and releases the other threads on the way out, so
        // that the scope can end and pass the panic on (instead of waiting for them forever).
        let _release = Release { stop: &stop, done };
        if rt_wanted {
            make_current_thread_background();
        }
        let (mut proposals, mut source_errors) = (0u64, Vec::new());
        while !control_thread.is_finished() {
            let Ok(request) = request_rx.pop() else {
                source.idle();
                continue;
            };
            let answer = source.propose(&request).unwrap_or_else(|e| {
                source_errors.push(e);
                Answer::Failed
            });
            proposals += 1;
            let mut proposal = Proposal { request: request.id, answer, from: request.state.q };
            while let Err(rtrb::PushError::Full(p)) = proposal_tx.push(proposal) {
                if control_thread.is_finished() {
                    break;
                }
                proposal = p;
                std::thread::sleep(std::time::Duration::from_micros(100));
            }
        }
        let joined = control_thread.join();
        done.store(true, Ordering::Release);
        let ((control, summary), rt) = match joined {
            Ok(out) => out,
            Err(panic) => std::panic::resume_unwind(panic),
        };
        let (compute, backend, wake, events) = logger_thread.join().unwrap_or_else(|p| std::panic::resume_unwind(p));
        planner_thread.join().unwrap_or_else(|p| std::panic::resume_unwind(p));
        Ok(SessionOutcome {
            control,
            summary,
            compute: Percentiles::of_ns(&compute),
            backend: Percentiles::of_ns(&backend),
            wake_latency: Percentiles::of_ns(&wake),
            events,
            proposals,
            source_errors,
            rt,
        })
    })
}
