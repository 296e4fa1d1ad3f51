//! Running a whole inference step on the rayon pool with its workers kept awake, so that the
//! step's many short parallel passes (three per U-Net convolution, the transfers, the dense
//! layers) split across the cores instead of each paying to wake a sleeping worker.
//!
//! Why: a rayon parallel call made from a thread outside the pool hands the work to the pool
//! and blocks the caller on a latch; a pool worker that found no work for a while sleeps on a
//! futex. On this project's 2-core machines one cold call costs ~150-200 us (measured: a
//! 30 us pass split in two took 160-210 us from outside the pool, 8-10 us from inside it with
//! the other worker awake), and the full-size grid model's step makes ~50 of them, so its
//! parallel passes ran no faster on 2 threads than on 1 (`bench node --skip-node`: the same
//! p50 with `RAYON_NUM_THREADS=1` and 2). OpenMP runtimes solve the same problem by letting
//! idle threads spin for a while before they sleep (`OMP_WAIT_POLICY=active`, KMP_BLOCKTIME);
//! rayon has no such setting, so [`hot`] spawns a task that keeps one more worker spinning,
//! and running pending jobs, for the length of the step (one: these machines have two cores;
//! on larger ones the other workers still sleep between passes).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How long the spinning task waits without finding a job before it gives up and lets its
/// worker sleep. Longer than the serial stretches between a step's parallel passes (~1 ms at
/// most, the P2G set-up), short enough that a spinner that cannot make progress (see
/// [`hot`]) costs little.
const IDLE_LIMIT: Duration = Duration::from_millis(2);

/// Runs `f` on a rayon pool worker while one more worker spins, ready to take the halves of
/// `f`'s parallel passes; returns `f`'s result.
///
/// From a thread outside the pool (the node's step loop, `bench node`) `f` is handed to the
/// pool once, instead of once per parallel pass. On a pool thread already (an `eval` that
/// steps scenes in parallel) `f` runs where it is, as before. With one worker no spinner is
/// started.
///
/// The spinner runs other pending jobs of the pool (`rayon::yield_now`) and stops when `f`
/// returns or after [`IDLE_LIMIT`] without a job. It is spawned detached, so `hot` returns
/// when `f` does, even if the spinner is still inside an unrelated job it picked up. It is
/// pushed onto the stepping worker's own queue before `f` starts, and other workers steal
/// the oldest job first, so no part of `f` can be stolen before the spinner is: the stepping
/// worker never runs its own spinner beneath `f`. The idle limit bounds the one case where a
/// spinner could still wait on a blocked step: two steps handed to the pool from two outside
/// threads at once, each worker blocked in its step beneath the other step's spinner.
///
/// The step now runs on whichever worker takes it, so per-thread scratch buffers (Winograd's
/// `V` and `M`, the im2col index cache) can exist once per worker, and the step runs under
/// the workers' flush-to-zero setting (`cli::flush_denormals`).
pub(crate) fn hot<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    if rayon::current_thread_index().is_some() {
        return f();
    }
    if rayon::current_num_threads() < 2 {
        return rayon::scope(|_| f());
    }
    rayon::scope(|_| {
        let done = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&done);
        rayon::spawn(move || spin(&flag));
        let _finished = SetOnDrop(done);
        f()
    })
}

/// Keeps the calling worker busy until `done` or [`IDLE_LIMIT`] without work.
fn spin(done: &AtomicBool) {
    let mut idle_since = Instant::now();
    while !done.load(Ordering::Acquire) {
        match rayon::yield_now() {
            Some(rayon::Yield::Executed) => idle_since = Instant::now(),
            _ if idle_since.elapsed() > IDLE_LIMIT => return,
            _ => std::hint::spin_loop(),
        }
    }
}

/// Sets its flag when dropped, so the spinner stops when `f` returns or panics.
struct SetOnDrop(Arc<AtomicBool>);

impl Drop for SetOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Release);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    #[test]
    fn returns_the_result_and_runs_parallel_passes_on_the_pool() {
        let from_outside = std::thread::spawn(|| {
            assert!(rayon::current_thread_index().is_none());
            hot(|| {
                assert!(
                    rayon::current_thread_index().is_some(),
                    "f runs on a worker"
                );
                (0..10_000u64).into_par_iter().map(|i| i * i).sum::<u64>()
            })
        });
        let sum = from_outside.join().unwrap();
        assert_eq!(sum, (0..10_000u64).map(|i| i * i).sum::<u64>());
    }

    #[test]
    fn nested_in_a_worker_runs_in_place() {
        let outer: Vec<usize> = (0..8usize)
            .into_par_iter()
            .map(|i| {
                let me = rayon::current_thread_index();
                hot(|| {
                    assert_eq!(rayon::current_thread_index(), me, "no hand-off");
                    i * 2
                })
            })
            .collect();
        assert_eq!(outer, (0..8).map(|i| i * 2).collect::<Vec<_>>());
    }

    #[test]
    fn steps_from_two_outside_threads_at_once_finish() {
        let threads: Vec<_> = (0..2)
            .map(|k| {
                std::thread::spawn(move || {
                    (0..50)
                        .map(|_| hot(|| (0..20_000u64).into_par_iter().map(|i| i ^ k).sum::<u64>()))
                        .count()
                })
            })
            .collect();
        for t in threads {
            assert_eq!(t.join().unwrap(), 50);
        }
    }
}
