//! Relative light intensities estimated from the images themselves: semi-calibrated
//! photometric stereo, I_k = e_k·ρ·max(0, N·l_k) with unknown per-image factors e_k.
//!
//! Cho, Matsushita, Tai & Kweon (2018), "Semi-calibrated photometric stereo", TPAMI 42(1),
//! show that the e_k are determined up to one global scale when the lights are not coplanar.
//! This module estimates them by alternation on a regular subsample of the mask: fit g per pixel
//! with the chosen estimator under the current gains, then set each image's correction to the
//! median of I_k/(g·l_k) over the samples that the fit used and that are well lit
//! (N·l_k ≥ 0.3), normalise the corrections to median 1 and repeat until the largest change is
//! below [`TOLERANCE`]. The median makes the estimate insensitive to the pixels where the model
//! fails (shadows, highlights), which a linear joint solve is not.
//!
//! The corrections are reported as gains (the factors the images are multiplied by), so a
//! capture whose intensity file is right gets gains near 1, and a wrong entry shows up as a
//! gain far from it.

use crate::error::{Error, Result};
use crate::grid::Mask;
use crate::input::ImageStack;
use crate::lights::Lights;
use crate::metrics::median_by;
use crate::solve::{PixelStatus, SolveOptions, fit_gathered};
use nalgebra::Vector3;
use rayon::prelude::*;
use serde::Serialize;

/// Fewest lights for which the factors are estimated (with few lights the fit absorbs them).
pub const MIN_LIGHTS: usize = 8;
/// Pixels of the regular subsample used for the estimate.
pub const SAMPLE_PIXELS: usize = 8000;
/// Most alternation rounds.
pub const MAX_ROUNDS: usize = 10;
/// The alternation stops when no factor changes by more than this (relative).
pub const TOLERANCE: f64 = 0.005;
/// Smallest N·l_k of a sample whose ratio counts (dim samples carry ambient light and noise).
const MIN_RATIO_COSINE: f64 = 0.3;
/// Fewest ratios for an image's factor to be estimated; otherwise it keeps its gain.
const MIN_RATIOS: usize = 30;

/// Estimated per-image gains.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GainEstimate {
    /// Factor each image's samples are multiplied by (median 1).
    pub gains: Vec<f32>,
    /// Alternation rounds run.
    pub rounds: usize,
    /// Whether the last round changed no factor by more than [`TOLERANCE`].
    pub converged: bool,
    /// Pixels in the subsample.
    pub pixels: usize,
}

impl GainEstimate {
    /// Unit gains (no correction) for `count` images.
    pub fn unit(count: usize) -> Self {
        GainEstimate {
            gains: vec![1.0; count],
            rounds: 0,
            converged: true,
            pixels: 0,
        }
    }

    /// The images (0-based) whose gain differs from 1 by more than `tolerance`.
    pub fn outliers(&self, tolerance: f32) -> Vec<usize> {
        (0..self.gains.len())
            .filter(|&k| (self.gains[k] - 1.0).abs() > tolerance)
            .collect()
    }
}

/// Estimates per-image gains for channel `channel` of `stack`, with the per-pixel estimator of
/// `options` (its recalibration setting is ignored; for [`crate::solve::Method::Auto`] the fit
/// test uses the noise estimated from the images, as [`crate::solve::solve`] does).
///
/// # Errors
/// [`Error::LightsMismatch`] when the light count differs from the image count;
/// [`Error::DimensionMismatch`] for a mask of another size; [`Error::InvalidParameter`] for a
/// bad channel or options.
pub fn estimate_gains(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
) -> Result<GainEstimate> {
    options.validate()?;
    if lights.len() != stack.count() {
        return Err(Error::LightsMismatch {
            reason: format!("{} lights for {} images", lights.len(), stack.count()),
        });
    }
    if channel >= stack.channels() {
        return Err(Error::param(
            "channel",
            format!("{channel} ≥ the stack's {} channels", stack.channels()),
        ));
    }
    crate::grid::Grid::new(stack.width(), stack.height(), ())
        .check_same_size(mask, "mask vs images")?;
    let sigma = crate::solve::test_sigmas(stack, channel, mask, options);
    Ok(estimate_gains_with(
        stack, channel, lights, mask, options, &sigma,
    ))
}

/// [`estimate_gains`] with the per-image noise of the fit test given, for inputs already
/// checked by the caller.
pub(crate) fn estimate_gains_with(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
    sigma: &[f32],
) -> GainEstimate {
    let k = stack.count();
    if k < MIN_LIGHTS {
        return GainEstimate::unit(k);
    }
    let masked: Vec<usize> = (0..mask.len()).filter(|&i| mask.data()[i]).collect();
    let stride = masked.len().div_ceil(SAMPLE_PIXELS).max(1);
    let pixels: Vec<usize> = masked.into_iter().step_by(stride).collect();
    let n = pixels.len();
    // Gather the subsample as [pixel][image].
    let mut values = vec![0f32; n * k];
    let mut saturated = vec![false; n * k];
    for img in 0..k {
        let plane = stack.plane(img, channel);
        for (i, &p) in pixels.iter().enumerate() {
            values[i * k + img] = plane[p];
            saturated[i * k + img] = stack.is_saturated(img, p);
        }
    }
    let dirs = lights.directions();
    let mut gains = vec![1.0f32; k];
    let mut rounds = 0;
    let mut converged = false;
    while rounds < MAX_ROUNDS {
        rounds += 1;
        // Per-pixel fits under the current gains; each yields (g, used flags).
        let fits: Vec<Option<(Vector3<f64>, Vec<bool>)>> = values
            .par_chunks(k)
            .zip(saturated.par_chunks(k))
            .map(|(v, s)| {
                let (sol, used) = fit_gathered(v, s, &dirs, &gains, sigma, options);
                (sol.status == PixelStatus::Solved).then_some((sol.g, used))
            })
            .collect();
        let mut ratios: Vec<Vec<f64>> = vec![Vec::new(); k];
        for (i, fit) in fits.iter().enumerate() {
            let Some((g, used)) = fit else { continue };
            let rho = g.norm();
            let normal = g / rho;
            for img in 0..k {
                let c = normal.dot(&dirs[img]);
                if used[img] && c >= MIN_RATIO_COSINE {
                    let v = f64::from(values[i * k + img]) * f64::from(gains[img]);
                    ratios[img].push(v / (rho * c));
                }
            }
        }
        let mut factors: Vec<f64> = ratios
            .iter_mut()
            .map(|r| {
                if r.len() < MIN_RATIOS {
                    f64::NAN
                } else {
                    median_by(r, f64::total_cmp).unwrap_or(f64::NAN)
                }
            })
            .collect();
        let mut known: Vec<f64> = factors.iter().copied().filter(|f| f.is_finite()).collect();
        let Some(median) = median_by(&mut known, f64::total_cmp) else {
            break;
        };
        let mut largest: f64 = 0.0;
        for (g, f) in gains.iter_mut().zip(&mut factors) {
            let e = if f.is_finite() && *f > 0.0 {
                *f / median
            } else {
                1.0
            };
            *g = (f64::from(*g) / e) as f32;
            largest = largest.max((e - 1.0).abs());
        }
        if largest < TOLERANCE {
            converged = true;
            break;
        }
    }
    // Report gains with median 1.
    let median = median_by(&mut gains.clone(), f32::total_cmp).unwrap_or(1.0);
    if median > 0.0 {
        for g in &mut gains {
            *g /= median;
        }
    }
    GainEstimate {
        gains,
        rounds,
        converged,
        pixels: n,
    }
}
