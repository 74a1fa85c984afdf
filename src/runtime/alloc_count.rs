//! Counting heap allocations made inside control ticks. A program that wants the figure installs
//! [`CountingAllocator`] as its global allocator (the `flowram` binary and the real-time tests
//! do); the control thread marks its ticks with [`TickScope`], and [`tick_allocations`] reads the
//! count. Without the allocator installed nothing is counted and [`is_installed`] says so.
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// The system allocator, counting the allocations of threads inside a tick.
pub struct CountingAllocator;

static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);
static INSTALLED: AtomicBool = AtomicBool::new(false);

thread_local! {
    static IN_TICK: Cell<bool> = const { Cell::new(false) };
}

fn count() {
    // `try_with`: thread-local storage may already be gone while a thread exits.
    if IN_TICK.try_with(Cell::get).unwrap_or(false) {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
    }
    if !INSTALLED.load(Ordering::Relaxed) {
        INSTALLED.store(true, Ordering::Relaxed);
    }
}

// SAFETY: every call is forwarded unchanged to the system allocator; counting touches only
// atomics and a const-initialised thread-local (no allocation, no re-entry).
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        count();
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

/// Marks the current thread as inside a tick until dropped.
pub struct TickScope(());

impl TickScope {
    pub fn enter() -> Self {
        IN_TICK.with(|t| t.set(true));
        Self(())
    }
}

impl Drop for TickScope {
    fn drop(&mut self) {
        IN_TICK.with(|t| t.set(false));
    }
}

/// Allocations counted inside ticks since the process started (all threads).
pub fn tick_allocations() -> u64 {
    ALLOCATIONS.load(Ordering::Relaxed)
}

/// Whether [`CountingAllocator`] is the global allocator (it has seen an allocation).
pub fn is_installed() -> bool {
    drop(std::hint::black_box(Box::new(0u8)));
    INSTALLED.load(Ordering::Relaxed)
}
