//! A DiLiGenT-layout folder end to end (`bench diligent`): the stages timed in-process — load,
//! solve, integrate, write — with the time to stream the loaded stack through memory once as
//! the yardstick for the solve ([`measure_stages`]); then the whole process timed beside the
//! numpy peer (`numpy_ps.py diligent DIR`, plain least squares), alternating runs so that
//! machine load hits both alike. Those runs are child processes, started by the caller;
//! [`ProcessComparison`] and [`Speedups`] turn their times into the report's numbers.

use crate::capture::dataset::Capture;
use crate::capture::stack::LoadOptions;
use crate::error::Result;
use crate::progress::Silent;
use crate::ps::solve::Method;
use crate::run::pipeline::{Config, reconstruct_and_write};
use crate::stats::median;
use rayon::prelude::*;
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

/// Runs of `bench diligent` by default; medians are reported.
pub const DEFAULT_REPEAT: usize = 5;

/// The numpy peer's estimator: its solve compares like with like only against this one.
pub const PEER_METHOD: Method = Method::LeastSquares;

/// Median in-process stage times of one folder, over the runs of [`measure_stages`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StageTimes {
    /// Load, solve, integration and writing together, seconds.
    pub in_process_total_s: f64,
    /// Reading the folder into a capture, seconds.
    pub load_s: f64,
    /// Solving normals and albedo, seconds.
    pub solve_s: f64,
    /// Integrating depth, seconds.
    pub integrate_s: f64,
    /// Writing every output, seconds.
    pub write_s: f64,
    /// One parallel pass summing every sample of the loaded stack: the memory-streaming
    /// yardstick, seconds.
    pub stream_stack_once_s: f64,
    /// Size of the loaded stack's samples, bytes.
    pub stack_bytes: usize,
    /// Solve time over the streaming yardstick: how many passes over memory the solve costs.
    pub solve_over_stream: f64,
}

/// Loads the DiLiGenT-layout folder `dir`, reconstructs it with `config` and writes every
/// output into `scratch` (overwritten each run), `repeat` times (at least once); the median
/// time of each stage.
///
/// # Errors
/// Any error of loading, reconstructing or writing.
pub fn measure_stages(
    dir: &Path,
    config: &Config,
    repeat: usize,
    scratch: &Path,
) -> Result<StageTimes> {
    let (mut total, mut load, mut solve, mut integrate, mut write, mut stream) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    let mut bytes = 0usize;
    for _ in 0..repeat.max(1) {
        let t = Instant::now();
        let capture = Capture::from_diligent(dir, &LoadOptions::default(), &Silent)?;
        let load_s = t.elapsed().as_secs_f64();
        let (recon, _) =
            reconstruct_and_write(&capture, config, scratch, load_s, &Silent, |_| Ok(None))?;
        total.push(t.elapsed().as_secs_f64());
        load.push(load_s);
        solve.push(recon.timings.solve);
        integrate.push(recon.timings.integrate);
        write.push(recon.timings.write);
        // Memory-streaming reference: one parallel pass summing every sample of the stack (the
        // sum is timed and thrown away, so rayon's order-dependent sum does no harm here).
        let data = capture.stack.data();
        bytes = std::mem::size_of_val(data);
        let t = Instant::now();
        let s: f64 = data
            .par_chunks(1 << 16)
            .map(|c| c.iter().map(|v| f64::from(*v)).sum::<f64>())
            .sum();
        stream.push(t.elapsed().as_secs_f64());
        std::hint::black_box(s);
    }
    let solve_s = median(solve);
    let stream_s = median(stream);
    Ok(StageTimes {
        in_process_total_s: median(total),
        load_s: median(load),
        solve_s,
        integrate_s: median(integrate),
        write_s: median(write),
        stream_stack_once_s: stream_s,
        stack_bytes: bytes,
        solve_over_stream: solve_s / stream_s,
    })
}

/// One run of the numpy peer on a folder: its wall time and the stage times it reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PeerRun {
    /// Wall time of the peer's process, seconds.
    pub wall_s: f64,
    /// The peer's own load time, seconds (NaN when it did not say).
    pub load_s: f64,
    /// The peer's own solve time, seconds (NaN when it did not say).
    pub solve_s: f64,
}

/// The peer's medians over its runs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PeerTimes {
    /// Wall time of the peer's process, seconds.
    pub process_wall_s: f64,
    /// The peer's load, seconds.
    pub load_s: f64,
    /// The peer's solve, seconds.
    pub solve_s: f64,
    /// Load and solve together, seconds.
    pub load_plus_solve_s: f64,
}

/// Whole-process times: ours and, when it ran, the peer's; medians over the runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProcessComparison {
    /// Wall time of our process (start-up, load, solve, integration, writing every output),
    /// seconds.
    pub ours_wall_s: f64,
    /// The peer's times.
    pub peer: Option<PeerTimes>,
}

impl ProcessComparison {
    /// The medians of our runs' wall times `ours_wall` and of the peer's runs `peer` (empty:
    /// the peer did not run).
    pub fn from_runs(ours_wall: Vec<f64>, peer: &[PeerRun]) -> Self {
        let peer = (!peer.is_empty()).then(|| {
            let (load_s, solve_s) = (
                median(peer.iter().map(|r| r.load_s).collect()),
                median(peer.iter().map(|r| r.solve_s).collect()),
            );
            PeerTimes {
                process_wall_s: median(peer.iter().map(|r| r.wall_s).collect()),
                load_s,
                solve_s,
                load_plus_solve_s: load_s + solve_s,
            }
        });
        ProcessComparison {
            ours_wall_s: median(ours_wall),
            peer,
        }
    }
}

/// The peer's time over ours: above 1, photostereo is faster.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Speedups {
    /// Load stage against load stage.
    pub load: f64,
    /// Solve stage against solve stage (like with like only for [`PEER_METHOD`]).
    pub solve: f64,
    /// Load and solve together.
    pub load_plus_solve: f64,
    /// The peer's whole process over ours.
    pub process_vs_process: f64,
    /// The peer's load and solve alone over our whole process (start-up, integration and
    /// writing included).
    pub vs_peer_load_plus_solve: f64,
}

impl Speedups {
    /// The ratios of `peer` to our stages `ours` and our process wall time `ours_wall_s`.
    pub fn new(ours: &StageTimes, ours_wall_s: f64, peer: &PeerTimes) -> Self {
        let (pl, ps) = (peer.load_s, peer.solve_s);
        let (ol, os) = (ours.load_s, ours.solve_s);
        Speedups {
            load: pl / ol,
            solve: ps / os,
            load_plus_solve: (pl + ps) / (ol + os),
            process_vs_process: peer.process_wall_s / ours_wall_s,
            vs_peer_load_plus_solve: (pl + ps) / ours_wall_s,
        }
    }
}
