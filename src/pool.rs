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

/// Indices per chunk of [`ordered_fold`].
const FOLD_CHUNK: usize = 4096;

/// Folds the indices `0..n` in parallel into one value that depends neither on the number of
/// threads nor on which thread stole which work: each fixed chunk of [`FOLD_CHUNK`] indices is
/// folded in order by `fold` from `identity()`, and the chunks' results are merged by `merge` in
/// chunk order, from `identity()`. Rayon's own `sum`, `reduce` and `fold` split the work by the
/// number of threads and where idle threads steal it, so a floating-point result taken with
/// them can change in its last bits with the threads and from one run to the next, and a solver
/// that compares such sums (a line search, a stopping test) can then take another path.
pub(crate) fn ordered_fold<A: Send>(
    n: usize,
    identity: impl Fn() -> A + Sync,
    fold: impl Fn(A, usize) -> A + Sync,
    merge: impl Fn(A, A) -> A,
) -> A {
    use rayon::prelude::*;
    let parts: Vec<A> = (0..n.div_ceil(FOLD_CHUNK))
        .into_par_iter()
        .map(|chunk| {
            let end = ((chunk + 1) * FOLD_CHUNK).min(n);
            (chunk * FOLD_CHUNK..end).fold(identity(), &fold)
        })
        .collect();
    parts.into_iter().fold(identity(), merge)
}

#[cfg(test)]
mod tests {
    use super::{in_pool, ordered_fold};
    use crate::synth::test_support::with_threads;
    use rayon::prelude::*;

    /// A floating-point sum whose value depends on the order of its terms (terms of widely
    /// different magnitudes) comes out bit for bit the same on one thread and on four, and as
    /// the sequential sum of the chunks' sequential sums.
    #[test]
    fn an_ordered_fold_does_not_depend_on_the_threads() {
        let n = 200_003;
        let term = |i: usize| ((i as f64) * 0.7).sin() * 10f64.powi((i % 17) as i32 - 8);
        let sum = || ordered_fold(n, || 0.0, |a, i| a + term(i), |a, b| a + b);
        let (one, four) = (with_threads(1, sum), with_threads(4, sum));
        assert_eq!(one.to_bits(), four.to_bits());
        let chunks: Vec<f64> = (0..n)
            .collect::<Vec<_>>()
            .chunks(super::FOLD_CHUNK)
            .map(|c| c.iter().fold(0.0, |a, &i| a + term(i)))
            .collect();
        assert_eq!(
            one.to_bits(),
            chunks.iter().fold(0.0, |a, b| a + b).to_bits()
        );
        // The terms are such that their order matters: the plain sequential sum differs.
        let sequential = (0..n).fold(0.0, |a, i| a + term(i));
        assert_ne!(one.to_bits(), sequential.to_bits());
    }

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
        let total = with_threads(1, || {
            in_pool(|| {
                assert_eq!(rayon::current_thread_index(), Some(0));
                (0..10_000u64).into_par_iter().sum::<u64>()
            })
        });
        assert_eq!(total, 10_000 * 9_999 / 2);
    }
}
