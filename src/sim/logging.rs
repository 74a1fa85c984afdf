//! Routes MuJoCo's warnings to stderr (never stdout, which carries `--json` output, and never
//! MuJoCo's default MUJOCO_LOG.TXT in the working folder).
use std::sync::Once;

use mujoco_rs::prelude::*;

static INSTALL: Once = Once::new();

/// Warnings that flowram's scene composition triggers by design (see `scene::compose`).
const EXPECTED: [&str; 1] = ["Attaching a spec with an empty prefix"];

pub(crate) fn install() {
    INSTALL.call_once(|| {
        // SAFETY: runs once, before this process loads its first model.
        unsafe { set_log_handler(handle) };
    });
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
    eprintln!("mujoco: {subject}{}", message.body().map(|b| format!("\n{b}")).unwrap_or_default());
}
