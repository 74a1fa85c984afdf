//! stack_blocks: "stack _ _ blocks", e.g. "stack 3 red blocks" (Table A: colour, count (60)).
//!
//! Scene: `models/tasks/stack_blocks.xml`, six 4 cm blocks and a stacking platform.
//! Variations: 20 colours x counts 2, 3, 4 (v = 3 * colour + count - 2). Reset: four blocks of
//! the target colour and two of other colours, at x in [0.38, 0.66] m, y in [-0.28, 0.28] m
//! (world), at least 8 cm apart and from the platform, turned by up to 45 deg; the platform
//! at x in [0.5, 0.58], y in [-0.05, 0.05]. The blocks to stack are the `count` blocks of the
//! target colour with the smallest y (the robot's right first), taken in that order: a rule the
//! camera can see, so the next block is a function of the scene and not of a hidden index (four
//! blocks look alike). Expert (6 keyframes per block): above the block, down and close, lift,
//! above the stack, down to the next level and open, lift. Success: at
//! least `count` blocks of the target colour on the platform's footprint (within 2.5 cm of its
//! centre), one per level, the stack standing.
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector2, Vector3};
use rand::Rng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;

use super::colors::{self, COLORS};
use super::grasp::{clearest_yaw, pick_and_place, symmetric_yaw, top_down};
use super::layout::{apart, scatter};
use super::{TargetAlternatives, Task, TaskError, TaskState};
use crate::control::keyframe::Keyframe;
use crate::sim::World;

const TABLE_Z: f64 = 0.75;
const BLOCKS: usize = 6;
const TARGET_BLOCKS: usize = 4;
const SIZE: f64 = 0.04;
const PLATFORM_TOP: f64 = 0.005;

pub struct StackBlocks;

fn colour_and_count(variation: usize) -> (usize, usize) {
    (variation / 3, variation % 3 + 2)
}

/// The blocks to stack, in order: of the target-colour blocks at `spots` (`block_0`...), the
/// `count` with the smallest y (the robot's right first), y rounded to 0.1 mm, equal rounded y
/// going to the smaller x (no camera tells 0.1 mm apart). The order is visible in the scene, so
/// a policy can learn which block comes next. Session 24's datasets were collected with exactly
/// this key.
fn stacking_order(spots: &[Vector2<f64>], count: usize) -> Vec<String> {
    let mut order: Vec<usize> = (0..spots.len()).collect();
    let key = |i: &usize| ((spots[*i].y * 1e4).round() as i64, (spots[*i].x * 1e4).round() as i64);
    order.sort_by_key(key);
    order.into_iter().take(count).map(|i| format!("block_{i}")).collect()
}

fn yaw_of(pose: &Isometry3<f64>) -> f64 {
    let x = pose.rotation * Vector3::x();
    x.y.atan2(x.x)
}

impl Task for StackBlocks {
    fn name(&self) -> &'static str {
        "stack_blocks"
    }

    fn variation_count(&self) -> usize {
        COLORS.len() * 3
    }

    fn instruction(&self, variation: usize) -> String {
        let (colour, count) = colour_and_count(variation);
        format!("stack {count} {} blocks", colors::name(colour))
    }

    fn reset(&self, world: &mut World, variation: usize, rng: &mut StdRng) -> Result<TaskState, TaskError> {
        let (colour, count) = colour_and_count(variation);
        let platform = Vector2::new(rng.random_range(0.5..0.58), rng.random_range(-0.05..0.05));
        world.set_fixed_body_pose("platform", &Translation3::new(platform.x, platform.y, TABLE_Z).into())?;
        let spots = scatter(rng, BLOCKS, 0.38..0.66, -0.28..0.28, |placed, p| {
            (p - platform).norm() > 0.12 && apart(0.08)(placed, p)
        });
        let mut others: Vec<usize> = (0..COLORS.len()).filter(|&c| c != colour).collect();
        others.shuffle(rng);
        for (i, spot) in spots.iter().enumerate() {
            let name = format!("block_{i}");
            let yaw = rng.random_range(-45f64..45.0).to_radians();
            world.set_body_pose(
                &name,
                &Isometry3::from_parts(
                    Translation3::new(spot.x, spot.y, TABLE_Z + SIZE / 2.0),
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
                ),
            )?;
            let c = if i < TARGET_BLOCKS { colour } else { others[i - TARGET_BLOCKS] };
            world.set_geom_rgba(&name, colors::rgba(c))?;
        }
        Ok(TaskState { targets: stacking_order(&spots[..TARGET_BLOCKS], count), events: Vec::new() })
    }

    fn success(&self, world: &World, state: &TaskState) -> bool {
        let Ok(platform) = world.body_pose("platform") else { return false };
        let centre = platform.translation.vector.xy();
        // Blocks 0..TARGET_BLOCKS carry the target colour (see `reset`).
        let mut levels: Vec<usize> = (0..TARGET_BLOCKS)
            .filter_map(|i| world.body_pose(&format!("block_{i}")).ok())
            .filter(|p| (p.translation.vector.xy() - centre).norm() < 0.025)
            .map(|p| ((p.translation.z - TABLE_Z - PLATFORM_TOP) / SIZE).floor().max(0.0) as usize)
            .collect();
        levels.sort_unstable();
        levels.dedup();
        let count = state.targets.len();
        // Levels 0..count all occupied by target-colour blocks.
        levels.len() >= count && levels.iter().take(count).enumerate().all(|(i, &l)| l == i)
    }

    /// Right: the other blocks of the named colour (success accepts any of them; the expert's
    /// rule stacks some later, or not at all); wrong: the two blocks of other colours. So the
    /// probe measures the colour, not whether a policy learnt the order.
    fn target_alternatives(&self, state: &TaskState) -> TargetAlternatives {
        let first = state.targets.first();
        let block = |i: usize| format!("block_{i}");
        let right = (0..TARGET_BLOCKS).map(block).filter(|n| Some(n) != first);
        TargetAlternatives {
            right: TargetAlternatives::targeting(right),
            wrong: TargetAlternatives::targeting((TARGET_BLOCKS..BLOCKS).map(block)),
        }
    }

    /// Success takes any `count` blocks of the named colour, one per level.
    fn targets_interchangeable(&self) -> bool {
        true
    }

    /// 2 since session 24: the named colour's blocks right to left ([`stacking_order`]); 1 took
    /// `block_0, block_1, ...`, an order the cameras cannot see.
    fn expert_version(&self) -> u32 {
        2
    }

    fn expert(&self, world: &World, state: &TaskState) -> Result<Vec<Keyframe>, TaskError> {
        let platform = world.body_pose("platform")?.translation.vector;
        let mut keyframes = Vec::new();
        for (level, name) in state.targets.iter().enumerate() {
            let block = world.body_pose(name)?;
            // Either pair of faces can be grasped: the one whose palm line passes farther from
            // the stack and the other blocks (the palm is lower than a two-block stack's top
            // when the fingers reach a block on the table).
            let obstacles: Vec<Vector3<f64>> = std::iter::once(Ok(platform))
                .chain(
                    (0..BLOCKS)
                        .map(|i| format!("block_{i}"))
                        .filter(|n| n != name)
                        .map(|n| world.body_pose(&n).map(|p| p.translation.vector)),
                )
                .collect::<Result<_, _>>()?;
            let first = symmetric_yaw(yaw_of(&block), std::f64::consts::FRAC_PI_2, 0.0);
            let second = symmetric_yaw(first + std::f64::consts::FRAC_PI_2, std::f64::consts::PI, 0.0);
            let yaw = clearest_yaw(&block.translation.vector, [first, second], &obstacles);
            let pick = block.translation.vector + Vector3::new(0.0, 0.0, 0.005);
            let place = Vector3::new(
                platform.x,
                platform.y,
                TABLE_Z + PLATFORM_TOP + SIZE * (level as f64 + 0.5) + 0.005 + 0.004,
            );
            keyframes.extend(pick_and_place(pick, top_down(yaw), place, top_down(0.0), 0.12));
        }
        Ok(keyframes)
    }
}
