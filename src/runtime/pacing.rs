//! Pacing the control thread by absolute deadlines, and the operating-system settings a
//! real-time thread asks for. Tick `i` is released at `start + i * period` and must finish its
//! compute before `start + (i + 1) * period`; the thread sleeps with `clock_nanosleep`
//! (`CLOCK_MONOTONIC`, `TIMER_ABSTIME`) until the release, so lateness never accumulates. On a
//! real robot its packets pace the loop instead.

/// Absolute-deadline pacing on the monotonic clock.
#[derive(Debug, Clone, Copy)]
pub struct Pacer {
    start_ns: u64,
    period_ns: u64,
}

/// Nanoseconds on the monotonic clock.
pub fn now_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid timespec; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &raw mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

impl Pacer {
    /// Tick 0 is released one period from now.
    pub fn new(period_ns: u64) -> Self {
        Self { start_ns: now_ns() + period_ns, period_ns }
    }

    pub fn period_ns(&self) -> u64 {
        self.period_ns
    }

    /// Release time of tick `i`.
    pub fn release_ns(&self, i: u64) -> u64 {
        self.start_ns + i * self.period_ns
    }

    /// Sleeps until tick `i`'s release (returns at once if it has passed) and returns how late
    /// the thread woke (ns).
    pub fn wait_for(&self, i: u64) -> u64 {
        let release = self.release_ns(i);
        let ts = libc::timespec { tv_sec: (release / 1_000_000_000) as _, tv_nsec: (release % 1_000_000_000) as _ };
        loop {
            // SAFETY: valid timespec, no remainder wanted with TIMER_ABSTIME.
            let rc = unsafe {
                libc::clock_nanosleep(libc::CLOCK_MONOTONIC, libc::TIMER_ABSTIME, &raw const ts, std::ptr::null_mut())
            };
            if rc != libc::EINTR {
                break;
            }
        }
        now_ns().saturating_sub(release)
    }
}

/// What the real-time settings of a run came to.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct RtSettings {
    /// The process's memory is locked (`mlockall`): no page faults in the tick.
    pub memory_locked: bool,
    /// The control thread runs under SCHED_FIFO.
    pub fifo: bool,
    /// The control thread is pinned to one core.
    pub pinned_core: Option<usize>,
    /// Why a setting was not applied (the run goes on without it).
    pub notes: Vec<String>,
}

/// SCHED_FIFO priority of the control thread (libfranka's default is 80).
const FIFO_PRIORITY: i32 = 80;

/// Locks memory, then gives the calling thread SCHED_FIFO and pins it to the last core, each
/// where permitted. A refusal is a note, not a failure: the run goes on as an ordinary thread.
pub fn make_current_thread_realtime() -> RtSettings {
    let mut notes = Vec::new();
    // SAFETY: plain system calls on the current process/thread with valid arguments.
    let memory_locked = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) } == 0;
    if !memory_locked {
        notes.push(format!(
            "mlockall refused ({}): page faults can stall ticks; raise the memlock limit (ulimit -l unlimited) or grant CAP_IPC_LOCK",
            std::io::Error::last_os_error()
        ));
    }
    let param = libc::sched_param { sched_priority: FIFO_PRIORITY };
    // SAFETY: valid thread handle (self) and parameter.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &raw const param) };
    let fifo = rc == 0;
    if !fifo {
        notes.push(format!(
            "SCHED_FIFO refused ({}): the control thread is an ordinary thread, so wake-ups can be late under load; grant CAP_SYS_NICE or an rtprio limit (see the README's real-robot section)",
            std::io::Error::from_raw_os_error(rc)
        ));
    }
    let core = control_core();
    let pinned = pin_current_thread(core);
    if !pinned {
        notes.push(format!("pinning to core {core} refused ({})", std::io::Error::last_os_error()));
    }
    RtSettings { memory_locked, fifo, pinned_core: pinned.then_some(core), notes }
}

/// The core the control thread pins itself to: the last of those the process may run on (the
/// last core unless the process was started confined, e.g. by `taskset` or [`share_one_core`]).
pub fn control_core() -> usize {
    // SAFETY: a zeroed set is valid; the call fills it for the calling thread.
    let allowed = unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        (libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &raw mut set) == 0)
            .then(|| (0..libc::CPU_SETSIZE as usize).rev().find(|&c| libc::CPU_ISSET(c, &set)))
    };
    allowed.flatten().unwrap_or_else(|| std::thread::available_parallelism().map_or(1, std::num::NonZero::get) - 1)
}

/// `--one-core`: confines the calling thread, and so every thread started after it (the
/// policy's pool, the planner, the logger), to [`control_core`], so the policy computes only
/// while the control thread (SCHED_FIFO) sleeps and no other core runs anything of the process
/// during a tick. Call it before any thread starts. On the 2-core VMs of sessions 26-32 the
/// tick's compute p99 fell from 41-58 us to 38-39 us at 10^5 ticks with the policy inferring,
/// and the policy ran 1.5x slower (`docs/results/realtime-s32/`). At 10^6 ticks (session 33,
/// one run each) p99 48.5 against 53.0 us, but 311 deadline misses against 115: an option, not
/// the default (README, "bench realtime"). Returns the core.
pub fn share_one_core() -> std::io::Result<usize> {
    let core = control_core();
    if pin_current_thread(core) { Ok(core) } else { Err(std::io::Error::last_os_error()) }
}

/// Restricts the calling thread (and the threads it starts afterwards) to `core`; false (with
/// `errno` set) where refused.
fn pin_current_thread(core: usize) -> bool {
    // SAFETY: the set is zeroed and filled with one valid CPU index before use.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(core, &mut set);
        libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &raw const set) == 0
    }
}

/// Undoes the memory lock (the other settings end with the thread).
pub fn release_memory_lock() {
    // SAFETY: no arguments; harmless when nothing is locked.
    unsafe { libc::munlockall() };
}

/// Lowers the calling thread's priority (nice 10, SCHED_BATCH): background work (policy,
/// planner, logger) then yields the cores to the control thread when it wakes.
pub fn make_current_thread_background() {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: plain system calls on the current thread with valid arguments; failures leave the
    // thread at normal priority, which is correct, only less favourable to the control thread.
    unsafe {
        libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_BATCH, &raw const param);
        libc::setpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t, 10);
    }
}

/// Starts rayon's global pool, where the policy computes ([`crate::policy::runtime::in_pool`]),
/// with each of its threads at background priority ([`make_current_thread_background`]), so the
/// control thread pre-empts them the moment it wakes. Call it before anything uses the pool and
/// after [`share_one_core`] where that is asked (the pool is sized from the cores the process
/// may use when it starts). False if the pool had already started: its threads keep the
/// priority they have.
pub fn start_background_pool() -> bool {
    rayon::ThreadPoolBuilder::new().start_handler(|_| make_current_thread_background()).build_global().is_ok()
}

/// The calling thread's scheduling policy, restored when dropped: for code that must leave a
/// thread as it found it (a library that raises the caller's priority, a control session that
/// raises it for its own duration).
#[derive(Debug)]
pub struct SchedulingRestore {
    policy: i32,
    priority: i32,
}

impl SchedulingRestore {
    /// Saves the calling thread's policy and priority.
    pub fn save() -> Self {
        let mut policy = libc::SCHED_OTHER;
        let mut param = libc::sched_param { sched_priority: 0 };
        // SAFETY: valid thread handle (self) and out-pointers; on failure the defaults stand.
        unsafe { libc::pthread_getschedparam(libc::pthread_self(), &raw mut policy, &raw mut param) };
        Self { policy, priority: param.sched_priority }
    }

    /// Saves the calling thread's scheduling, then gives it SCHED_FIFO at the control thread's
    /// priority where permitted. Returns whether FIFO was granted.
    pub fn raise_to_fifo() -> (Self, bool) {
        let saved = Self::save();
        let param = libc::sched_param { sched_priority: FIFO_PRIORITY };
        // SAFETY: valid thread handle (self) and parameter.
        let granted =
            unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &raw const param) } == 0;
        (saved, granted)
    }
}

impl Drop for SchedulingRestore {
    fn drop(&mut self) {
        let param = libc::sched_param { sched_priority: self.priority };
        // SAFETY: valid thread handle (self) and parameter; a refusal leaves the thread as is.
        unsafe { libc::pthread_setschedparam(libc::pthread_self(), self.policy, &raw const param) };
    }
}
