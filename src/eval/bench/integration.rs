//! Time and accuracy of each integrator against image size (`bench integration`): the true
//! normals of a sphere (radius 0.45 N on an N×N image, disk mask) integrated at each size
//! ([`integrator_rows`]), with the log-log slope of time against pixels per integrator
//! ([`slopes`]); and DCT Poisson timed on the numpy peer's own test field, MATLAB's peaks on
//! the full N×N grid ([`peaks_gradients`], [`time_poisson_on_peaks`]), beside
//! `numpy_ps.py poisson N` run by the caller ([`PeerPoissonRow`]).

use super::PowerLaw;
use crate::error::Result;
use crate::eval::metrics::depth_errors;
use crate::eval::timed;
use crate::grid::{Grid, ScalarMap};
use crate::integrate::{
    IntegrationOptions, Integrator, LinearSolver, SolveInfo, integrate_gradients, integrate_normals,
};
use crate::progress::Silent;
use crate::stats::median;
use crate::synth::scene::{Albedo, Scene};
use serde::Serialize;
use std::time::Instant;

/// Image sizes (square) timed by default.
pub const DEFAULT_SIZES: [usize; 4] = [256, 512, 1024, 2048];
/// Sizes above this are timed once, whatever the repeat count.
pub const MAX_REPEATED_SIZE: usize = 512;
/// The sphere's radius as a fraction of the image size.
pub const SPHERE_RADIUS: f64 = 0.45;

/// What to time.
#[derive(Debug, Clone, PartialEq)]
pub struct IntegrationBenchOptions {
    /// Image sizes (square).
    pub sizes: Vec<usize>,
    /// Integrators, in the order of the rows.
    pub methods: Vec<Integrator>,
    /// Runs at sizes up to [`MAX_REPEATED_SIZE`] (one above); medians are reported.
    pub repeat: usize,
}

impl Default for IntegrationBenchOptions {
    fn default() -> Self {
        IntegrationBenchOptions {
            sizes: DEFAULT_SIZES.to_vec(),
            methods: Integrator::ALL.to_vec(),
            repeat: super::DEFAULT_REPEAT,
        }
    }
}

/// One integrator at one size.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct IntegratorRow {
    /// Integrator name.
    pub method: &'static str,
    /// Image size (square).
    pub size: usize,
    /// Pixels in the mask.
    pub pixels: usize,
    /// Median wall time, seconds.
    pub time_s: f64,
    /// Depth RMSE after the mean offset, over the true depth range.
    pub rmse_over_range: f64,
    /// How the linear system was solved (masked methods).
    pub solve: Option<SolveInfo>,
}

/// Each of `options.methods` on the sphere at each of `options.sizes`: sizes outer, methods
/// inner.
///
/// # Errors
/// Any error of integration.
pub fn integrator_rows(options: &IntegrationBenchOptions) -> Result<Vec<IntegratorRow>> {
    let mut rows = Vec::new();
    for &n in &options.sizes {
        let hf = Scene::sphere(n, SPHERE_RADIUS * n as f64, Albedo::Constant(0.5)).height_field();
        let runs = if n <= MAX_REPEATED_SIZE {
            options.repeat.max(1)
        } else {
            1
        };
        for &m in &options.methods {
            let o = IntegrationOptions {
                method: m,
                ..IntegrationOptions::default()
            };
            let (r, time_s) = timed(runs, || {
                integrate_normals(&hf.normals, &hf.mask, &o, &Silent)
            })?;
            let e = depth_errors(&r.depth, &hf.depth, &hf.mask)?;
            rows.push(IntegratorRow {
                method: m.name(),
                size: n,
                pixels: hf.mask.count(),
                time_s,
                rmse_over_range: e.rmse_over_range,
                solve: r.solve,
            });
        }
    }
    Ok(rows)
}

/// The cost of one integrator against the pixels in the mask.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct IntegratorSlope {
    /// Integrator name.
    pub method: &'static str,
    /// Slope of log time against log pixels (1 = linear).
    pub loglog_slope_vs_pixels: f64,
    /// The fitted power law (its slope is the one above).
    #[serde(skip)]
    pub fit: PowerLaw,
    /// The measurements fitted: (pixels, seconds).
    #[serde(skip)]
    pub points: Vec<(f64, f64)>,
}

/// Per integrator of `methods`, the power law of time against pixels fitted over `rows`.
pub fn slopes(rows: &[IntegratorRow], methods: &[Integrator]) -> Vec<IntegratorSlope> {
    methods
        .iter()
        .map(|m| {
            let points: Vec<(f64, f64)> = rows
                .iter()
                .filter(|r| r.method == m.name())
                .map(|r| (r.pixels as f64, r.time_s))
                .collect();
            let fit = PowerLaw::fit(&points);
            IntegratorSlope {
                method: m.name(),
                loglog_slope_vs_pixels: fit.slope,
                fit,
                points,
            }
        })
        .collect()
}

/// The peer's test field: forward differences of MATLAB's peaks on [−3, 3]² sampled on an n×n
/// grid, converted to this crate's gradient convention (x right, y up): (p, q).
pub fn peaks_gradients(n: usize) -> (ScalarMap, ScalarMap) {
    let f = |x: f64, y: f64| {
        3.0 * (1.0 - x).powi(2) * (-x * x - (y + 1.0).powi(2)).exp()
            - 10.0 * (x / 5.0 - x.powi(3) - y.powi(5)) * (-x * x - y * y).exp()
            - (-(x + 1.0).powi(2) - y * y).exp() / 3.0
    };
    let z = |c: usize, r: usize| {
        f(
            c as f64 / n as f64 * 6.0 - 3.0,
            r as f64 / n as f64 * 6.0 - 3.0,
        )
    };
    let p = Grid::from_fn(n, n, |c, r| {
        if c + 1 < n {
            (z(c + 1, r) - z(c, r)) as f32
        } else {
            0.0
        }
    });
    // The peer's rows run downwards; our q is ∂z/∂y with y up.
    let q = Grid::from_fn(n, n, |c, r| {
        if r + 1 < n {
            -(z(c, r + 1) - z(c, r)) as f32
        } else {
            0.0
        }
    });
    (p, q)
}

/// Median wall time of DCT Poisson on [`peaks_gradients`]`(n)` over the full grid, `repeat`
/// runs (at least one).
///
/// # Errors
/// Any error of integration.
pub fn time_poisson_on_peaks(n: usize, repeat: usize) -> Result<f64> {
    let (p, q) = peaks_gradients(n);
    let mask = Grid::new(n, n, true);
    let mut times = Vec::new();
    for _ in 0..repeat.max(1) {
        let t = Instant::now();
        integrate_gradients(&p, &q, &mask, Integrator::Poisson, LinearSolver::Auto)?;
        times.push(t.elapsed().as_secs_f64());
    }
    Ok(median(times))
}

/// DCT Poisson on the peaks field, ours beside the peer's.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PeerPoissonRow {
    /// Image size (square).
    pub size: usize,
    /// Our median time ([`time_poisson_on_peaks`]), seconds.
    pub photostereo_poisson_s: f64,
    /// The peer's median solve time as it reports it, seconds.
    pub numpy_dct_poisson_s: f64,
    /// The peer's time over ours.
    pub speedup: f64,
}

impl PeerPoissonRow {
    /// The row of size `size` from our median time `ours` and the peer's reported solve times
    /// `theirs` (their median is taken).
    pub fn new(size: usize, ours: f64, theirs: Vec<f64>) -> Self {
        let t = median(theirs);
        PeerPoissonRow {
            size,
            photostereo_poisson_s: ours,
            numpy_dct_poisson_s: t,
            speedup: t / ours,
        }
    }
}
