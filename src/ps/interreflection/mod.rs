//! Interreflection compensation: the light a concave surface throws onto itself, predicted
//! from the reconstructed shape and subtracted from the images before photometric stereo is
//! solved again (Nayar, Ikeuchi & Kanade, "Shape from interreflections", IJCV 6(3), 1991).
//!
//! **Why.** Photometric stereo assumes each pixel is lit by the light sources alone. In a
//! groove, a bowl or a fold each face is also lit by the faces it sees, so a pixel receives
//! I = ρ (n·l)⁺ E + ρ H, H the irradiance from the rest of the surface. H grows with the light
//! that the opposite faces catch, so the fit bends each normal towards them: concavities come
//! out shallower (the "pseudo-shape") and albedo too bright.
//!
//! **The correction.** For a Lambertian surface the observed pixel value is its radiosity B
//! (per unit light intensity, as the images are stored), and the radiosity equation
//! B = B⁽⁰⁾ + ρ F B (Goral et al., SIGGRAPH 1984; F the form factors) gives the direct part
//! exactly from the observed one:
//!
//! B⁽⁰⁾_i = B_i − ρ_i Σ_j F_ij B_j,
//!
//! every bounce at once, with no series to sum: the observed image already holds them. What
//! it needs is the shape (for F) and the reflectance ρ. Following Nayar et al., both come
//! from the current estimate: solve, integrate the normals to a height map, trace F on it
//! ([`FormFactors`]), subtract, solve again, and iterate; each round deepens the concavities
//! that the interreflections flattened.
//!
//! **The reflectance's scale.** F is absolute, but the albedo photometric stereo gives is ρ
//! times the unknown gain from scene radiance to pixel value: compensating needs ρ itself,
//! ρ = s·albedo. When the user does not give s, it is estimated from the data. The
//! interreflected light is not a linear function of the light direction: it is switched on
//! and off as the faces that send it pass in and out of attached and cast shadow, so with the
//! right s the compensated samples fit Lambert's law better than with any other. The estimate
//! is the s that minimises the relative RMS residual of threshold least squares
//! ([`crate::ps::solve::Method::Threshold`]) over the pixels that see at least
//! [`MIN_OCCLUSION`] of surface ([`estimate_scale`]), searched over reflectances 0 to 1 of the
//! brightest albedo ([`SCALE_STEPS`] steps, refined by a parabola). It is applied only when
//! the fall is more than chance: the paired z statistic of the per-pixel fall in squared
//! residual must exceed the fit test's deviate ([`SolveOptions::fit_test_z`], 3.09: a 0.1%
//! false-alarm rate). Otherwise the data do not show interreflections (a convex object, or one
//! whose residual is set by noise, highlights or shadows), and nothing is changed.
//!
//! **Senders.** A sample that is missing or saturated sends the Lambertian prediction
//! albedo·(n·l)⁺ of the current fit instead of its clipped value.
//!
//! **Where it breaks.** The shape is an orthographic height map integrated from the current
//! normals (in pixel units; a perspective capture is treated as orthographic here): separate
//! parts of the mask have independent heights, so light between them is not modelled, and
//! surfaces the camera cannot see (the walls under an overhang, the object's back, the
//! surround) send nothing. Specular interreflections are not modelled: a highlight's
//! reflection onto another face is light the correction does not remove. On a dark object
//! (ρ small) the correction is small and s poorly determined; the estimate then falls to 0.

pub mod form_factors;

pub use form_factors::FormFactors;

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, NormalMap, ScalarMap};
use crate::progress::Silent;
use crate::ps::solve::{Method, SolveOptions, solve};
use rayon::prelude::*;
use serde::Serialize;

/// Default rays per pixel of the form factors.
pub const DEFAULT_RAYS: usize = 64;
/// Default rounds of integrate → trace → compensate → solve.
pub const DEFAULT_ITERATIONS: usize = 3;
/// Pixels whose hemisphere is at least this fraction surface take part in the estimate of the
/// reflectance scale: with less, the interreflected light is at most this fraction of the
/// pixel's value, below the model error of real captures.
pub const MIN_OCCLUSION: f32 = 0.05;
/// Fewest such pixels for an estimate of the scale.
pub const MIN_PIXELS: usize = 50;
/// Steps of the search over the brightest pixel's reflectance, 0 to 1.
pub const SCALE_STEPS: usize = 10;
/// Quantile of the albedo taken as the brightest (robust to a few bright outliers).
pub const BRIGHT_QUANTILE: f64 = 0.99;

/// Interreflection compensation parameters, for [`crate::run::pipeline::Config::interreflections`].
///
/// # Example
/// A rendered V-groove lit by its own faces, solved without and with compensation:
/// ```
/// use photostereo::capture::{dataset::Capture, lights::Lights, stack::ColorMode};
/// use photostereo::eval::metrics::angular_errors;
/// use photostereo::progress::Silent;
/// use photostereo::ps::interreflection::InterreflectionOptions;
/// use photostereo::run::pipeline::{Config, reconstruct};
/// use photostereo::synth::{Material, render::{RenderOptions, render}, scene::{Albedo, SceneKind}};
///
/// let lights = Lights::fibonacci(16, 30.0)?;
/// let scene = SceneKind::Groove.build(48, Albedo::Constant(0.7), Material::lambertian());
/// let options = RenderOptions { bounces: 3, ..RenderOptions::default() };
/// let rendering = render(&scene, &lights, &options)?;
/// let stack = rendering.to_stack(&lights, ColorMode::Grey)?;
/// let capture = Capture::from_stack(stack, lights, Some(rendering.truth.mask.clone()))?;
/// let error = |config: &Config| -> photostereo::error::Result<f64> {
///     let recon = reconstruct(&capture, config, &Silent)?;
///     Ok(angular_errors(&recon.maps.normals, &rendering.truth.normals, &capture.mask)?.mean_deg)
/// };
/// let plain = error(&Config::default())?;
/// let compensated = error(&Config {
///     interreflections: Some(InterreflectionOptions::default()),
///     ..Config::default()
/// })?;
/// assert!(compensated < 0.5 * plain, "{compensated}° against {plain}°");
/// # Ok::<(), photostereo::error::Error>(())
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct InterreflectionOptions {
    /// Rounds of integrate → trace → compensate → solve (at least 1).
    pub iterations: usize,
    /// Cosine-weighted rays per pixel for the form factors.
    pub rays: usize,
    /// Reflectance per unit albedo (ρ = scale·albedo), when known; `None`: estimated from
    /// the data ([`estimate_scale`]).
    pub scale: Option<f64>,
    /// Seed of the ray directions.
    pub seed: u64,
}

impl Default for InterreflectionOptions {
    fn default() -> Self {
        InterreflectionOptions {
            iterations: DEFAULT_ITERATIONS,
            rays: DEFAULT_RAYS,
            scale: None,
            seed: 1,
        }
    }
}

impl InterreflectionOptions {
    /// Checks parameter ranges.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] naming the first bad parameter.
    pub fn validate(&self) -> Result<()> {
        if self.iterations == 0 || self.iterations > 20 {
            return Err(Error::param(
                "interreflection iterations",
                format!("{} is outside 1..=20", self.iterations),
            ));
        }
        if !(1..=form_factors::MAX_RAYS).contains(&self.rays) {
            return Err(Error::param(
                "interreflection rays",
                format!("{} is outside 1..={}", self.rays, form_factors::MAX_RAYS),
            ));
        }
        if let Some(s) = self.scale
            && !(s.is_finite() && s >= 0.0)
        {
            return Err(Error::param(
                "interreflection scale",
                format!("{s} is not a finite number ≥ 0"),
            ));
        }
        Ok(())
    }
}

/// The current estimate the compensation works from.
#[derive(Debug, Clone, Copy)]
pub struct Estimate<'a> {
    /// Albedo per channel (one map for all channels, or one per channel).
    pub albedo: &'a [ScalarMap],
    /// Unit normals (NaN where none).
    pub normals: &'a NormalMap,
}

impl Estimate<'_> {
    fn albedo(&self, channel: usize) -> &ScalarMap {
        &self.albedo[channel.min(self.albedo.len() - 1)]
    }

    /// The brightest albedo over `pixels` (the [`BRIGHT_QUANTILE`] quantile over channels).
    pub fn bright_albedo(&self, pixels: &[u32]) -> f64 {
        let mut v: Vec<f32> = self
            .albedo
            .iter()
            .flat_map(|a| pixels.iter().map(|&p| a.data()[p as usize]))
            .filter(|a| a.is_finite() && *a > 0.0)
            .collect();
        if v.is_empty() {
            return 0.0;
        }
        let k = ((v.len() - 1) as f64 * BRIGHT_QUANTILE).round() as usize;
        let (_, x, _) = v.select_nth_unstable_by(k, f32::total_cmp);
        f64::from(*x)
    }
}

/// `stack` with the interreflected light of the surface `ff` subtracted:
/// B⁽⁰⁾_i = B_i − scale·albedo_i·Σ_j F_ij B_j for every surface pixel i, image and channel
/// (floored at 0), B_j the observed sample, or the prediction albedo_j (n_j·l)⁺ where it is
/// missing or saturated. Samples off the surface, missing or saturated are left as they are.
///
/// # Errors
/// [`Error::DimensionMismatch`] when the maps are not the stack's size;
/// [`Error::InvalidParameter`] when the albedo has neither one map nor one per channel, or the
/// lights are not one per image.
pub fn compensate(
    stack: &ImageStack,
    lights: &Lights,
    ff: &FormFactors,
    estimate: &Estimate<'_>,
    scale: f64,
) -> Result<ImageStack> {
    check(stack, lights, ff, estimate)?;
    let n = stack.window().len();
    let directions = lights.directions();
    let mut data = stack.data().to_vec();
    data.par_chunks_mut(n.max(1))
        .enumerate()
        .take(stack.count() * stack.channels())
        .for_each(|(plane, out)| {
            let (k, c) = (plane / stack.channels(), plane % stack.channels());
            let sender = Sender::new(stack, &directions, estimate, k, c);
            let h = ff.gather(|p| sender.value(p));
            for (&p, h) in ff.pixels().iter().zip(h) {
                sender.subtract(p as usize, scale, h, out);
            }
        });
    stack.with_data(data)
}

/// The radiosity that surface pixels send under one image and channel, and the subtraction
/// at a receiver.
struct Sender<'a> {
    stack: &'a ImageStack,
    source: &'a [f32],
    albedo: &'a [f32],
    normals: &'a [nalgebra::Vector3<f32>],
    light: nalgebra::Vector3<f32>,
    image: usize,
}

impl<'a> Sender<'a> {
    fn new(
        stack: &'a ImageStack,
        directions: &[nalgebra::Vector3<f64>],
        estimate: &'a Estimate<'a>,
        image: usize,
        channel: usize,
    ) -> Self {
        Sender {
            stack,
            source: stack.plane(image, channel),
            albedo: estimate.albedo(channel).data(),
            normals: estimate.normals.data(),
            light: directions[image].cast::<f32>(),
            image,
        }
    }

    /// The observed sample of image pixel `p` where it is usable, else the Lambertian
    /// prediction albedo·(n·l)⁺ (0 where that is undefined).
    fn value(&self, p: usize) -> f32 {
        let v = self.stack.local(p).map_or(f32::NAN, |i| self.source[i]);
        if v.is_finite() && !self.stack.is_saturated(self.image, p) {
            v
        } else {
            let predicted = self.albedo[p] * self.normals[p].dot(&self.light).max(0.0);
            if predicted.is_finite() {
                predicted
            } else {
                0.0
            }
        }
    }

    /// Writes max(I − scale·albedo·h, 0) into `out` (the plane of the corrected copy) at
    /// image pixel `p`, where its sample is usable.
    fn subtract(&self, p: usize, scale: f64, h: f32, out: &mut [f32]) {
        let Some(i) = self.stack.local(p) else {
            return;
        };
        let v = self.source[i];
        let rho = scale as f32 * self.albedo[p];
        if v.is_finite() && rho.is_finite() && !self.stack.is_saturated(self.image, p) {
            out[i] = (v - rho * h).max(0.0);
        }
    }
}

fn check(stack: &ImageStack, lights: &Lights, ff: &FormFactors, e: &Estimate<'_>) -> Result<()> {
    let size = (stack.width(), stack.height());
    let mismatch = |what: &str, (w, h): (usize, usize)| Error::DimensionMismatch {
        what: what.into(),
        width: size.0,
        height: size.1,
        found_width: w,
        found_height: h,
    };
    if ff.size() != size {
        return Err(mismatch("form factors", ff.size()));
    }
    if (e.normals.width(), e.normals.height()) != size {
        return Err(mismatch("normals", (e.normals.width(), e.normals.height())));
    }
    if e.albedo.is_empty() || (e.albedo.len() != 1 && e.albedo.len() != stack.channels()) {
        return Err(Error::param(
            "albedo",
            format!(
                "{} maps for {} channels; 1 or one per channel expected",
                e.albedo.len(),
                stack.channels()
            ),
        ));
    }
    if let Some(a) = e.albedo.iter().find(|a| (a.width(), a.height()) != size) {
        return Err(mismatch("albedo", (a.width(), a.height())));
    }
    if lights.len() != stack.count() {
        return Err(Error::param(
            "lights",
            format!("{} lights for {} images", lights.len(), stack.count()),
        ));
    }
    Ok(())
}

/// What [`estimate_scale`] found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScaleEstimate {
    /// Reflectance per unit albedo; 0 when the data do not show interreflections.
    pub scale: f64,
    /// The reflectance this gives the brightest albedo ([`BRIGHT_QUANTILE`]).
    pub bright_reflectance: f64,
    /// Pixels that took part (those seeing at least [`MIN_OCCLUSION`] of surface).
    pub pixels: usize,
    /// Relative RMS residual of the threshold fit over those pixels without compensation.
    pub residual_without: f64,
    /// The same at the chosen scale.
    pub residual_with: f64,
    /// How far the fall in squared residual per pixel stands above chance: the paired z
    /// statistic (compensation is applied above the fit test's deviate,
    /// [`SolveOptions::fit_test_z`]).
    pub fall_z: f64,
    /// (brightest reflectance, relative residual) at each step of the search.
    pub curve: Vec<(f64, f64)>,
    /// The scale is a bound rather than a measurement: the residual was lowest at the top of
    /// the search (the brightest reflectance 1), so the data asked for at least this much. In
    /// a later round that kept an earlier round's scale, the earlier round's flag.
    pub at_limit: bool,
}

/// The reflectance scale s (ρ = s·albedo) that makes the compensated samples most
/// Lambertian, over the pixels that see at least [`MIN_OCCLUSION`] of surface (see the module
/// documentation); s = 0 when there are fewer than [`MIN_PIXELS`] of them or the residual's
/// fall is not above chance (paired z ≤ [`SolveOptions::fit_test_z`]).
///
/// # Errors
/// The errors of [`compensate`] and of the solve.
pub fn estimate_scale(
    stack: &ImageStack,
    lights: &Lights,
    ff: &FormFactors,
    estimate: &Estimate<'_>,
    solve_options: &SolveOptions,
) -> Result<ScaleEstimate> {
    let occlusion = ff.occlusion();
    let (w, h) = ff.size();
    let mut mask: Mask = Grid::new(w, h, false);
    let mut pixels = 0;
    for (&p, &o) in ff.pixels().iter().zip(&occlusion) {
        if o >= MIN_OCCLUSION {
            mask.data_mut()[p as usize] = true;
            pixels += 1;
        }
    }
    let bright = estimate.bright_albedo(ff.pixels());
    let none = ScaleEstimate {
        scale: 0.0,
        bright_reflectance: 0.0,
        pixels,
        residual_without: f64::NAN,
        residual_with: f64::NAN,
        fall_z: f64::NAN,
        curve: Vec::new(),
        at_limit: false,
    };
    let bright_ok = bright > 0.0; // false for NaN too
    if pixels < MIN_PIXELS || !bright_ok {
        return Ok(none);
    }
    let options = SolveOptions {
        method: Method::Threshold,
        fill: false,
        shadow_labels: None,
        ..*solve_options
    };
    // The irradiance at the pixels that take part, per image and channel: it does not depend
    // on the scale, so it is gathered once for the whole search.
    check(stack, lights, ff, estimate)?;
    let rows: Vec<usize> = (0..ff.pixels().len())
        .filter(|&k| occlusion[k] >= MIN_OCCLUSION)
        .collect();
    let directions = lights.directions();
    let planes = stack.count() * stack.channels();
    let gathered: Vec<Vec<f32>> = (0..planes)
        .into_par_iter()
        .map(|plane| {
            let (k, c) = (plane / stack.channels(), plane % stack.channels());
            let sender = Sender::new(stack, &directions, estimate, k, c);
            rows.iter()
                .map(|&row| ff.gather_at(row, |p| sender.value(p)))
                .collect()
        })
        .collect();
    let n = stack.window().len();
    let residuals_at = |reflectance: f64| -> Result<Vec<f64>> {
        let scale = reflectance / bright;
        let mut data = stack.data().to_vec();
        data.par_chunks_mut(n.max(1))
            .zip(&gathered)
            .enumerate()
            .for_each(|(plane, (out, h))| {
                let (k, c) = (plane / stack.channels(), plane % stack.channels());
                let sender = Sender::new(stack, &directions, estimate, k, c);
                for (&row, &h) in rows.iter().zip(h) {
                    sender.subtract(ff.pixels()[row] as usize, scale, h, out);
                }
            });
        relative_residuals(&stack.with_data(data)?, lights, &mask, &options)
    };
    let mut curve = Vec::with_capacity(SCALE_STEPS + 1);
    let mut residuals = Vec::with_capacity(SCALE_STEPS + 1);
    for step in 0..=SCALE_STEPS {
        let r = step as f64 / SCALE_STEPS as f64;
        let v = residuals_at(r)?;
        curve.push((r, rms(&v)));
        residuals.push(v);
    }
    let best = (0..curve.len())
        .min_by(|&a, &b| curve[a].1.total_cmp(&curve[b].1))
        .unwrap_or(0);
    let (mut reflectance, mut with) = curve[best];
    let mut with_residuals = residuals[best].clone();
    // A parabola through the minimum and its two neighbours, kept if it fits better.
    if best > 0 && best < SCALE_STEPS {
        let (a, b, c) = (curve[best - 1].1, curve[best].1, curve[best + 1].1);
        let denom = a - 2.0 * b + c;
        if denom > 0.0 {
            let refined =
                reflectance + (0.5 * (a - c) / denom).clamp(-0.5, 0.5) / SCALE_STEPS as f64;
            let v = residuals_at(refined)?;
            if rms(&v) < with {
                (reflectance, with, with_residuals) = (refined, rms(&v), v);
            }
        }
    }
    let without = curve[0].1;
    let z = paired_z(&residuals[0], &with_residuals);
    // The fall must be more than chance at the fit test's false-alarm rate; false for NaN.
    let shown = reflectance > 0.0 && z > solve_options.fit_test_z;
    if !shown {
        return Ok(ScaleEstimate {
            residual_without: without,
            residual_with: without,
            fall_z: z,
            curve,
            ..none
        });
    }
    Ok(ScaleEstimate {
        scale: reflectance / bright,
        bright_reflectance: reflectance,
        pixels,
        residual_without: without,
        residual_with: with,
        fall_z: z,
        curve,
        at_limit: best == SCALE_STEPS,
    })
}

/// The RMS of the finite values (NaN when there are none).
fn rms(values: &[f64]) -> f64 {
    let (sum, n) = values
        .iter()
        .filter(|v| v.is_finite())
        .fold((0.0, 0usize), |(s, n), v| (s + v * v, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        (sum / n as f64).sqrt()
    }
}

/// The paired z statistic of the fall from `before` to `after` in squared residual, over the
/// pixels finite in both: mean(d)/(sd(d)/√n) with d = before² − after² (NaN for fewer than
/// two pixels).
fn paired_z(before: &[f64], after: &[f64]) -> f64 {
    let d: Vec<f64> = before
        .iter()
        .zip(after)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .map(|(a, b)| a * a - b * b)
        .collect();
    let n = d.len() as f64;
    if d.len() < 2 {
        return f64::NAN;
    }
    let mean = d.iter().sum::<f64>() / n;
    let var = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
    if var > 0.0 {
        mean / (var / n).sqrt()
    } else if mean > 0.0 {
        f64::INFINITY
    } else {
        0.0
    }
}

/// Each of `mask`'s pixels' RMS residual / |g| per channel, in mask order (NaN where a pixel is
/// not solved).
fn relative_residuals(
    stack: &ImageStack,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
) -> Result<Vec<f64>> {
    let mut values = Vec::new();
    for c in 0..stack.channels() {
        let s = solve(stack, c, lights, mask, options, &Silent)?;
        for ((g, r), &m) in s.g.data().iter().zip(s.residual.data()).zip(mask.data()) {
            if m {
                let norm = g.norm();
                values.push(if r.is_finite() && norm > 0.0 {
                    f64::from(r / norm)
                } else {
                    f64::NAN
                });
            }
        }
    }
    Ok(values)
}
