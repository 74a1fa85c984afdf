//! MuJoCo's warnings and errors, routed to whoever runs the library: a handler the program
//! registers with [`set_warning_handler`] (the `flowram` binary prints them to stderr), or,
//! until one is registered, a short in-memory list read with [`take_warnings`]. Never stdout
//! (which carries JSON output) and never MuJoCo's default MUJOCO_LOG.TXT in the working folder.
use std::sync::{Mutex, Once, RwLock};

use mujoco_rs::prelude::*;

static INSTALL: Once = Once::new();

/// Where MuJoCo's messages go; `None`: into [`PENDING`].
static HANDLER: RwLock<Option<fn(&str)>> = RwLock::new(None);

/// Messages seen while no handler was registered (the newest [`PENDING_MAX`]).
static PENDING: Mutex<Vec<String>> = Mutex::new(Vec::new());
const PENDING_MAX: usize = 64;

/// Warnings that flowram's scene composition triggers by design (see `scene::compose`).
const EXPECTED: [&str; 1] = ["Attaching a spec with an empty prefix"];

pub(crate) fn install() {
    INSTALL.call_once(|| {
        // SAFETY: runs once, before this process loads its first model.
        unsafe { set_log_handler(handle) };
    });
}

/// Sends every later MuJoCo warning or error (one line of text, `mujoco: ...`) to `handler`.
pub fn set_warning_handler(handler: fn(&str)) {
    if let Ok(mut h) = HANDLER.write() {
        *h = Some(handler);
    }
}

/// The MuJoCo messages seen while no handler was registered, oldest first (and forgets them).
pub fn take_warnings() -> Vec<String> {
    PENDING.lock().map(|mut p| std::mem::take(&mut *p)).unwrap_or_default()
}

fn handle(message: &MjLogMessage) {
    let level = message.level();
    if matches!(level, MjtLogLevel::mjLOG_DEBUG | MjtLogLevel::mjLOG_INFO) {
        return;
    }
    let subject = message.subject();
    if EXPECTED.iter().any(|e| subject.contains(e)) {
        return;
    }
    let text = format!("mujoco: {subject}{}", message.body().map(|b| format!("\n{b}")).unwrap_or_default());
    match HANDLER.read().ok().and_then(|h| *h) {
        Some(handler) => handler(&text),
        None => {
            if let Ok(mut pending) = PENDING.lock() {
                if pending.len() == PENDING_MAX {
                    pending.remove(0);
                }
                pending.push(text);
            }
        }
    }
}
