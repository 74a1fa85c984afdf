//! push_buttons: "push the _ button" and sequences "push the _ button, then push the _ button"
//! of up to three colours (Table A: colour(50)).
//!
//! Scene: `models/tasks/push_buttons.xml`, three sprung push buttons. Like RLBench's, a button
//! shows whether it has been pressed: its housing ring starts red and turns lime (0, 1, 0) once
//! its cap has gone down 3 mm, target or not, and stays lime for the episode (RLBench turns the
//! top plate and wrapper; here the cap carries the named colour, so the ring does). So the
//! scene says which buttons of a sequence are done, not only the keyframe index. The named
//! colours are RLBench's push_buttons list: its 20 colours less red and lime, the ring's two.
//! Variations (50, over those 18 colours c): 0-17 push colour v; 18-33 push v-18 then v-17;
//! 34-49 push v-34, v-33, v-32 (colours mod 18). The targets take random buttons; the other
//! buttons get random distinct other colours. Reset: buttons at x in [0.42, 0.64] m, y in
//! [-0.22, 0.22] m (world), at least 0.12 m apart. Expert (2 keyframes per button + a final
//! lift): closed gripper above the cap, press 8 mm into it, on to the next. Success: the presses
//! seen after each keyframe (a cap down more than 3 mm, RLBench's threshold) are exactly the
//! target colours, in order. That is stricter than RLBench, whose ordered condition set ignores
//! presses of other buttons: here a press of any button other than the next target fails the
//! episode (the same button pressed twice in a row counts once). Presses are read (and rings
//! turned) at the end of each keyframe, where RLBench checks its conditions at every simulation
//! step.
//!
//! Until 2026-12-07 (expert version 1) the housings were grey and never changed, and the colours
//! were all 20 (0-19 single, 20-34 pairs, 35-49 triples): a sequence's stage showed only in the
//! keyframe index (docs/experiments.md, session 35).
use nalgebra::{Translation3, Vector3};
use rand::rngs::StdRng;
use rand::seq::SliceRandom;

use super::colors::{self, COLORS};
use super::grasp::{keyframe, top_down};
use super::layout::{apart, scatter};
use super::{TargetAlternatives, Task, TaskError, TaskState};
use crate::control::keyframe::Keyframe;
use crate::sim::World;

const BUTTONS: usize = 3;
/// The named colours (indices into [`COLORS`]): RLBench's push_buttons list, all but red and
/// lime, which the housing rings show.
const PALETTE: [usize; 18] = [1, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19];
const _: () = assert!(PALETTE.len() == COLORS.len() - 2);
/// A housing ring before and after its button is pressed (RLBench's top plate and wrapper).
const UNPRESSED_RGBA: [f32; 4] = [1.0, 0.0, 0.0, 1.0];
const PRESSED_RGBA: [f32; 4] = [0.0, 1.0, 0.0, 1.0];
/// Cap travel below which a button counts as pressed (m): RLBench's, whose push_buttons counts a
/// press once the button's joint has moved 3 mm (`JointCondition(target_button_joint, 0.003)`).
/// Until 2026-12-04 this was 6 mm, which left the expert's 8 mm press a 2 mm margin and a policy
/// whose press stops 2 mm high no press at all (docs/experiments.md, session 18).
const PRESSED: f64 = -0.003;
/// How far the closed fingertips reach beyond the TCP, and how deep the expert presses (m).
const FINGERTIPS_BELOW_TCP: f64 = 0.0086;
const PRESS_DEPTH: f64 = 0.008;
/// Height of a cap's top above the table when up (m).
const CAP_TOP: f64 = 0.032;

pub struct PushButtons;

/// The colours to push for a variation, in order (indices into [`PALETTE`]).
fn sequence(variation: usize) -> Vec<usize> {
    let n = PALETTE.len();
    match variation {
        0..18 => vec![variation],
        18..34 => vec![variation - 18, (variation - 17) % n],
        _ => vec![(variation - 34) % n, (variation - 33) % n, (variation - 32) % n],
    }
}

fn housing(button: usize) -> String {
    format!("button_{button}_housing")
}

impl Task for PushButtons {
    fn name(&self) -> &'static str {
        "push_buttons"
    }

    fn variation_count(&self) -> usize {
        50
    }

    fn instruction(&self, variation: usize) -> String {
        sequence(variation)
            .iter()
            .map(|&c| format!("push the {} button", colors::name(PALETTE[c])))
            .collect::<Vec<_>>()
            .join(", then ")
    }

    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError> {
        let targets = sequence(variation);
        let mut others: Vec<usize> = (0..PALETTE.len()).filter(|c| !targets.contains(c)).collect();
        others.shuffle(rng);
        let mut palette: Vec<usize> = targets.iter().copied().chain(others).take(BUTTONS).collect();
        palette.shuffle(rng);
        let spots = scatter(rng, BUTTONS, 0.42..0.64, -0.22..0.22, apart(0.12));
        for (i, (spot, &color)) in spots.iter().zip(&palette).enumerate() {
            world.set_fixed_body_pose(&format!("button_{i}"), &Translation3::new(spot.x, spot.y, 0.75).into())?;
            world.set_geom_rgba(&format!("button_{i}_cap"), colors::rgba(PALETTE[color]))?;
            world.set_geom_rgba(&housing(i), UNPRESSED_RGBA)?;
            world.set_joint_position(&format!("button_{i}_press"), 0.0)?;
        }
        // Targets as button names, in the order to press them.
        let names =
            targets.iter().map(|c| format!("button_{}", palette.iter().position(|p| p == c).unwrap_or(0))).collect();
        Ok(TaskState { targets: names, events: Vec::new() })
    }

    /// Wrong: every button but the first to push.
    fn target_alternatives(&self, state: &TaskState) -> TargetAlternatives {
        let first = state.targets.first();
        let wrong = (0..BUTTONS).map(|i| format!("button_{i}")).filter(|n| Some(n) != first);
        TargetAlternatives { right: Vec::new(), wrong: TargetAlternatives::targeting(wrong) }
    }

    fn observe(&self, world: &mut World, state: &mut TaskState) -> Result<(), TaskError> {
        for i in 0..BUTTONS {
            let name = format!("button_{i}");
            if world.joint_position(&format!("{name}_press"))? < PRESSED {
                world.set_geom_rgba(&housing(i), PRESSED_RGBA)?;
                if state.events.last() != Some(&name) {
                    state.events.push(name);
                }
            }
        }
        Ok(())
    }

    fn expert_version(&self) -> u32 {
        2
    }

    fn success(&self, _world: &World, state: &TaskState) -> bool {
        state.events == state.targets
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        let down = top_down(0.0);
        let mut keyframes = Vec::with_capacity(2 * state.targets.len() + 1);
        let mut last = Vector3::zeros();
        for name in &state.targets {
            let base = world.body_pose(name)?.translation.vector;
            let top = base + Vector3::new(0.0, 0.0, CAP_TOP);
            keyframes.push(keyframe(top + Vector3::new(0.0, 0.0, 0.06), down, false));
            // The closed fingertips reach 8.6 mm beyond the TCP: press the cap 8 mm (of 10).
            keyframes.push(keyframe(top + Vector3::new(0.0, 0.0, FINGERTIPS_BELOW_TCP - PRESS_DEPTH), down, false));
            last = top;
        }
        keyframes.push(keyframe(last + Vector3::new(0.0, 0.0, 0.08), down, false));
        Ok(keyframes)
    }
}
