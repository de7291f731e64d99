//! Near-light photometric stereo: LEDs a few object sizes away, whose direction and irradiance
//! change across the object.
//!
//! **Model** (Quéau, Durix, Wu, Cremers, Lauze and Durou, "LED-based photometric stereo:
//! modeling, calibration and numerical solution", JMIV 2018). Light k at position P_k with
//! intensity Φ_k and angular profile cos^μ θ about its principal direction D_k
//! ([`crate::capture::lights::Anisotropy`]) lights the surface point X with
//!
//! ```text
//! I_k(X) = ρ · a_k(X) · max(0, n · l_k(X)),   l_k = (P_k − X)/|P_k − X|,
//! a_k(X) = Φ_k · (D_k · (X − P_k)/|X − P_k|)^μ_k / |P_k − X|²,
//! ```
//!
//! where X = d · K⁻¹(u, v, 1) is the point a pinhole camera of intrinsics K sees at pixel (u, v)
//! and depth d. Unlike distant lights, the lights at a pixel depend on its depth: normals and
//! depth must be estimated together.
//!
//! **Solver** (the alternating scheme of Quéau et al. 2018, §5, with this crate's pieces):
//! 1. start from a fronto-parallel plane at depth d₀: given, or the plane whose per-pixel fits
//!    explain evenly spaced pixels best, searched within a factor 16 of the lights' mean
//!    distance from the camera;
//! 2. at the current depth, each pixel's light directions l_k and fall-offs a_k are computed and
//!    g = ρn fitted from I_k/a_k with the per-pixel estimator of [`crate::ps::solve`]
//!    (shadow threshold, `auto`'s fit test and robust refit, with the pixel's own half vectors
//!    for the specular estimator);
//! 3. the normals are integrated under the pinhole camera (log depth, [`crate::integrate`]),
//!    which gives each connected part's shape up to a scale;
//! 4. each part's scale s is the one whose lights best explain the images: with the normals
//!    fixed (scaling a surface about the camera centre keeps its normals), the relative
//!    residual Σ w (I − ρ a(sX) n·l(sX))² / Σ w I² with ρ fitted in closed form, over the
//!    samples the fits kept (weights w), minimised over ln s on a grid and then by golden
//!    section;
//! 5. repeat from 2 until the depth moves by less than [`NearOptions::tolerance`] of its range.
//!
//! Until the depth change falls below ten tolerances, step 2 uses threshold least squares and
//! step 3 masked least squares; the alternations after it, and always the last one allowed,
//! use the method and integrator asked for, and only those count for convergence.
//!
//! The absolute scale is in the data because the fall-off and the directions depend on the
//! distance to the lights; it is what a distant-light solve cannot give.
//!
//! **Failure modes.** Lights far away (≳ 20 object sizes) make the scale poorly determined (the
//! residual is flat in s; the distant model is then as good); a wrong camera K or wrong light
//! positions bias the normals by the angle they misplace the lights; the scale of a part with
//! few pixels is fitted from few samples. The refit with specular lobes
//! ([`crate::ps::lobes`]) and the cast-shadow labelling ([`crate::ps::shadows`]) assume
//! distant lights and are not run.

use crate::camera::Intrinsics;
use crate::capture::lights::{Light, Lights};
use crate::capture::stack::ImageStack;
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, ScalarMap};
use crate::integrate::sparse::Unknowns;
use crate::integrate::{Integration, IntegrationOptions, Integrator, integrate_normals};
use crate::progress::Progress;
use crate::ps::fill::{PixelData, fill};
use crate::ps::solve::{
    PixelSolution, Solution, SolveOptions, check_inputs, fit_with, fitter, test_sigmas,
};
use crate::synth::near::near_light_at;
use nalgebra::Vector3;
use rayon::prelude::*;
use serde::Serialize;

/// Default largest number of alternations.
pub const DEFAULT_MAX_ITERATIONS: usize = 30;
/// Default convergence threshold: the RMS depth change of an alternation as a fraction of the
/// depth's range (1st to 99th percentile).
pub const DEFAULT_TOLERANCE: f64 = 1e-3;
/// The alternations fit pixels by threshold least squares until the depth changes by less than
/// this many tolerances.
const ROUGH_UNTIL: f64 = 10.0;
/// About this many evenly spaced pixels of the whole mask are fitted alone by the start search;
/// four times as many keep their samples for the scale fit (each part's share of them).
const SCALE_SAMPLE: usize = 4000;
/// Grid points of ln s for the scale fit, and the half-width of the grid in ln s on the first
/// alternation (from the start plane) and later.
const FIRST_GRID: usize = 61;
const LATER_GRID: usize = 9;
const FIRST_SPAN: f64 = 2.77; // ln 16
const LATER_SPAN: f64 = 0.22; // ln 1.25

/// Options of [`solve_near`].
#[derive(Debug, Clone, PartialEq)]
pub struct NearOptions {
    /// The per-pixel fit. Specular lobes and shadow labels are not used (see the module
    /// documentation).
    pub solve: SolveOptions,
    /// How the normals are integrated; the camera is the solve's.
    pub integration: IntegrationOptions,
    /// Depth of the start plane along the optical axis (camera units); `None`: searched from the
    /// images within a factor 16 of the lights' mean distance from the camera.
    pub start_distance: Option<f64>,
    /// Largest number of alternations.
    pub max_iterations: usize,
    /// Convergence threshold (see [`DEFAULT_TOLERANCE`]).
    pub tolerance: f64,
}

impl Default for NearOptions {
    fn default() -> Self {
        NearOptions {
            solve: SolveOptions::default(),
            integration: IntegrationOptions::default(),
            start_distance: None,
            max_iterations: DEFAULT_MAX_ITERATIONS,
            tolerance: DEFAULT_TOLERANCE,
        }
    }
}

/// One alternation of [`solve_near`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NearStep {
    /// RMS depth change over the part pixels, as a fraction of the depth range.
    pub depth_change: f64,
    /// Relative residual of the scale fit at its optimum (pixel-averaged).
    pub residual: f64,
    /// Geometric-mean depth of the largest part after the step (camera units).
    pub distance: f64,
}

/// Result of [`solve_near`].
#[derive(Debug, Clone)]
pub struct NearSolve {
    /// Per-pixel g = ρn and diagnostics, fitted at the final depth.
    pub solution: Solution,
    /// Depth along the optical axis, in the units of the light positions; NaN outside.
    pub depth: ScalarMap,
    /// The last integration (its depth is the relative shape before the scale fit).
    pub integration: Integration,
    /// The alternations, in order.
    pub steps: Vec<NearStep>,
    /// Whether the depth change fell below the tolerance before the iteration cap.
    pub converged: bool,
    /// Depth of the start plane.
    pub start_distance: f64,
}

/// What the alternation needs at every step.
struct Context<'a> {
    stack: &'a ImageStack,
    channel: usize,
    lights: &'a [Light],
    mask: &'a Mask,
    camera: &'a Intrinsics,
    sigma: Vec<f32>,
    options: &'a SolveOptions,
}

/// A pixel's samples kept for the scale fit.
struct ScaleSample {
    /// Row-major index of the pixel.
    pixel: usize,
    /// The pixel's ray K⁻¹(u, v, 1) (depth 1).
    ray: Vector3<f64>,
    normal: Vector3<f64>,
    values: Vec<f32>,
    weights: Vec<f32>,
    part: u32,
    /// The integrated depth at the pixel, relative to its part's scale.
    relative: f64,
}

/// Estimates normals, albedo and absolute depth under near lights (see the module
/// documentation): every light needs a position, and the camera's intrinsics are required.
///
/// # Errors
/// [`Error::InvalidLight`] naming a light without a position; [`Error::InvalidParameter`] for
/// invalid options (a non-positive start distance, a zero iteration cap, a tolerance outside
/// (0, 1)) and the errors of [`crate::ps::solve::solve`] and
/// [`crate::integrate::integrate_normals`].
pub fn solve_near(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    camera: &Intrinsics,
    options: &NearOptions,
    progress: &dyn Progress,
) -> Result<NearSolve> {
    check_inputs(stack, channel, lights, mask, &options.solve)?;
    if let Some(index) = lights.lights().iter().position(|l| l.position.is_none()) {
        return Err(Error::InvalidLight {
            index,
            reason: "near-light photometric stereo needs every light's position".into(),
        });
    }
    if options.max_iterations == 0 {
        return Err(Error::param("max_iterations", "must be at least 1"));
    }
    if !(options.tolerance > 0.0 && options.tolerance < 1.0) {
        return Err(Error::param(
            "tolerance",
            format!("{} must be in (0, 1)", options.tolerance),
        ));
    }
    if ![camera.fx, camera.fy, camera.cx, camera.cy]
        .iter()
        .all(|v| v.is_finite())
        || camera.fx <= 0.0
        || camera.fy <= 0.0
    {
        return Err(Error::param(
            "camera",
            format!(
                "intrinsics fx {} fy {} cx {} cy {}: the focal lengths must be finite and > 0",
                camera.fx, camera.fy, camera.cx, camera.cy
            ),
        ));
    }
    let centre = match options.start_distance {
        Some(d) => d,
        None => {
            lights
                .lights()
                .iter()
                .filter_map(|l| l.position.map(|p| p.norm()))
                .sum::<f64>()
                / lights.len() as f64
        }
    };
    if !(centre.is_finite() && centre > 0.0) {
        return Err(Error::param(
            "start_distance",
            format!("{centre} must be finite and > 0"),
        ));
    }
    let solve = SolveOptions {
        lobes: false,
        shadow_labels: None,
        recalibrate: Some(false),
        ..options.solve
    };
    let ctx = Context {
        stack,
        channel,
        lights: lights.lights(),
        mask,
        camera,
        sigma: if solve.method == crate::ps::Method::Auto {
            test_sigmas(stack, channel, mask, &solve)
        } else {
            vec![f32::NAN; stack.count()]
        },
        options: &solve,
    };
    let integration_options = IntegrationOptions {
        camera: Some(*camera),
        ..options.integration
    };
    let (w, h) = (mask.width(), mask.height());
    // A distance the caller gives is the start plane; otherwise it is searched from the images
    // around the lights' mean distance.
    let start = match options.start_distance {
        Some(d) => d,
        None => search_start(&ctx, centre).unwrap_or(centre),
    };
    // While the depth is far from converged, the pixels are fitted by threshold least squares
    // (the robust refit of `auto` would chase the misfit that wrong lights cause) and
    // integrated by masked least squares; the last alternations (and always the last one
    // allowed) use the method and the integrator asked for.
    let rough = SolveOptions {
        method: crate::ps::Method::Threshold,
        ..solve
    };
    let mut precise = false;
    let mut depth = Grid::from_fn(w, h, |c, r| {
        if *mask.at(c, r) {
            start as f32
        } else {
            f32::NAN
        }
    });
    let mut steps = Vec::new();
    let mut converged = false;
    let mut first = true;
    let mut last_integration: Option<Integration> = None;
    progress.begin("near-light alternation", options.max_iterations as u64);
    loop {
        let capped = steps.len() >= options.max_iterations;
        precise |= steps.len() + 1 >= options.max_iterations;
        let fit_options = if precise || capped { &solve } else { &rough };
        let (solution, samples) = solve_at(&ctx, fit_options, &depth);
        if (converged || capped)
            && let Some(integration) = last_integration
        {
            progress.end();
            // Pixels the last integration did not reach have no depth (the alternation carried
            // their previous one along).
            for (d, z) in depth.data_mut().iter_mut().zip(integration.depth.data()) {
                if !z.is_finite() {
                    *d = f32::NAN;
                }
            }
            // Each light's position checked against the other images.
            let mut solution = solution;
            solution.light_agreement = Some(crate::ps::light_agreement::measure_near(
                stack, channel, ctx.lights, mask, &solution, &depth, camera,
            ));
            return Ok(NearSolve {
                solution,
                depth,
                integration,
                steps,
                converged,
                start_distance: start,
            });
        }
        // The rough alternations integrate by masked least squares where the method asked for
        // is the slower discontinuity-preserving one (or `auto`, which may choose it).
        let integrator = match integration_options.method {
            Integrator::Auto | Integrator::Bilateral if !precise => IntegrationOptions {
                method: Integrator::MaskedLs,
                ..integration_options
            },
            _ => integration_options,
        };
        if !solution.status.data().iter().any(|s| s.has_normal()) {
            return Err(Error::param(
                "mask",
                "near-light photometric stereo solved no pixel of the mask, so there is no depth to alternate with",
            ));
        }
        let integration = integrate(&solution, mask, &integrator)?;
        let (parts, count) = label_parts(&integration.depth);
        let samples = attach_parts(samples, &parts, &integration.depth);
        let (span, grid) = if first {
            (FIRST_SPAN, FIRST_GRID)
        } else {
            (LATER_SPAN, LATER_GRID)
        };
        first = false;
        let mut next = Grid::new(w, h, f32::NAN);
        let mut residual_sum = 0.0;
        let mut residual_n = 0usize;
        let mut biggest = (0usize, f64::NAN);
        let mut members: Vec<Vec<usize>> = vec![Vec::new(); count];
        for (p, &part) in parts.iter().enumerate() {
            if part != u32::MAX {
                members[part as usize].push(p);
            }
        }
        let mut by_part: Vec<Vec<&ScaleSample>> = vec![Vec::new(); count];
        for s in &samples {
            by_part[s.part as usize].push(s);
        }
        for (pixels, own) in members.into_iter().zip(by_part) {
            // The previous depth's geometric mean over the part: where the scale search centres.
            let logs: Vec<f64> = pixels
                .iter()
                .map(|&p| f64::from(depth.data()[p]).ln())
                .filter(|v| v.is_finite())
                .collect();
            let centre = (logs.iter().sum::<f64>() / logs.len() as f64).exp();
            let centre = if centre.is_finite() { centre } else { start };
            let (scale, residual) = match fit_scale(&own, ctx.lights, centre, span, grid) {
                Some((s, e)) => (s, e),
                None => (centre, f64::NAN),
            };
            if residual.is_finite() {
                residual_sum += residual * own.len() as f64;
                residual_n += own.len();
            }
            if pixels.len() > biggest.0 {
                biggest = (pixels.len(), scale);
            }
            for p in pixels {
                next.data_mut()[p] = (scale * f64::from(integration.depth.data()[p])) as f32;
            }
        }
        // Pixels the integration did not reach keep their depth.
        for p in 0..w * h {
            if mask.data()[p] && !next.data()[p].is_finite() {
                next.data_mut()[p] = depth.data()[p];
            }
        }
        let change = depth_change(&depth, &next, mask);
        steps.push(NearStep {
            depth_change: change,
            residual: if residual_n > 0 {
                residual_sum / residual_n as f64
            } else {
                f64::NAN
            },
            distance: biggest.1,
        });
        progress.advance(1);
        depth = next;
        last_integration = Some(integration);
        if change < options.tolerance && precise {
            converged = true;
        }
        if change < ROUGH_UNTIL * options.tolerance {
            precise = true;
        }
    }
}

/// Integrates the unit normals of `solution` under the pinhole camera of `options`.
fn integrate(
    solution: &Solution,
    mask: &Mask,
    options: &IntegrationOptions,
) -> Result<Integration> {
    let (_, normals) = crate::ps::normals::albedo_and_normals(solution);
    integrate_normals(&normals, mask, options, &crate::progress::Silent)
}

/// Fits every masked pixel at depth `depth`: the solution, and the samples of evenly spaced
/// pixels for the scale fit.
fn solve_at(
    ctx: &Context,
    options: &SolveOptions,
    depth: &ScalarMap,
) -> (Solution, Vec<ScaleSample>) {
    let (w, h) = (ctx.mask.width(), ctx.mask.height());
    let k = ctx.stack.count();
    let masked = ctx.mask.count().max(1);
    let every = masked.div_ceil(SCALE_SAMPLE * 4).max(1);
    // Rank of each masked pixel in row-major order, so that sampling is by rank.
    let row_start: Vec<usize> = {
        let mut acc = 0;
        (0..h)
            .map(|r| {
                let s = acc;
                acc += (0..w).filter(|&c| *ctx.mask.at(c, r)).count();
                s
            })
            .collect()
    };
    type Row = (
        Vec<(usize, PixelSolution)>,
        Vec<PixelData>,
        Vec<ScaleSample>,
    );
    let rows: Vec<Row> = (0..h)
        .into_par_iter()
        .map(|r| {
            let mut out = Vec::new();
            let mut unsolved = Vec::new();
            let mut kept = Vec::new();
            let mut work = PixelWork::new(k);
            let mut rank = row_start[r];
            for c in 0..w {
                let p = r * w + c;
                if !ctx.mask.data()[p] {
                    continue;
                }
                let keep = rank.is_multiple_of(every);
                rank += 1;
                let ray = Vector3::from(ctx.camera.unproject(c as f64, r as f64, 1.0));
                let x = ray * f64::from(depth.data()[p]);
                work.load(ctx, p, &x);
                let mut f = fitter(&work.dirs, &work.gains, options);
                f.set_view(&(-x.normalize()));
                let px = fit_with(&mut f, &work.values, &work.saturated, &ctx.sigma, options);
                if px.status.has_normal() {
                    if keep {
                        kept.push(ScaleSample {
                            pixel: p,
                            ray,
                            normal: px.g.normalize(),
                            values: work.values.clone(),
                            weights: f.weights().iter().map(|&v| v as f32).collect(),
                            part: u32::MAX,
                            relative: f64::NAN,
                        });
                    }
                } else if options.fill {
                    let reject = options.method != crate::ps::Method::LeastSquares;
                    let (a, b, samples) =
                        f.usable_normal_equations(&work.values, &work.saturated, reject);
                    unsolved.push(PixelData {
                        pixel: p,
                        a,
                        b,
                        samples,
                    });
                }
                out.push((p, px));
            }
            (out, unsolved, kept)
        })
        .collect();
    let mut sol = Solution::empty(
        w,
        h,
        crate::ps::intensities::GainEstimate::unit(k),
        ctx.sigma.clone(),
        options,
    );
    let mut unsolved = Vec::new();
    let mut samples = Vec::new();
    for (out, u, s) in rows {
        for (p, px) in out {
            sol.record(p, &px);
        }
        unsolved.extend(u);
        samples.extend(s);
    }
    if options.fill {
        fill(&mut sol, &unsolved);
    }
    (sol, samples)
}

/// One pixel's samples and lights at a point X: directions l_k, gains 1/a_k (NaN where a light
/// gives the point nothing), values and saturation flags.
struct PixelWork {
    dirs: Vec<Vector3<f64>>,
    gains: Vec<f32>,
    values: Vec<f32>,
    saturated: Vec<bool>,
}

impl PixelWork {
    fn new(k: usize) -> Self {
        PixelWork {
            dirs: vec![Vector3::z(); k],
            gains: vec![0.0; k],
            values: vec![0.0; k],
            saturated: vec![false; k],
        }
    }

    /// Loads pixel `p`'s samples and its lights at the camera-frame point `x`.
    fn load(&mut self, ctx: &Context, p: usize, x: &Vector3<f64>) {
        for (j, light) in ctx.lights.iter().enumerate() {
            match near_light_at(light, x) {
                Some((fall, l)) if fall > 0.0 => {
                    self.dirs[j] = l;
                    self.gains[j] = (1.0 / fall) as f32;
                }
                _ => {
                    self.dirs[j] = Vector3::z();
                    self.gains[j] = f32::NAN;
                }
            }
            self.values[j] = ctx.stack.value(j, ctx.channel, p);
            self.saturated[j] = ctx.stack.is_saturated(j, p);
        }
    }
}

/// The depth of a fronto-parallel plane that best explains evenly spaced pixels when each is
/// fitted alone (threshold least squares, relative residual Σ w (I/a − g·l)² / Σ w (I/a)²),
/// searched over ln d within a factor 16 of `start`: a start for the alternation from the
/// images themselves, since a pixel's residual grows as its lights are misplaced. `None` when
/// no pixel can be fitted.
fn search_start(ctx: &Context, start: f64) -> Option<f64> {
    let (w, h) = (ctx.mask.width(), ctx.mask.height());
    let masked: Vec<usize> = (0..w * h).filter(|&p| ctx.mask.data()[p]).collect();
    let every = masked.len().div_ceil(SCALE_SAMPLE).max(1);
    let pixels: Vec<(usize, Vector3<f64>)> = masked
        .iter()
        .step_by(every)
        .map(|&p| {
            let ray = ctx.camera.unproject((p % w) as f64, (p / w) as f64, 1.0);
            (p, Vector3::from(ray))
        })
        .collect();
    let options = SolveOptions {
        method: crate::ps::Method::Threshold,
        ..*ctx.options
    };
    let k = ctx.stack.count();
    let at = |t: f64| -> f64 {
        let d = t.exp();
        let sums: Vec<(f64, usize)> = pixels
            .par_chunks(64)
            .map(|chunk| {
                let mut work = PixelWork::new(k);
                let (mut total, mut n) = (0.0, 0usize);
                for (p, ray) in chunk {
                    let x = ray * d;
                    work.load(ctx, *p, &x);
                    let mut f = fitter(&work.dirs, &work.gains, &options);
                    let px = fit_with(&mut f, &work.values, &work.saturated, &ctx.sigma, &options);
                    if !px.status.has_normal() {
                        continue;
                    }
                    let (mut rr, mut vv) = (0.0, 0.0);
                    for (j, wt) in f.weights().iter().enumerate() {
                        if *wt > 0.0 {
                            let v = f64::from(work.values[j]) * f64::from(work.gains[j]);
                            rr += wt * (v - px.g.dot(&work.dirs[j])).powi(2);
                            vv += wt * v * v;
                        }
                    }
                    if vv > 0.0 {
                        total += rr / vv;
                        n += 1;
                    }
                }
                (total, n)
            })
            .collect();
        let (t, n) = sums.iter().fold((0.0, 0), |(a, b), (c, d)| (a + c, b + d));
        if n == 0 { f64::NAN } else { t / n as f64 }
    };
    minimise_ln(at, start.ln(), FIRST_SPAN, FIRST_GRID).map(|(t, _)| t.exp())
}

/// Labels the 4-connected parts of the finite pixels of `depth` (u32::MAX elsewhere), in the
/// order of their first pixel ([`Unknowns`]' own labelling).
fn label_parts(depth: &ScalarMap) -> (Vec<u32>, usize) {
    let u = Unknowns::new(&depth.map(|v| v.is_finite()));
    let mut label = vec![u32::MAX; depth.len()];
    for (&pixel, &part) in u.pixel.iter().zip(&u.part) {
        label[pixel as usize] = part;
    }
    (label, u.parts)
}

/// Gives each kept sample the part of its pixel and its relative depth there (samples the
/// integration did not reach are dropped).
fn attach_parts(
    samples: Vec<ScaleSample>,
    parts: &[u32],
    relative: &ScalarMap,
) -> Vec<ScaleSample> {
    samples
        .into_iter()
        .filter_map(|mut s| {
            s.part = parts[s.pixel];
            s.relative = f64::from(relative.data()[s.pixel]);
            (s.part != u32::MAX && s.relative.is_finite() && s.relative > 0.0).then_some(s)
        })
        .collect()
}

/// The relative residual of samples `own` with every point at `scale` times its ray.
fn scale_residual(own: &[&ScaleSample], lights: &[Light], scale: f64) -> f64 {
    // Summed over fixed chunks in order, so that the result does not depend on the threads.
    let chunks: Vec<(f64, usize)> = own
        .par_chunks(256)
        .map(|chunk| chunk_residual(chunk, lights, scale))
        .collect();
    let (total, n) = chunks
        .iter()
        .fold((0.0, 0), |(t, n), (a, b)| (t + a, n + b));
    if n == 0 { f64::NAN } else { total / n as f64 }
}

/// The sum of the relative residuals of `own` at `scale`, and how many pixels it has.
fn chunk_residual(own: &[&ScaleSample], lights: &[Light], scale: f64) -> (f64, usize) {
    let mut total = 0.0;
    let mut n = 0usize;
    for s in own {
        let x = s.ray * (scale * s.relative);
        let (mut vv, mut vm, mut mm) = (0.0, 0.0, 0.0);
        for (j, light) in lights.iter().enumerate() {
            let w = f64::from(s.weights[j]);
            if w <= 0.0 {
                continue;
            }
            let v = f64::from(s.values[j]);
            let m = match near_light_at(light, &x) {
                Some((fall, l)) => fall * s.normal.dot(&l).max(0.0),
                None => 0.0,
            };
            vv += w * v * v;
            vm += w * v * m;
            mm += w * m * m;
        }
        if vv > 0.0 && mm > 0.0 {
            total += (vv - vm * vm / mm).max(0.0) / vv;
            n += 1;
        }
    }
    (total, n)
}

/// The scale (depth of the part's geometric-mean point) that minimises [`scale_residual`],
/// searched over ln s within `span` of ln `centre`: (scale, residual), or `None` without
/// usable samples.
fn fit_scale(
    own: &[&ScaleSample],
    lights: &[Light],
    centre: f64,
    span: f64,
    points: usize,
) -> Option<(f64, f64)> {
    if own.is_empty() {
        return None;
    }
    minimise_ln(
        |t| scale_residual(own, lights, t.exp()),
        centre.ln(),
        span,
        points,
    )
    .map(|(t, e)| (t.exp(), e))
}

/// The minimum of `at` over [c − span, c + span]: the best of `points` evenly spaced values
/// (evaluated in parallel), refined by golden section between its neighbours to 10⁻⁵;
/// (argument, value), or `None` when `at` is nowhere finite.
fn minimise_ln(
    at: impl Fn(f64) -> f64 + Sync,
    c: f64,
    span: f64,
    points: usize,
) -> Option<(f64, f64)> {
    let grid: Vec<(f64, f64)> = (0..points)
        .into_par_iter()
        .map(|i| {
            let t = c - span + 2.0 * span * i as f64 / (points - 1) as f64;
            (t, at(t))
        })
        .collect();
    let (best, _) = grid
        .iter()
        .enumerate()
        .filter(|(_, (_, e))| e.is_finite())
        .min_by(|a, b| a.1.1.total_cmp(&b.1.1))?;
    let step = 2.0 * span / (points - 1) as f64;
    let (mut a, mut b) = (grid[best].0 - step, grid[best].0 + step);
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut x1, mut x2) = (b - g * (b - a), a + g * (b - a));
    let (mut f1, mut f2) = (at(x1), at(x2));
    while b - a > 1e-5 {
        if f1 <= f2 || !f2.is_finite() {
            b = x2;
            x2 = x1;
            f2 = f1;
            x1 = b - g * (b - a);
            f1 = at(x1);
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            x2 = a + g * (b - a);
            f2 = at(x2);
        }
    }
    let t = 0.5 * (a + b);
    let e = at(t);
    if e.is_finite() && e <= grid[best].1 {
        Some((t, e))
    } else {
        Some(grid[best])
    }
}

/// RMS of the depth change over the masked pixels with both depths, as a fraction of the new
/// depth's 1st-to-99th-percentile range, or of 1% of its median depth when that is larger (a
/// nearly flat scene); ∞ when no pixel has both.
fn depth_change(old: &ScalarMap, new: &ScalarMap, mask: &Mask) -> f64 {
    let mut values = Vec::new();
    let (mut sum, mut n) = (0.0, 0usize);
    for p in 0..mask.len() {
        let (a, b) = (old.data()[p], new.data()[p]);
        if mask.data()[p] && a.is_finite() && b.is_finite() {
            sum += f64::from(b - a).powi(2);
            n += 1;
            values.push(b);
        }
    }
    if n == 0 {
        return f64::INFINITY;
    }
    values.sort_by(f32::total_cmp);
    let q = |f: f64| f64::from(values[((values.len() - 1) as f64 * f).round() as usize]);
    // A nearly flat part's range is no scale for the change: at least 1% of the distance.
    let range = (q(0.99) - q(0.01)).max(0.01 * q(0.5).abs()).max(1e-30);
    (sum / n as f64).sqrt() / range
}
