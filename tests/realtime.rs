//! The 1 kHz tick does not allocate: a counting global allocator sees no allocation across a
//! tracking run's control ticks (controller and simulated robot cycle), after the first tick.
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use flowram::control::backend::{Cycle, RobotBackend};
use flowram::control::osc_config::OscConfig;
use flowram::rollout::stack::build_runner;
use flowram::sim::World;
use nalgebra::{Translation3, UnitQuaternion, Vector3};

struct Counting;
static COUNTING: AtomicBool = AtomicBool::new(false);
static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if COUNTING.load(Ordering::Relaxed) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if COUNTING.load(Ordering::Relaxed) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn control_ticks_do_not_allocate() {
    let mut world = World::load_named("default").unwrap();
    let mut runner = build_runner(&world, OscConfig::default_profile().unwrap()).unwrap();
    let home = world.arm_state().tcp_in_base;
    let target = Translation3::new(0.1, -0.1, -0.05) * home * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3);
    let goal = runner.ik.solve(runner.controller.kinematics_mut(), &target, &world.read_state().q).unwrap().q;
    runner.controller.set_goal(&goal);
    let mut ticks = 0u32;
    world
        .control(|state| {
            let command = runner.controller.tick(state);
            ticks += 1;
            if ticks == 1 {
                COUNTING.store(true, Ordering::SeqCst); // from the second tick on
            }
            if ticks == 2000 {
                COUNTING.store(false, Ordering::SeqCst);
                return Cycle::Finish(command);
            }
            if ticks == 700 {
                runner.controller.set_goal(&home_goal(&goal)); // a re-plan mid-motion, too
            }
            Cycle::Continue(command)
        })
        .unwrap();
    assert!(runner.controller.osc().stats().ticks >= 2000);
    assert_eq!(ALLOCATIONS.load(Ordering::SeqCst), 0, "heap allocations inside control ticks");
}

fn home_goal(goal: &flowram::robot::JointVector) -> flowram::robot::JointVector {
    let mut q = *goal;
    q[0] -= 0.2;
    q
}
