//! The watchdog of a real-time run: a request for a keyframe that stays unanswered (the policy
//! or the planner went silent, hung or died) for longer than its limit ends the run while the
//! arm holds its pose. Holding needs nothing from the watchdog: with no new plan the trajectory
//! stays at its last goal and the controller keeps the arm there; the watchdog decides when to
//! give up and says why.

/// Counts ticks since the outstanding request was made.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Watchdog {
    limit: u64,
    since: Option<u64>,
}

impl Watchdog {
    pub fn new(limit_ticks: u64) -> Self {
        Self { limit: limit_ticks, since: None }
    }

    /// A request was made at `tick`.
    pub fn arm(&mut self, tick: u64) {
        self.since = Some(tick);
    }

    /// The request was answered.
    pub fn disarm(&mut self) {
        self.since = None;
    }

    /// `Some(ticks waited)` once the outstanding request is older than the limit.
    pub fn expired(&self, tick: u64) -> Option<u64> {
        self.since.map(|s| tick - s).filter(|&waited| waited > self.limit)
    }
}

#[cfg(test)]
mod tests {
    use super::Watchdog;

    #[test]
    fn expires_only_while_armed_and_after_the_limit() {
        let mut w = Watchdog::new(10);
        assert_eq!(w.expired(100), None);
        w.arm(5);
        assert_eq!(w.expired(15), None);
        assert_eq!(w.expired(16), Some(11));
        w.disarm();
        assert_eq!(w.expired(1000), None);
    }
}
