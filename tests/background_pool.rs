//! `runtime::pacing::start_background_pool`, in a test binary of its own: rayon's global pool
//! starts once per process, and no other test here may start it first.
use flowram::runtime::pacing::start_background_pool;

#[test]
fn the_policys_pool_starts_at_background_priority_and_only_once() {
    assert!(start_background_pool(), "the global pool had started before the test");
    // on a pool thread (in_pool runs the work on one): SCHED_BATCH at nice 10
    let (policy, nice) = flowram::policy::runtime::in_pool(|| {
        // SAFETY: plain queries about the calling thread.
        unsafe {
            *libc::__errno_location() = 0;
            let nice = libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t);
            (libc::sched_getscheduler(0), nice)
        }
    });
    assert_eq!(policy, libc::SCHED_BATCH);
    assert_eq!(nice, 10);
    // this (test) thread is not a pool thread and keeps its priority
    // SAFETY: as above.
    assert_ne!(unsafe { libc::sched_getscheduler(0) }, libc::SCHED_BATCH);
    assert!(!start_background_pool(), "a second start cannot change the running pool");
}
