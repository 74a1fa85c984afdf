//! Process-wide settings that the policy's CPU speed depends on. They must be applied before
//! any thread exists (first thing in `main`), so they live here and not in a lazy init.
//!
//! - `CANDLE_NUM_THREADS=1`: candle runs element-wise ops on its own spinning pool, which fights
//!   rayon's (scan kernels, convolutions, FPS, GEMM) for the cores.
//! - `RAYON_NUM_THREADS` = the available parallelism: without it candle calls
//!   `num_cpus::get_physical()` on every matmul, which parses `/proc/cpuinfo` (3.4 % of the
//!   policy benchmark's time in `perf`).
//! - glibc malloc keeps large blocks: by default every activation above the dynamic mmap threshold
//!   is mmap'ed, page-faulted in zeroed and munmap'ed on drop (11 % of the benchmark in page
//!   faults). With mmap off for malloc and a high trim threshold, freed activations stay in the
//!   heap for the next step: training step 6.6 -> 3.1 s at batch 8 (paper config); raising only
//!   the mmap threshold (at most 32 MiB) left the 60 MiB training activations on mmap. One arena:
//!   the pool threads' own arenas are mmap'ed heaps of at most 64 MiB, so with mmap off their
//!   large blocks failed over to the main arena on every allocation (training step 3.1 -> 5.3 s
//!   once it ran on pool threads, see [`in_pool`]; 3.0 s with one arena).
//!
//! A value the user already set in the environment wins.

/// Keep up to this much free memory at the top of the heap instead of returning it.
const TRIM_THRESHOLD: i32 = 1 << 30;

/// Applies the settings above. Call it as the first statement of `main`, before any thread
/// is spawned (it writes environment variables).
pub fn configure_process() {
    // SAFETY (both set_var calls): documented precondition of this function - no other thread
    // exists yet that could read the environment concurrently.
    if std::env::var_os("CANDLE_NUM_THREADS").is_none() {
        unsafe { std::env::set_var("CANDLE_NUM_THREADS", "1") };
    }
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        unsafe { std::env::set_var("RAYON_NUM_THREADS", threads.to_string()) };
    }
    configure_malloc();
}

/// The malloc part of [`configure_process`] alone: safe to call at any time, from any thread
/// (tests call it; they cannot set environment variables once the harness runs threads).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn configure_malloc() {
    if std::env::var_os("GLIBC_TUNABLES").is_some() {
        return;
    }
    // SAFETY: mallopt only changes allocator parameters; it is thread-safe in glibc. A zero
    // return means the parameter was refused, which leaves the default behaviour (slower, correct).
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_ARENA_MAX, 1);
        libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn configure_malloc() {}

/// Runs `work` on a thread of rayon's global pool (inline when already on one).
///
/// Every parallel kernel (GEMM, scan, convolutions) called from a thread outside the pool injects
/// its job, wakes a worker and sleeps until it is done: two context switches per operation,
/// ~60 per Euler step, which on this 2-core machine ate most of the second core (one Mamba
/// suffix pass 9.9 ms with 2 threads vs 11.6 ms with 1). From inside the pool the calling
/// worker takes its share of each job and the other steals the rest.
pub fn in_pool<R: Send>(work: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| work())
}
