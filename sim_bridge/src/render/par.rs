//! Splitting a frame's work over a few threads (`std::thread::scope`; no
//! pool, a frame's stages are long enough for the spawn to be negligible).
//!
//! Every task computes the same numbers whichever thread runs it and in
//! whatever order, so the output does not depend on the thread count.

use std::sync::Mutex;

/// The number of threads a [`super::Renderer`] uses by default: the
/// machine's parallelism, at most 8.
pub(super) fn default_threads() -> usize {
    std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1)
        .clamp(1, 8)
}

/// `f` of every item, in order, the items split in contiguous chunks over
/// up to `threads` threads.
pub(super) fn map_chunks<T: Sync, R: Send>(
    items: &[T],
    threads: usize,
    f: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    let threads = threads.clamp(1, items.len().max(1));
    if threads == 1 {
        return items.iter().map(f).collect();
    }
    let chunk = items.len().div_ceil(threads);
    let f = &f;
    std::thread::scope(|s| {
        let handles: Vec<_> = items
            .chunks(chunk)
            .map(|c| s.spawn(move || c.iter().map(f).collect::<Vec<R>>()))
            .collect();
        let mut out = Vec::with_capacity(items.len());
        for h in handles {
            match h.join() {
                Ok(v) => out.extend(v),
                Err(e) => std::panic::resume_unwind(e),
            }
        }
        out
    })
}

/// Run `f` on every task, the tasks taken in order from a shared queue by
/// up to `threads` threads (tasks own disjoint parts of the output).
pub(super) fn run_tasks<T: Send>(tasks: Vec<T>, threads: usize, f: impl Fn(T) + Sync) {
    let threads = threads.clamp(1, tasks.len().max(1));
    if threads == 1 {
        tasks.into_iter().for_each(f);
        return;
    }
    let mut tasks = tasks;
    tasks.reverse();
    let queue = Mutex::new(tasks);
    let (f, queue) = (&f, &queue);
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(move || loop {
                // A poisoned queue means another task panicked: stop taking work.
                let next = match queue.lock() {
                    Ok(mut q) => q.pop(),
                    Err(_) => None,
                };
                match next {
                    Some(t) => f(t),
                    None => break,
                }
            });
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    #[test]
    fn map_chunks_keeps_the_order_and_run_tasks_runs_each_once() {
        let items: Vec<usize> = (0..103).collect();
        for threads in [1, 2, 3, 8, 200] {
            let out = map_chunks(&items, threads, |&i| i * i);
            assert_eq!(out, items.iter().map(|i| i * i).collect::<Vec<_>>());
            let mut slots = vec![0usize; 103];
            let count = AtomicUsize::new(0);
            let tasks: Vec<(usize, &mut usize)> = slots.iter_mut().enumerate().collect();
            run_tasks(tasks, threads, |(i, s)| {
                *s += i + 1;
                count.fetch_add(1, Ordering::Relaxed);
            });
            assert_eq!(count.load(Ordering::Relaxed), 103);
            assert!(slots.iter().enumerate().all(|(i, &s)| s == i + 1));
        }
        assert!(map_chunks(&[] as &[u8], 4, |&b| b).is_empty());
    }
}
