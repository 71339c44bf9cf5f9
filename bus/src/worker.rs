//! A background service thread that runs until told to stop.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;

/// A thread polling a stop flag, and its handle: [`Worker::stop`] (or
/// dropping the worker) raises the flag and waits for the thread.
#[derive(Debug)]
pub struct Worker {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Worker {
    /// Run `body` on a thread called `name`; it is given the stop flag to poll.
    pub fn spawn(
        name: impl Into<String>,
        body: impl FnOnce(Arc<AtomicBool>) + Send + 'static,
    ) -> std::io::Result<Worker> {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::Builder::new()
            .name(name.into())
            .spawn(move || body(flag))?;
        Ok(Worker {
            stop,
            thread: Some(thread),
        })
    }

    /// Raise the stop flag and wait for the thread.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            join_reporting(t);
        }
    }
}

/// Wait for `thread`; a panic in it is reported (logged at error level with
/// the thread's name and the panic message) rather than dropped, and `None`
/// is returned for it.
pub fn join_reporting<T>(thread: JoinHandle<T>) -> Option<T> {
    let name = thread.thread().name().unwrap_or("unnamed").to_string();
    match thread.join() {
        Ok(v) => Some(v),
        Err(payload) => {
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a non-text panic payload".to_string());
            tracing::error!(thread = %name, "thread panicked: {message}");
            None
        }
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        self.shutdown();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panicking_thread_is_reported_not_dropped() {
        let t = std::thread::Builder::new()
            .name("doomed".into())
            .spawn(|| -> u32 { panic!("camera 3 lost its sensor") })
            .unwrap();
        assert_eq!(join_reporting(t), None);
        let t = std::thread::spawn(|| 7u32);
        assert_eq!(join_reporting(t), Some(7));
    }
    use std::sync::atomic::AtomicU64;
    use std::time::Duration;

    #[test]
    fn stopping_and_dropping_both_end_the_thread() {
        let laps = Arc::new(AtomicU64::new(0));
        for by_drop in [false, true] {
            let l = laps.clone();
            let w = Worker::spawn("test-worker", move |stop| {
                while !stop.load(Ordering::Relaxed) {
                    l.fetch_add(1, Ordering::Relaxed);
                    std::thread::sleep(Duration::from_millis(1));
                }
            })
            .unwrap();
            std::thread::sleep(Duration::from_millis(20));
            if by_drop {
                drop(w);
            } else {
                w.stop();
            }
            let after = laps.load(Ordering::Relaxed);
            assert!(after > 0);
            std::thread::sleep(Duration::from_millis(20));
            assert_eq!(
                laps.load(Ordering::Relaxed),
                after,
                "the thread kept running"
            );
        }
    }
}
