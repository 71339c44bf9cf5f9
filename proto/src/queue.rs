//! A bounded queue that drops its *oldest* item under overload and counts it.
//!
//! Every queue in shoal is one of these (DESIGN.md: "under overload the
//! oldest frame is dropped and counted, never an unbounded backlog").

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

#[derive(Debug)]
struct Inner<T> {
    items: VecDeque<T>,
    closed: bool,
}

/// Shared handle; clone it to give producers and the consumer their ends.
#[derive(Debug)]
pub struct DropOldestQueue<T> {
    state: Arc<(Mutex<Inner<T>>, Condvar)>,
    capacity: usize,
    pushed: Arc<AtomicU64>,
    dropped: Arc<AtomicU64>,
}

impl<T> Clone for DropOldestQueue<T> {
    fn clone(&self) -> Self {
        Self {
            state: self.state.clone(),
            capacity: self.capacity,
            pushed: self.pushed.clone(),
            dropped: self.dropped.clone(),
        }
    }
}

/// Why `pop_timeout` returned nothing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PopError {
    Timeout,
    /// Closed and drained.
    Closed,
}

impl<T> DropOldestQueue<T> {
    /// A queue holding at most `capacity` items (at least 1).
    pub fn new(capacity: usize) -> Self {
        Self {
            state: Arc::new((
                Mutex::new(Inner {
                    items: VecDeque::with_capacity(capacity.max(1)),
                    closed: false,
                }),
                Condvar::new(),
            )),
            capacity: capacity.max(1),
            pushed: Arc::new(AtomicU64::new(0)),
            dropped: Arc::new(AtomicU64::new(0)),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Inner<T>> {
        // A panic while holding this lock cannot leave the deque inconsistent.
        self.state.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Enqueue; when full, the oldest item is dropped (and counted). Returns
    /// `false` if the queue is closed (the item is discarded).
    pub fn push(&self, item: T) -> bool {
        let mut g = self.lock();
        if g.closed {
            return false;
        }
        if g.items.len() >= self.capacity {
            g.items.pop_front();
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
        g.items.push_back(item);
        self.pushed.fetch_add(1, Ordering::Relaxed);
        drop(g);
        self.state.1.notify_one();
        true
    }

    /// Wait up to `timeout` for an item.
    pub fn pop_timeout(&self, timeout: Duration) -> Result<T, PopError> {
        let deadline = Instant::now() + timeout;
        let mut g = self.lock();
        loop {
            if let Some(item) = g.items.pop_front() {
                return Ok(item);
            }
            if g.closed {
                return Err(PopError::Closed);
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(PopError::Timeout);
            }
            g = self
                .state
                .1
                .wait_timeout(g, deadline - now)
                .map(|(g, _)| g)
                .unwrap_or_else(|e| e.into_inner().0);
        }
    }

    /// Take everything queued now without waiting.
    pub fn drain(&self) -> Vec<T> {
        self.lock().items.drain(..).collect()
    }

    /// Stop accepting items and wake the consumer.
    pub fn close(&self) {
        self.lock().closed = true;
        self.state.1.notify_all();
    }

    pub fn len(&self) -> usize {
        self.lock().items.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Items accepted since creation.
    pub fn pushed(&self) -> u64 {
        self.pushed.load(Ordering::Relaxed)
    }

    /// Items dropped for overload since creation.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overload_drops_the_oldest_and_counts_it() {
        let q = DropOldestQueue::new(2);
        for i in 0..5 {
            q.push(i);
        }
        assert_eq!(q.dropped(), 3);
        assert_eq!(q.drain(), vec![3, 4]);
    }

    #[test]
    fn closed_queue_drains_then_reports_closed() {
        let q = DropOldestQueue::new(4);
        q.push(1);
        q.close();
        assert!(!q.push(2));
        assert_eq!(q.pop_timeout(Duration::from_millis(1)), Ok(1));
        assert_eq!(
            q.pop_timeout(Duration::from_millis(1)),
            Err(PopError::Closed)
        );
    }

    #[test]
    fn pop_wakes_on_push_from_another_thread() {
        let q = DropOldestQueue::new(1);
        let p = q.clone();
        let t = std::thread::Builder::new()
            .name("producer".into())
            .spawn(move || {
                std::thread::sleep(Duration::from_millis(20));
                p.push(7u8);
            })
            .unwrap();
        assert_eq!(q.pop_timeout(Duration::from_secs(5)), Ok(7));
        t.join().unwrap();
    }
}
