//! close_jar: "close the _ jar" (20 colours; Table A: colour(20)).
//!
//! Scene: `models/tasks/close_jar.xml`, two jars and a lid. Reset: the target jar takes the
//! variation's colour, the other jar a random other colour; jars at x in [0.45, 0.62] m,
//! y in [-0.22, 0.22] m (world), at least 0.14 m apart; the lid flat on the table at least
//! 0.12 m from both. Expert (6 keyframes): above the lid, down and close, lift, above the named
//! jar, down until the lid rests on the rim and open, lift. Success: the lid upright (within 10
//! deg) on the named jar: centre within 12 mm of its axis and resting on its rim.
use nalgebra::{Translation3, Vector3};
use rand::Rng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;

use super::colors::{self, COLORS};
use super::grasp::{clearest_yaw, pick_and_place, top_down};
use super::layout::scatter;
use super::{TargetAlternatives, Task, TaskError, TaskState};
use crate::control::keyframe::Keyframe;
use crate::sim::World;

const TABLE_Z: f64 = 0.75;
const JAR_HEIGHT: f64 = 0.08;
const LID_HALF: f64 = 0.01;

pub struct CloseJar;

impl Task for CloseJar {
    fn name(&self) -> &'static str {
        "close_jar"
    }

    fn variation_count(&self) -> usize {
        COLORS.len()
    }

    fn instruction(&self, variation: usize) -> String {
        format!("close the {} jar", colors::name(variation))
    }

    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError> {
        let spots = scatter(rng, 3, 0.45..0.62, -0.22..0.22, |placed, p| {
            let gap = if placed.len() < 2 { 0.14 } else { 0.12 };
            placed.iter().all(|q| (p - q).norm() > gap)
        });
        let mut others: Vec<usize> = (0..COLORS.len()).filter(|&c| c != variation).collect();
        others.shuffle(rng);
        let target = rng.random_range(0..2usize);
        for (jar, spot) in spots.iter().take(2).enumerate() {
            let name = format!("jar_{jar}");
            world.set_fixed_body_pose(&name, &Translation3::new(spot.x, spot.y, TABLE_Z).into())?;
            world.set_geom_rgba(&name, colors::rgba(if jar == target { variation } else { others[0] }))?;
        }
        world.set_body_pose("lid", &Translation3::new(spots[2].x, spots[2].y, TABLE_Z + LID_HALF).into())?;
        Ok(TaskState { targets: vec![format!("jar_{target}")], events: Vec::new() })
    }

    fn success(&self, world: &World, state: &TaskState) -> bool {
        let (Ok(lid), Ok(jar)) = (world.body_pose("lid"), world.body_pose(&state.targets[0])) else { return false };
        let d = lid.translation.vector - jar.translation.vector;
        let upright = (lid.rotation * Vector3::z()).z > 10f64.to_radians().cos();
        let seated = (d.z - (JAR_HEIGHT + LID_HALF)).abs() < 0.006;
        upright && seated && d.xy().norm() < 0.012
    }

    /// Wrong: the other jar.
    fn target_alternatives(&self, state: &TaskState) -> TargetAlternatives {
        let wrong = ["jar_0", "jar_1"].into_iter().map(String::from).filter(|n| !state.targets.contains(n));
        TargetAlternatives { right: Vec::new(), wrong: TargetAlternatives::targeting(wrong) }
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        let lid = world.body_pose("lid")?.translation.vector;
        let jar = world.body_pose(&state.targets[0])?.translation.vector;
        // The lid is round, so any yaw grasps it; the hand's palm (20 cm along the fingers'
        // closing direction, 4.5 cm above the TCP) must not come down on a jar's top, which is
        // higher than the palm when the fingers reach the lid: the yaw whose palm line passes
        // farthest from both jars (in 5-degree steps, smaller turns first).
        let jars = [world.body_pose("jar_0")?.translation.vector, world.body_pose("jar_1")?.translation.vector];
        let turns = (0..36).map(|k: i32| f64::from(if k % 2 == 0 { k / 2 } else { -(k + 1) / 2 }) * 5f64.to_radians());
        let yaw = clearest_yaw(&lid, turns, &jars);
        let down = top_down(yaw);
        // The fingers close across the lid 5 mm above its centre; it is set down 3 mm above the
        // rim and dropped.
        let grasp = lid + Vector3::new(0.0, 0.0, 0.005);
        let place = jar + Vector3::new(0.0, 0.0, JAR_HEIGHT + LID_HALF + 0.005 + 0.003);
        Ok(pick_and_place(grasp, down, place, down, 0.12).to_vec())
    }
}
