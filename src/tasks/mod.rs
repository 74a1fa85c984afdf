//! RLBench-style tasks, one file per task: the objects each adds to the base scene
//! (`models/tasks/<task>.xml`), its variations and their instructions (the templates of the
//! paper's Table A), a seeded reset that randomises object placement within documented ranges,
//! a success check on the simulator state, and an expert that computes keyframes (TCP pose +
//! gripper) from the object poses, like RLBench's waypoints. Task definitions only: the
//! closed loop that runs them (with the expert or a learned policy) is the `rollout` module.
pub mod close_jar;
pub mod colors;
pub mod drag_stick;
pub mod grasp;
pub mod layout;
pub mod meat_off_grill;
pub mod open_drawer;
pub mod push_buttons;
pub mod put_item_in_drawer;
pub mod slide_block;
pub mod stack_blocks;
pub mod sweep_to_dustpan;
pub mod turn_tap;

use std::path::PathBuf;

use rand::rngs::StdRng;

use crate::control::keyframe::Keyframe;
use crate::sim::{SimError, World};

/// What a task remembers between keyframes.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TaskState {
    /// Named objects chosen at reset, in the order that matters (e.g. buttons to push).
    pub targets: Vec<String>,
    /// Events seen so far (e.g. buttons pressed, in order).
    pub events: Vec<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum TaskError {
    #[error("unknown task `{name}`; tasks: {valid}")]
    UnknownTask { name: String, valid: String },
    #[error("task {task} has variations 0 to {max}; {variation} is out of range")]
    BadVariation { task: &'static str, variation: usize, max: usize },
    #[error(transparent)]
    Sim(#[from] SimError),
}

/// One RLBench-style task.
pub trait Task: Send + Sync {
    fn name(&self) -> &'static str;
    fn variation_count(&self) -> usize;
    /// The language instruction of a variation.
    fn instruction(&self, variation: usize) -> String;
    /// Places the objects (randomised with `rng`) in a world freshly reset to `home`.
    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError>;
    /// Called after each keyframe: records events (presses, grasps) into the state, and shows
    /// in the scene what the task shows of them (push_buttons turns a pressed button's ring
    /// lime, as RLBench does), so the next observation sees it. `reset` undoes what this paints
    /// (`World::reset_to` does not restore colours).
    fn observe(&self, _world: &mut World, _state: &mut TaskState) -> Result<(), TaskError> {
        Ok(())
    }
    /// Whether the episode has succeeded, from the simulator state (and recorded events).
    fn success(&self, world: &World, state: &TaskState) -> bool;
    /// The expert's keyframes in the world frame, from the objects as they are now.
    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError>;
    /// The expert's version: raised whenever the expert demonstrates differently for the same
    /// seed and variation (collections record it, and datasets of an older version are
    /// refused by a resumed collection and named when trained or scored on). Default: 1.
    fn expert_version(&self) -> u32 {
        1
    }

    /// The MJCF files with the task's objects (default: `models/tasks/<name>.xml`; a task built
    /// on another's fixtures lists that task's file too).
    fn model_files(&self) -> Vec<PathBuf> {
        vec![model_file(self.name())]
    }

    /// Whether the task's success accepts its `targets` in any order (the expert's order is a
    /// convention, not the task): then a demonstration may take them in another order
    /// ([`crate::rollout::episode::Perturbation::shuffle_targets`]). Default: false.
    fn targets_interchangeable(&self) -> bool {
        false
    }

    /// For tasks whose instruction picks objects by colour, where another variation paints
    /// another scene: the same scene's states with other objects as targets, for the target
    /// probe (the expert of a `right` state goes to an object the instruction also accepts, of
    /// a `wrong` state to one it does not). Default: none.
    fn target_alternatives(&self, _state: &TaskState) -> TargetAlternatives {
        TargetAlternatives::default()
    }
}

/// See [`Task::target_alternatives`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TargetAlternatives {
    pub right: Vec<TaskState>,
    pub wrong: Vec<TaskState>,
}

impl TargetAlternatives {
    /// One single-target state per named object.
    pub(crate) fn targeting(names: impl IntoIterator<Item = String>) -> Vec<TaskState> {
        names.into_iter().map(|name| TaskState { targets: vec![name], events: Vec::new() }).collect()
    }
}

/// Every task, in Table A's order.
pub fn all() -> Vec<Box<dyn Task>> {
    vec![
        Box::new(open_drawer::OpenDrawer),
        Box::new(push_buttons::PushButtons),
        Box::new(slide_block::SlideBlock),
        Box::new(close_jar::CloseJar),
        Box::new(stack_blocks::StackBlocks),
        Box::new(meat_off_grill::MeatOffGrill),
        Box::new(turn_tap::TurnTap),
        Box::new(put_item_in_drawer::PutItemInDrawer),
        Box::new(drag_stick::DragStick),
        Box::new(sweep_to_dustpan::SweepToDustpan),
    ]
}

pub fn by_name(name: &str) -> Result<Box<dyn Task>, TaskError> {
    all().into_iter().find(|t| t.name() == name).ok_or_else(|| TaskError::UnknownTask {
        name: name.into(),
        valid: all().iter().map(|t| t.name()).collect::<Vec<_>>().join(", "),
    })
}

/// `models/tasks/<name>.xml`.
pub fn model_file(name: &str) -> PathBuf {
    crate::deps::models_dir().join("tasks").join(format!("{name}.xml"))
}

/// The world of a task: the default scene with the task's objects.
pub fn load_world(task: &dyn Task) -> Result<World, TaskError> {
    let scene = crate::sim::scene::resolve_scene("default")?;
    Ok(World::load_with(&scene, &task.model_files(), &crate::deps::Deps::locate())?)
}
