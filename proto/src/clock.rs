//! Injected clocks (DESIGN.md: "Time comes from an injected clock").
//!
//! Services ask a [`Clock`] for `now`; the simulator and log replay drive a
//! [`ManualClock`], so a run is reproducible; deployments use [`WallClock`].

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

pub trait Clock: Send + Sync + std::fmt::Debug {
    /// Nanoseconds on this clock's time line.
    fn now_ns(&self) -> u64;
}

/// UNIX time.
#[derive(Debug, Default, Clone, Copy)]
pub struct WallClock;

impl Clock for WallClock {
    fn now_ns(&self) -> u64 {
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0)
    }
}

/// A clock that only moves when told to (simulation time, replay time).
#[derive(Debug, Default)]
pub struct ManualClock {
    ns: AtomicU64,
}

impl ManualClock {
    pub fn new(start_ns: u64) -> ManualClock {
        ManualClock {
            ns: AtomicU64::new(start_ns),
        }
    }
    /// Move to `ns`; never backwards.
    pub fn advance_to(&self, ns: u64) {
        self.ns.fetch_max(ns, Ordering::Relaxed);
    }
}

impl Clock for ManualClock {
    fn now_ns(&self) -> u64 {
        self.ns.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manual_clock_never_goes_back() {
        let c = ManualClock::new(10);
        c.advance_to(5);
        assert_eq!(c.now_ns(), 10);
        c.advance_to(20);
        assert_eq!(c.now_ns(), 20);
    }
}
