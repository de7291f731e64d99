//! Running the library's parallel loops from inside rayon's thread pool.
//!
//! A parallel loop started from a thread outside the pool (the caller's: a command's main
//! thread, a notebook's) is handed to the pool as a job, and the caller sleeps on a latch until
//! the pool has finished it: every loop costs two cross-thread hand-offs, a wake-up of a pool
//! thread and one of the caller, each a system call and a context switch. The iterative solvers
//! run thousands of short loops (a reweighting step of the bilateral integrator on a DiLiGenT
//! object runs about twenty for each of its 5–25 conjugate-gradient iterations, each over
//! 25–80 k pixels), and there the hand-offs took about as long as the work: two threads were
//! only 5–10% faster than one, and a quarter of the time was spent in the scheduler.
//!
//! Started from a pool thread, the same loop only pushes its second half onto that thread's own
//! queue, where an idle pool thread steals it if it is awake and the owner takes it back if not;
//! nobody sleeps on it. [`in_pool`] runs a whole computation on a pool thread, so that every
//! loop inside it starts there: the caller is handed off once. The computation's
//! [`crate::progress::Progress`] calls then come from that thread. The iterative solvers' sums
//! are taken over fixed chunks whatever thread runs them, so their results do not change (the
//! nine DiLiGenT depth maps of `docs/integration.md` are the same value for value).

/// Runs `work` on a thread of rayon's current pool (the global one, or the one installed by the
/// caller) and returns its result; the calling thread waits. Inside a pool thread already it
/// runs `work` in place.
pub(crate) fn in_pool<R: Send>(work: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| work())
}

#[cfg(test)]
mod tests {
    use super::in_pool;
    use rayon::prelude::*;

    /// The work runs on a pool thread, whether the caller is outside the pool or a pool
    /// thread itself, and a parallel loop inside it gives what it gives outside.
    #[test]
    fn work_runs_on_a_pool_thread() {
        assert_eq!(
            rayon::current_thread_index(),
            None,
            "the test thread is not in the pool"
        );
        let sum = |n: u64| (0..n).into_par_iter().map(|k| k * k).sum::<u64>();
        let (index, inside) = in_pool(|| (rayon::current_thread_index(), sum(100_000)));
        assert!(index.is_some(), "ran on the calling thread");
        assert_eq!(inside, sum(100_000));
        let nested = in_pool(|| in_pool(rayon::current_thread_index));
        assert!(nested.is_some());
    }

    /// A smoke test of a pool of one thread (`--threads 1` builds the global pool so): called
    /// on its only thread, the work and the loops inside it run there. (The global pool cannot
    /// be rebuilt in a test, so the call from outside such a pool is not exercised here.)
    #[test]
    fn a_pool_of_one_thread_runs_it() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .expect("a pool of one thread");
        let total = pool.install(|| {
            in_pool(|| {
                assert_eq!(rayon::current_thread_index(), Some(0));
                (0..10_000u64).into_par_iter().sum::<u64>()
            })
        });
        assert_eq!(total, 10_000 * 9_999 / 2);
    }
}
