//! The solve's independent per-item steps (frames, track groups, pairs,
//! triangles, gate residuals) over a few threads with rayon: each item
//! computed by the same code as on one thread and the results collected in
//! item order, so a map is bit for bit the same whatever the thread count
//! ([`crate::FusionParams::threads`]).
//!
//! A whole solve runs inside one pool ([`install`]), so each step's items
//! are split by work stealing among the pool's threads, the solve's own
//! thread included: a part that no other thread takes (another process on
//! the core, say) is done by the thread that split it instead of being
//! waited for. A step with fewer than `min_per_thread` items per thread
//! stays on one thread.

use rayon::prelude::*;
use std::num::NonZeroUsize;
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

/// Threads to use for `requested` (0: the machine's available parallelism).
pub(crate) fn resolve_threads(requested: usize) -> usize {
    if requested > 0 {
        return requested;
    }
    std::thread::available_parallelism().map_or(1, NonZeroUsize::get)
}

/// The pools made so far, by thread count.
type Pools = Vec<(usize, Arc<rayon::ThreadPool>)>;

/// One pool per thread count, shared by every fusion instance of the
/// process (instances are many and short-lived in tests and evals; a pool's
/// threads sleep while nothing runs on them).
fn pool(threads: usize) -> Option<Arc<rayon::ThreadPool>> {
    static POOLS: OnceLock<Mutex<Pools>> = OnceLock::new();
    let mut pools = POOLS
        .get_or_init(Mutex::default)
        .lock()
        .unwrap_or_else(PoisonError::into_inner);
    if let Some((_, p)) = pools.iter().find(|(n, _)| *n == threads) {
        return Some(Arc::clone(p));
    }
    match rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("fusion-{i}"))
        .build()
    {
        Ok(p) => {
            let p = Arc::new(p);
            pools.push((threads, Arc::clone(&p)));
            Some(p)
        }
        Err(e) => {
            tracing::warn!("fusion: no pool of {threads} threads ({e}); solving on one");
            None
        }
    }
}

/// `f` inside the pool of `threads` threads (on the caller's thread when
/// `threads` ≤ 1 or no pool can be made), and the thread count the steps
/// may use.
pub(crate) fn install<R: Send>(threads: usize, f: impl FnOnce(usize) -> R + Send) -> R {
    match (threads > 1).then(|| pool(threads)).flatten() {
        Some(p) => p.install(|| f(threads)),
        None => f(1),
    }
}

/// Whether `n` items are worth splitting over `threads` threads: at least
/// `min_per_thread` each for two threads.
fn split(n: usize, threads: usize, min_per_thread: usize) -> bool {
    threads > 1 && n >= 2 * min_per_thread.max(1)
}

/// Smallest part a thread takes: a quarter of the minimum share, so that a
/// late thread's part is small.
fn min_len(min_per_thread: usize) -> usize {
    (min_per_thread / 4).max(1)
}

/// `items.iter().enumerate().map(f).collect()`, split over the current
/// pool's threads when `threads` > 1 and the items are many.
pub(crate) fn map<T, R, F>(items: &[T], threads: usize, min_per_thread: usize, f: F) -> Vec<R>
where
    T: Sync,
    R: Send,
    F: Fn(usize, &T) -> R + Sync,
{
    if !split(items.len(), threads, min_per_thread) {
        return items.iter().enumerate().map(|(i, t)| f(i, t)).collect();
    }
    items
        .par_iter()
        .enumerate()
        .with_min_len(min_len(min_per_thread))
        .map(|(i, t)| f(i, t))
        .collect()
}

/// `items.iter_mut().enumerate().for_each(f)`, split like [`map`].
pub(crate) fn for_each_mut<T, F>(items: &mut [T], threads: usize, min_per_thread: usize, f: F)
where
    T: Send,
    F: Fn(usize, &mut T) + Sync,
{
    if !split(items.len(), threads, min_per_thread) {
        items.iter_mut().enumerate().for_each(|(i, t)| f(i, t));
        return;
    }
    items
        .par_iter_mut()
        .enumerate()
        .with_min_len(min_len(min_per_thread))
        .for_each(|(i, t)| f(i, t));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn map_keeps_item_order_and_indices_at_every_thread_count() {
        let items: Vec<u64> = (0..1003).map(|i| i * 7 + 1).collect();
        let expected: Vec<(usize, u64)> = items.iter().map(|&x| x * x).enumerate().collect();
        for threads in [1, 2, 3, 8] {
            for min in [1, 10, 600, 2000] {
                let got = install(threads, |t| map(&items, t, min, |i, &x| (i, x * x)));
                assert_eq!(got, expected, "threads {threads}, min {min}");
            }
        }
        assert!(map(&[] as &[u8], 4, 1, |_, &x| x).is_empty());
    }

    #[test]
    fn for_each_mut_visits_every_item_once_with_its_index() {
        for threads in [1, 2, 5] {
            let mut items = vec![0usize; 777];
            install(threads, |t| {
                for_each_mut(&mut items, t, 3, |i, x| *x += i + 1);
            });
            assert!(items.iter().enumerate().all(|(i, &x)| x == i + 1));
        }
    }

    #[test]
    fn work_is_split_only_when_each_thread_gets_its_minimum() {
        assert!(!split(100, 2, 64));
        assert!(split(128, 2, 64));
        assert!(!split(10_000, 1, 64));
        assert!(split(2, 2, 0));
        assert!(resolve_threads(0) >= 1);
        assert_eq!(resolve_threads(3), 3);
        // Inside a pool of 3 the work runs on its threads; with 1, on the caller's.
        assert_eq!(install(3, |t| (t, rayon::current_num_threads())), (3, 3));
        let caller = std::thread::current().id();
        assert_eq!(
            install(1, |t| (t, std::thread::current().id())),
            (1, caller)
        );
    }
}
