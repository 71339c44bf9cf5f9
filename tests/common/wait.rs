//! Polling with a deadline, for tests that wait on services over Zenoh.

use std::time::{Duration, Instant};

/// Poll `check` every 20 ms until it returns `Some` or `timeout` passes;
/// panics naming `what`.
pub fn wait_for<T>(what: &str, timeout: Duration, mut check: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(v) = check() {
            return v;
        }
        assert!(
            Instant::now() < deadline,
            "timed out after {timeout:?} waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}
