//! Measuring results: error metrics against ground truth ([`metrics`]), the built-in demo scene
//! and its evaluation ([`demo`]), and the experiments behind `docs/bench` — error and time over
//! noise, lights, specularity and integrators ([`sweep`]), and the benchmarks of the
//! `photostereo bench` commands ([`bench`](mod@bench): stage timings, scaling, integrators, real data).

pub mod bench;
pub mod demo;
pub mod from_object;
pub mod metrics;
pub mod near;
pub mod sfs;
pub mod sweep;

use crate::error::{Error, Result};
use std::time::Instant;

/// Runs `f` `runs` times; its last value and the median wall time ([`crate::stats::median`]).
pub(crate) fn timed<T>(runs: usize, mut f: impl FnMut() -> Result<T>) -> Result<(T, f64)> {
    let mut times = Vec::with_capacity(runs);
    let mut last = None;
    for _ in 0..runs {
        let t = Instant::now();
        last = Some(f()?);
        times.push(t.elapsed().as_secs_f64());
    }
    match last {
        Some(v) => Ok((v, crate::stats::median(times))),
        None => Err(Error::param("repeat", "no run")),
    }
}
