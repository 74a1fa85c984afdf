//! The closed loop: tasks, the simulated control stack and a keyframe source composed into
//! episodes, and the evaluations built on them.
//!
//! - [`stack`]: the simulated Panda and its control stack (IK -> ruckig -> OSC at 1 kHz);
//! - [`episode`]: the one episode loop (reset, observe, next keyframe, execute, until done),
//!   fed by the task's expert, nobody (idle), or a learned [`episode::KeyframePolicy`];
//! - [`learned`]: a trained FlowRAM checkpoint as a keyframe policy, in lock-step with the
//!   simulation;
//! - [`realtime`]: one such episode on the real-time runtime (the policy and the 1 kHz control
//!   thread run concurrently; the arm holds while the policy thinks);
//! - [`collection`]: expert demonstrations collected into datasets;
//! - [`evaluation`]: closed-loop success rates on held-out seeds, and held-out keyframe errors
//!   against trivial baselines;
//! - [`steps_grid`]: those success rates and latencies against Euler steps and DRS (the Table C
//!   analogue), tabulated from results files and plotted;
//! - [`faults`]: fault streams injected into the real stack, counting limit violations,
//!   non-finite torques and panics (`flowram bench faults`);
//! - [`shard`]: splitting collection and evaluation over processes and machines (which seeds a
//!   shard owns; the scheduler's environment), for `flowram merge` to combine.
pub mod collection;
pub mod episode;
pub mod evaluation;
pub mod faults;
pub mod learned;
pub mod realtime;
pub mod shard;
pub mod stack;
pub mod steps_grid;

use crate::control::backend::BackendError;
use crate::control::ik::IkError;
use crate::control::runner::StackError;
use crate::data::DataError;
use crate::policy::PolicyError;
use crate::sim::SimError;
use crate::tasks::TaskError;
use crate::unit_config::ConfigError;

/// What can go wrong running episodes and evaluations.
#[derive(Debug, thiserror::Error)]
pub enum RolloutError {
    #[error(transparent)]
    Task(#[from] TaskError),
    #[error(transparent)]
    Sim(#[from] SimError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("building the control stack")]
    Stack(#[from] StackError),
    #[error(transparent)]
    Backend(#[from] BackendError),
    #[error(transparent)]
    Policy(#[from] PolicyError),
    #[error(transparent)]
    Data(#[from] DataError),
    /// A keyframe that cannot be a target pose (non-finite position, zero quaternion).
    #[error("keyframe {index} is not a valid pose")]
    InvalidKeyframe { index: usize, source: IkError },
    /// A perturbation of expert demonstrations out of its ranges.
    #[error("{problem}")]
    Perturbation { problem: String },
    /// A learned policy was asked to act without camera frames to look at.
    #[error("the policy needs camera frames, but the episode observes no cameras")]
    NoCameras,
    /// The policy sees square frames of one size.
    #[error(
        "the policy needs square frames of one size; camera {camera} is {width}x{height} (the first is {size}x{size})"
    )]
    FrameSize { camera: String, width: usize, height: usize, size: usize },
    /// The operating system refused a thread of the real-time runtime.
    #[error("cannot start the real-time runtime's threads: {0}")]
    Thread(String),
    /// An episode to be saved as a demonstration recorded no images (no cameras, or no keyframes).
    #[error("the episode recorded no images")]
    NoImages,
    /// The policy returned no keyframe.
    #[error("the policy returned no keyframe")]
    NoKeyframe,
    /// A count that must be positive was zero (episodes, keyframes per episode).
    #[error("{what} must be at least 1")]
    Zero { what: &'static str },
    /// A baseline of the held-out evaluation has no training keyframes to average.
    #[error("no training keyframes of {of} to form a baseline from")]
    NoBaseline { of: String },
    #[error(transparent)]
    Shard(#[from] shard::ShardError),
    /// A manifest or results file that cannot be read as one.
    #[error("{} is not a valid flowram manifest ({problem}); delete it and re-run the shard", path.display())]
    Manifest { path: std::path::PathBuf, problem: String },
    /// An output folder or file that already holds other work.
    #[error(
        "{} already holds another run: {found}; this one is {asked}. Re-run with the same arguments to resume it, or write to a new path",
        dir.display()
    )]
    OtherRun { dir: std::path::PathBuf, found: String, asked: String },
    /// Results files that do not form one grid of comparable cells (`bench grid`).
    #[error("cannot tabulate the grid: {problem}")]
    Grid { problem: String },
    /// A figure that cannot be drawn or written.
    #[error("cannot draw {}: {problem}", path.display())]
    Plot { path: std::path::PathBuf, problem: String },
    /// Shard outputs that cannot be merged.
    #[error("cannot merge: {problem}")]
    Merge { problem: String },
}
