//! The Franka Hand on worker threads. Its service is a separate TCP connection whose replies
//! block (a move or a grasp answers when the fingers stop), so nothing on the
//! control thread may call it: the control callback only publishes the wanted state (an atomic
//! and an unpark: no lock, no allocation); a command thread moves the fingers on each change,
//! and a state thread publishes the measured width for the control callback to read.
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};
use std::thread::{self, JoinHandle};

use ::franka::Gripper;

use crate::control::backend::BackendError;

/// Fully open (m) and the finger speed of every move (m/s).
const OPEN_WIDTH: f64 = 0.08;
const SPEED: f64 = 0.1;
/// Grasp force (N). The grasp's tolerances accept any width between closed and open, so the
/// hand reports a grasp on nothing as a success too: the grasp check is the controller's
/// (`control::gripper`, from the published width).
const GRASP_FORCE: f64 = 20.0;

const WANT_OPEN: u8 = 1;
const WANT_CLOSED: u8 = 2;

#[derive(Debug, Default)]
struct Shared {
    /// WANT_OPEN / WANT_CLOSED, 0 before the first command.
    wanted: AtomicU8,
    /// Width (m) and its rate (m/s), f64 bits.
    width: AtomicU64,
    speed: AtomicU64,
    /// Commands sent and commands the hand refused or that failed.
    commands: AtomicU64,
    failures: AtomicU64,
    /// Failed reads of the hand's state (the width is then the last one read).
    read_errors: AtomicU64,
    stop: AtomicBool,
}

/// The hand's worker threads.
#[derive(Debug)]
pub struct GripperWorker {
    shared: Arc<Shared>,
    commander: Option<JoinHandle<()>>,
    last_wanted: Option<bool>,
}

impl GripperWorker {
    /// Connects to the hand at `host` (port 1338) and starts the threads. A command is sent
    /// only when it changes what the fingers are (open if wider than 4 cm when connected).
    pub fn start(host: &str) -> Result<Self, BackendError> {
        let hand = Arc::new(Gripper::new(host).map_err(|e| BackendError::Connect {
            address: format!("{host}:1338 (the hand)"),
            detail: e.to_string(),
        })?);
        let first = hand.read_once().map_err(|e| BackendError::Communication(format!("reading the hand: {e}")))?;
        let open = first.width > 0.04;
        let shared = Arc::new(Shared::default());
        shared.width.store(first.width.to_bits(), Ordering::Relaxed);
        // The state thread: blocks on the hand's state stream (a read times out after 1 s and
        // is retried) and publishes the width. It owns a clone of the connection and ends at
        // the next read after `stop` (never joined).
        {
            let (hand, shared) = (Arc::clone(&hand), Arc::clone(&shared));
            thread::Builder::new()
                .name("gripper-state".into())
                .spawn(move || {
                    let mut previous = (first.width, first.time.as_secs_f64());
                    while !shared.stop.load(Ordering::Relaxed) {
                        let Ok(s) = hand.read_once() else {
                            shared.read_errors.fetch_add(1, Ordering::Relaxed);
                            thread::sleep(std::time::Duration::from_millis(10));
                            continue;
                        };
                        let t = s.time.as_secs_f64();
                        if t > previous.1 {
                            let speed = (s.width - previous.0) / (t - previous.1);
                            shared.speed.store(speed.to_bits(), Ordering::Relaxed);
                        }
                        shared.width.store(s.width.to_bits(), Ordering::Relaxed);
                        previous = (s.width, t);
                    }
                })
                .map_err(|e| BackendError::Communication(format!("starting the hand's state thread: {e}")))?;
        }
        let commander = {
            let shared = Arc::clone(&shared);
            thread::Builder::new()
                .name("gripper-command".into())
                .spawn(move || command_loop(&hand, &shared))
                .map_err(|e| BackendError::Communication(format!("starting the hand's command thread: {e}")))?
        };
        Ok(Self { shared, commander: Some(commander), last_wanted: Some(open) })
    }

    /// Asks for the fingers open or closed; acts on changes only. Real-time safe (an atomic
    /// store and an unpark).
    pub fn command(&mut self, open: bool) {
        if self.last_wanted == Some(open) {
            return;
        }
        self.last_wanted = Some(open);
        self.shared.wanted.store(if open { WANT_OPEN } else { WANT_CLOSED }, Ordering::Release);
        if let Some(t) = &self.commander {
            t.thread().unpark();
        }
    }

    /// The measured finger width (m) and its rate (m/s).
    pub fn width_and_speed(&self) -> (f64, f64) {
        (
            f64::from_bits(self.shared.width.load(Ordering::Relaxed)),
            f64::from_bits(self.shared.speed.load(Ordering::Relaxed)),
        )
    }

    /// Commands sent to the hand, how many it refused or failed, and failed state reads.
    pub fn commands(&self) -> (u64, u64, u64) {
        let s = &self.shared;
        (s.commands.load(Ordering::Relaxed), s.failures.load(Ordering::Relaxed), s.read_errors.load(Ordering::Relaxed))
    }
}

impl Drop for GripperWorker {
    /// Tells the threads to end and leaves them: a command in flight returns when the hand
    /// answers, which a hand that stopped answering never does, and a drop must not hang.
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.commander.take() {
            t.thread().unpark();
        }
    }
}

/// Moves the fingers to the latest wanted state, one blocking command at a time.
fn command_loop(hand: &Gripper, shared: &Shared) {
    let mut done = 0u8;
    while !shared.stop.load(Ordering::Relaxed) {
        let wanted = shared.wanted.load(Ordering::Acquire);
        if wanted == done || wanted == 0 {
            thread::park();
            continue;
        }
        let ok = if wanted == WANT_OPEN {
            hand.move_gripper(OPEN_WIDTH, SPEED)
        } else {
            hand.grasp(0.0, SPEED, GRASP_FORCE, OPEN_WIDTH, OPEN_WIDTH)
        };
        shared.commands.fetch_add(1, Ordering::Relaxed);
        if !matches!(ok, Ok(true)) {
            shared.failures.fetch_add(1, Ordering::Relaxed);
        }
        done = wanted;
    }
}
