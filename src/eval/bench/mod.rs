//! The benchmarks behind `docs/bench` and the `photostereo bench` commands, one file per
//! experiment: what is measured (scenes, sizes, light sets, noise levels, data sets), the
//! measurement loops with their timing, and the rows of numbers they give. Writing the rows as
//! tables, charts and JSON is the caller's part (the command line does it), and so is running
//! other programs (the command line as a child process, the numpy peer): the experiments say
//! what to run and turn the measured times into their rows.
//!
//! - [`stages`]: a DiLiGenT-layout folder end to end, stage by stage, and as a whole process
//!   beside the numpy peer (`bench diligent`).
//! - [`integration`]: time and accuracy of each integrator against image size, and DCT Poisson
//!   on the peer's own test field (`bench integration`).
//! - [`interreflections`]: interreflection compensation on rendered concave scenes
//!   (`bench interreflections`).
//! - [`specularity`]: each estimator's error against specular strength (`bench specularity`).
//! - [`scaling`]: solve time against pixels × lights (`bench scaling`).
//! - [`stream`]: the same stack solved in memory and streamed in row bands (`bench stream`).
//! - [`diligent`]: every estimator on DiLiGenT objects, with all lights and with well-spread
//!   subsets of them.
//! - [`real_depth`]: every integrator on the shared depth data (DiLiGenT with its camera, the
//!   vase).
//! - [`suite`]: what `bench all` runs, with the full and the quick settings.
//!
//! The speed–accuracy sweeps on rendered scenes are [`crate::eval::sweep`].

pub mod diligent;
pub mod integration;
pub mod interreflections;
pub mod real_depth;
pub mod scaling;
pub mod specularity;
pub mod stages;
pub mod stream;
pub mod suite;

/// Runs `config` on `capture` and measures its normals against `truth` over the capture's mask:
/// the reconstruction, the angular errors and the wall time of the run in seconds.
pub(crate) fn timed_normal_errors(
    capture: &crate::capture::dataset::Capture,
    config: &crate::run::pipeline::Config,
    truth: &crate::grid::NormalMap,
) -> crate::error::Result<(
    crate::run::pipeline::Reconstruction,
    crate::eval::metrics::AngularErrorStats,
    f64,
)> {
    let t = std::time::Instant::now();
    let recon = crate::run::pipeline::reconstruct(capture, config, &crate::progress::Silent)?;
    let seconds = t.elapsed().as_secs_f64();
    let errors = crate::eval::metrics::angular_errors(&recon.maps.normals, truth, &capture.mask)?;
    Ok((recon, errors, seconds))
}

/// Timed runs per point of the benchmarks on rendered scenes; medians are reported.
pub const DEFAULT_REPEAT: usize = 3;

/// A power law y = exp(intercept)·x^slope, fitted by least squares on log y against log x: the
/// slope is how a cost grows with the size (1 = linear).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PowerLaw {
    /// The exponent: the slope of log y against log x.
    pub slope: f64,
    /// log y at x = 1.
    pub intercept: f64,
}

impl PowerLaw {
    /// The least-squares line through (ln x, ln y) of `points` (NaN slope for fewer than two
    /// distinct x).
    ///
    /// # Example
    /// ```
    /// use photostereo::eval::bench::PowerLaw;
    /// let fit = PowerLaw::fit(&[(1.0, 3.0), (2.0, 12.0), (4.0, 48.0)]);
    /// assert!((fit.slope - 2.0).abs() < 1e-12);
    /// assert!((fit.intercept.exp() - 3.0).abs() < 1e-12);
    /// ```
    pub fn fit(points: &[(f64, f64)]) -> PowerLaw {
        let (x, y): (Vec<f64>, Vec<f64>) = points.iter().map(|(x, y)| (x.ln(), y.ln())).unzip();
        Self::fit_logs(&x, &y)
    }

    /// The least-squares line of `ly` against `lx` (logarithms already taken).
    pub(crate) fn fit_logs(lx: &[f64], ly: &[f64]) -> PowerLaw {
        let n = lx.len() as f64;
        let (mx, my) = (lx.iter().sum::<f64>() / n, ly.iter().sum::<f64>() / n);
        let sxy: f64 = lx.iter().zip(ly).map(|(a, b)| (a - mx) * (b - my)).sum();
        let sxx: f64 = lx.iter().map(|a| (a - mx).powi(2)).sum();
        let slope = sxy / sxx;
        PowerLaw {
            slope,
            intercept: my - slope * mx,
        }
    }
}
