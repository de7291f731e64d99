//! Solve time against the number of samples (`bench scaling`): per estimator, the solve of a
//! Lambertian sphere (radius 0.45 of the size, albedo 0.6, noise σ = 0.005, attached shadows)
//! at every size × light count ([`scaling_rows`]), and the slope of log time against
//! log(pixels × lights) fitted over them ([`slopes`]): 1 means cost linear in the samples.

use super::PowerLaw;
use crate::capture::lights::Lights;
use crate::capture::stack::ColorMode;
use crate::error::{Error, Result};
use crate::eval::timed;
use crate::progress::Silent;
use crate::ps::solve::{Method, SolveOptions, solve};
use crate::synth::render::{RenderOptions, render};
use crate::synth::scene::{Albedo, Scene};
use serde::Serialize;

/// Image sizes (square) by default.
pub const DEFAULT_SIZES: [usize; 4] = [128, 256, 512, 1024];
/// Light counts by default.
pub const DEFAULT_LIGHTS: [usize; 3] = [8, 24, 96];
/// Estimators by default: the linear ones and two robust ones.
pub const DEFAULT_METHODS: [Method; 5] = [
    Method::LeastSquares,
    Method::Threshold,
    Method::Auto,
    Method::Trimmed,
    Method::Huber,
];
/// The sphere's radius as a fraction of the image size.
pub const SPHERE_RADIUS: f64 = 0.45;
/// Gaussian image noise σ of the renderings.
pub const NOISE: f32 = 0.005;
/// Lowest light elevation of the Fibonacci light sets, degrees above the horizon.
pub const MIN_ELEVATION_DEG: f64 = 30.0;

/// What to time.
#[derive(Debug, Clone, PartialEq)]
pub struct ScalingOptions {
    /// Image sizes (square), each at least 16.
    pub sizes: Vec<usize>,
    /// Light counts, each at least 3.
    pub lights: Vec<usize>,
    /// Estimators, in the order of the rows.
    pub methods: Vec<Method>,
    /// Runs per point; medians are reported.
    pub repeat: usize,
}

impl Default for ScalingOptions {
    fn default() -> Self {
        ScalingOptions {
            sizes: DEFAULT_SIZES.to_vec(),
            lights: DEFAULT_LIGHTS.to_vec(),
            methods: DEFAULT_METHODS.to_vec(),
            repeat: super::DEFAULT_REPEAT,
        }
    }
}

impl ScalingOptions {
    /// Checks the sizes and light counts.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] naming the first bad one.
    pub fn validate(&self) -> Result<()> {
        if let Some(s) = self.sizes.iter().find(|s| **s < 16) {
            return Err(Error::param("sizes", format!("{s} is below 16")));
        }
        if let Some(l) = self.lights.iter().find(|l| **l < 3) {
            return Err(Error::param(
                "lights",
                format!("{l}: photometric stereo needs at least 3"),
            ));
        }
        Ok(())
    }
}

/// One estimator at one size and light count.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScalingRow {
    /// Estimator name.
    pub method: &'static str,
    /// Image size (square).
    pub size: usize,
    /// Pixels in the mask.
    pub pixels: usize,
    /// Number of lights.
    pub lights: usize,
    /// Samples solved: pixels × lights.
    pub samples: f64,
    /// Median solve time, seconds.
    pub solve_s: f64,
    /// Solve time per sample, nanoseconds.
    pub ns_per_sample: f64,
}

/// Every estimator of `options` at every size × light count: sizes outer, light counts, then
/// estimators inner.
///
/// # Errors
/// [`Error::InvalidParameter`] for bad options; any error of rendering or solving.
pub fn scaling_rows(options: &ScalingOptions) -> Result<Vec<ScalingRow>> {
    options.validate()?;
    let mut rows = Vec::new();
    for &size in &options.sizes {
        for &count in &options.lights {
            let lights = Lights::fibonacci(count, MIN_ELEVATION_DEG)?;
            let scene = Scene::sphere(size, SPHERE_RADIUS * size as f64, Albedo::Constant(0.6));
            let render_options = RenderOptions {
                noise_sigma: NOISE,
                seed: 1,
                ..RenderOptions::default()
            };
            let rendering = render(&scene, &lights, &render_options)?;
            let stack = rendering.to_stack(&lights, ColorMode::Grey)?;
            let mask = rendering.truth.mask.clone();
            let samples = (mask.count() * count) as f64;
            for &m in &options.methods {
                let o = SolveOptions::with_method(m);
                let (_, t) = timed(options.repeat.max(1), || {
                    Ok(std::hint::black_box(solve(
                        &stack, 0, &lights, &mask, &o, &Silent,
                    )?))
                })?;
                rows.push(ScalingRow {
                    method: m.name(),
                    size,
                    pixels: mask.count(),
                    lights: count,
                    samples,
                    solve_s: t,
                    ns_per_sample: 1e9 * t / samples,
                });
            }
        }
    }
    Ok(rows)
}

/// At one light count, the slope against pixels alone.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LightCountSlope {
    /// Number of lights.
    pub lights: usize,
    /// Slope of log time against log pixels.
    pub loglog_slope_vs_pixels: f64,
}

/// The cost of one estimator against the samples.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScalingSlope {
    /// Estimator name.
    pub method: &'static str,
    /// Slope of log time against log(pixels × lights) over every row (1 = linear).
    pub loglog_slope_vs_samples: f64,
    /// The same against pixels alone, at each light count.
    pub per_light_count: Vec<LightCountSlope>,
    /// The fitted power law of time against samples.
    #[serde(skip)]
    pub fit: PowerLaw,
    /// The measurements fitted: (samples, seconds).
    #[serde(skip)]
    pub points: Vec<(f64, f64)>,
}

/// Per estimator of `options`, the power laws fitted over `rows`.
pub fn slopes(rows: &[ScalingRow], options: &ScalingOptions) -> Vec<ScalingSlope> {
    options
        .methods
        .iter()
        .map(|m| {
            let name = m.name();
            let points: Vec<(f64, f64)> = rows
                .iter()
                .filter(|r| r.method == name)
                .map(|r| (r.samples, r.solve_s))
                .collect();
            let fit = PowerLaw::fit(&points);
            let per_light_count = options
                .lights
                .iter()
                .map(|&l| {
                    let pts: Vec<(f64, f64)> = rows
                        .iter()
                        .filter(|r| r.method == name && r.lights == l)
                        .map(|r| (r.pixels as f64, r.solve_s))
                        .collect();
                    LightCountSlope {
                        lights: l,
                        loglog_slope_vs_pixels: PowerLaw::fit(&pts).slope,
                    }
                })
                .collect();
            ScalingSlope {
                method: name,
                loglog_slope_vs_samples: fit.slope,
                per_light_count,
                fit,
                points,
            }
        })
        .collect()
}

/// The scaling benchmark: its rows and slopes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScalingReport {
    /// Worker threads of the solves.
    pub threads: usize,
    /// Runs per point.
    pub repeat: usize,
    /// Per estimator, the fitted slopes.
    pub slopes: Vec<ScalingSlope>,
    /// The measurements.
    pub rows: Vec<ScalingRow>,
}

/// [`scaling_rows`] and their [`slopes`].
///
/// # Errors
/// As [`scaling_rows`].
pub fn scaling(options: &ScalingOptions) -> Result<ScalingReport> {
    let rows = scaling_rows(options)?;
    Ok(ScalingReport {
        threads: rayon::current_num_threads(),
        repeat: options.repeat.max(1),
        slopes: slopes(&rows, options),
        rows,
    })
}
