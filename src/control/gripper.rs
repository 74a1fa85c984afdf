//! The gripper: open/close commands to the hand, and the grasp check (the fingers were told to
//! close and stopped on something instead of closing fully).
use super::backend::RobotState;

/// Below this finger-gap speed the fingers count as stopped (m/s).
const STILL_SPEED: f64 = 2e-3;
/// Stopped for this many consecutive ticks counts as settled.
const STILL_TICKS: u32 = 40;
/// Closed on nothing: the gap is below this (m).
const EMPTY_WIDTH: f64 = 0.002;
/// Fully open: the gap is above this (m) (the Franka hand opens to 0.08 m).
const OPEN_WIDTH: f64 = 0.075;

/// What the fingers are doing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GraspState {
    /// Still moving toward the commanded state.
    Moving,
    /// Commanded open and fully open.
    Open,
    /// Commanded closed and stopped on an object this wide (m).
    Grasped { width: f64 },
    /// Commanded closed and closed on nothing.
    Empty,
    /// Commanded open but stopped before fully open (blocked).
    Blocked { width: f64 },
}

impl GraspState {
    /// The fingers have stopped (whatever the outcome).
    pub fn is_settled(&self) -> bool {
        !matches!(self, GraspState::Moving)
    }
}

/// What the gripper did, in words: `open`, `grasped (30.0 mm)`, `closed on nothing`, ...
impl std::fmt::Display for GraspState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            GraspState::Moving => write!(f, "still moving (timed out)"),
            GraspState::Open => write!(f, "open"),
            GraspState::Grasped { width } => write!(f, "grasped ({:.1} mm)", width * 1e3),
            GraspState::Empty => write!(f, "closed on nothing"),
            GraspState::Blocked { width } => write!(f, "blocked at {:.1} mm", width * 1e3),
        }
    }
}

/// Tracks the command and decides the grasp state from the finger motion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gripper {
    open: bool,
    still_ticks: u32,
}

impl Gripper {
    pub fn new(open: bool) -> Self {
        Self { open, still_ticks: 0 }
    }

    pub fn is_open_commanded(&self) -> bool {
        self.open
    }

    /// A new command; the fingers are considered moving until they settle again.
    pub fn command(&mut self, open: bool) {
        if open != self.open {
            self.open = open;
            self.still_ticks = 0;
        }
    }

    /// Call once per tick.
    pub fn update(&mut self, state: &RobotState) -> GraspState {
        if state.gripper_speed.abs() < STILL_SPEED {
            self.still_ticks = self.still_ticks.saturating_add(1);
        } else {
            self.still_ticks = 0;
        }
        if self.still_ticks < STILL_TICKS {
            return GraspState::Moving;
        }
        let width = state.gripper_width;
        match (self.open, width) {
            (true, w) if w > OPEN_WIDTH => GraspState::Open,
            (true, w) => GraspState::Blocked { width: w },
            (false, w) if w < EMPTY_WIDTH => GraspState::Empty,
            (false, w) => GraspState::Grasped { width: w },
        }
    }
}
