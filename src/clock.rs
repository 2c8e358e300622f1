//! The server's clock: the wall-clock time against which liveness (how old the newest sample
//! is), the future-time check of ingest, retention and creation stamps are judged.
//!
//! Measurement times come with the data and order everything the filters do; the server's
//! clock only says how that data relates to "now". It sits behind [`Clock`] so that a test (or
//! a replay tool) can set it instead of sleeping. Imports nothing of the crate.

use std::sync::Arc;
use std::sync::atomic::{AtomicI64, Ordering};

/// Nanoseconds in a second.
pub const NS_PER_S: f64 = 1e9;

/// A source of the current time (ns since the Unix epoch, UTC).
pub trait Clock: Send + Sync + std::fmt::Debug {
    /// Now (ns since the Unix epoch).
    fn now_ns(&self) -> i64;
}

/// The operating system's wall clock.
#[derive(Debug, Default, Clone, Copy)]
pub struct SystemClock;

impl Clock for SystemClock {
    fn now_ns(&self) -> i64 {
        wall_now_ns()
    }
}

/// A clock that moves only when told (tests, replays). Clones share the same time.
#[derive(Debug, Clone)]
pub struct ManualClock(Arc<AtomicI64>);

impl ManualClock {
    /// A clock reading `now_ns`.
    pub fn new(now_ns: i64) -> Self {
        Self(Arc::new(AtomicI64::new(now_ns)))
    }

    /// Sets the time.
    pub fn set_ns(&self, now_ns: i64) {
        self.0.store(now_ns, Ordering::SeqCst);
    }

    /// Moves the time on by `seconds` (back when negative).
    pub fn advance_s(&self, seconds: f64) {
        self.0
            .fetch_add((seconds * NS_PER_S).round() as i64, Ordering::SeqCst);
    }
}

impl Clock for ManualClock {
    fn now_ns(&self) -> i64 {
        self.0.load(Ordering::SeqCst)
    }
}

/// The shared handle the service keeps.
pub type SharedClock = Arc<dyn Clock>;

/// The system clock as a shared handle.
pub fn system() -> SharedClock {
    Arc::new(SystemClock)
}

/// The operating system's wall-clock time (ns since the Unix epoch); 0 before 1970, saturating
/// in 2262.
pub fn wall_now_ns() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_manual_clock_moves_only_when_told_and_its_clones_share_it() {
        let c = ManualClock::new(1_000);
        let shared: SharedClock = Arc::new(c.clone());
        assert_eq!(shared.now_ns(), 1_000);
        c.advance_s(2.5);
        assert_eq!(shared.now_ns(), 2_500_001_000);
        c.set_ns(7);
        assert_eq!(shared.now_ns(), 7);
    }

    #[test]
    fn the_system_clock_reads_after_2026() {
        // 2026-01-01T00:00:00Z: a clock reading earlier is broken, not merely skewed.
        assert!(SystemClock.now_ns() > 1_767_225_600_000_000_000);
    }
}
