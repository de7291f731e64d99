//! Per-pixel estimation of the scaled normal g = ρN of the Lambertian model
//! I_k = E_k ρ max(0, N·l_k) (images already divided by E_k).
//!
//! Estimators, chosen by [`Method`]:
//! - [`Method::LeastSquares`]: plain least squares over every finite sample, g = (LᵀL)⁻¹LᵀI
//!   (Woodham 1980). The reference; biased wherever a pixel is shadowed in some images.
//! - [`Method::Threshold`]: least squares over the samples that pass threshold rejection:
//!   samples at or below a fraction of the pixel's brightest sample (shadows, ambient and
//!   interreflection floors) and saturated samples are dropped.
//! - [`Method::ShadowWeighted`]: the same rejection, and each equation I_k = l_k·g multiplied by
//!   I_k, so diag(I)·I = diag(I)·L·g (Forsyth & Ponce, *Computer Vision: A Modern Approach*,
//!   §5.4): shadowed samples carry no weight, dim ones little, and bright ones — including
//!   specular highlights — the most.
//! - Robust estimators ([`crate::ps::robust`]): rank trimming, IRLS with Huber, Tukey or L1 loss,
//!   and half-vector specular rejection.
//! - [`Method::Auto`] (the default) uses no more model than the data needs: every pixel is
//!   first fitted by threshold least squares; a χ² test of its residuals against the image
//!   noise (estimated from the images, [`crate::ps::noise`]) decides whether Lambert's law
//!   explains it, and only the pixels that fail are refitted with specular rejection. With 8
//!   or more lights it also corrects the light intensities from the data
//!   ([`crate::ps::intensities`]).
//!
//! Measured on DiLiGenT (mean angular error, cat / bear): plain least squares 8.41° / 8.39°,
//! threshold rejection 7.04° / 6.84°, intensity weighting 7.59° / 9.30°; see
//! `docs/photometric-stereo.md` for the robust estimators and `auto`.
//!
//! A pixel with fewer than [`MIN_SAMPLES`] usable samples, or whose used light directions have a
//! condition number above the limit, cannot be solved alone: by default it is filled from the
//! samples it has and its solved neighbours ([`crate::ps::fill`]) and marked
//! [`PixelStatus::Filled`]; with [`SolveOptions::fill`] off it is left unsolved.
//!
//! The linear estimators stream through the stack in blocks of masked pixels (each block reads
//! every image's rows once, then solves and measures residuals from cache) and run blocks in
//! parallel; the robust ones gather each block's samples pixel by pixel.
//!
//! The files: `options.rs` (what to compute: [`Method`], [`SolveOptions`]), `model.rs` (the
//! capture-wide [`ImageModel`], estimated before any pixel is fitted), `pixel.rs` (one pixel's
//! fit: [`solve_pixel`]), `kernel.rs` (the block kernel the whole-image solve runs),
//! `solution.rs` (the per-pixel results: [`Solution`], [`PixelStatus`], [`StatusCounts`]); the
//! entry points [`solve`] and [`solve_with_model`] are here.

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, ScalarMap, Window};
use crate::linalg::{condition_from_gram, solve_spd};
use crate::progress::Progress;
use crate::ps::fill::PixelData;
use crate::ps::robust::{
    DEFAULT_MIN_LIT_COSINE, DEFAULT_SPECULAR_CONE_DEG, DEFAULT_TRIM_HIGH, DEFAULT_TRIM_LOW,
    Estimator, Loss, PixelFitter, chi2_upper_quantile,
};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::Serialize;

mod kernel;
mod model;
mod options;
mod pixel;
mod solution;

use kernel::*;
pub use model::*;
pub use options::*;
pub use pixel::*;
pub use solution::*;

/// Checks that `stack`, `lights`, `mask` and `options` fit together for a solve of channel
/// `channel`.
pub(crate) fn check_inputs(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
) -> Result<()> {
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
    Grid::new(stack.width(), stack.height(), ()).check_same_size(mask, "mask vs images")?;
    let stored = stack.window();
    match mask.bounding_box() {
        Some(needed) if !stored.covers(&needed) => Err(Error::param(
            "mask",
            format!(
                "spans {needed} but the stack holds only {stored} of the images; load it with LoadOptions::window covering the mask"
            ),
        )),
        _ => Ok(()),
    }
}

/// Estimates g = ρN for every masked pixel of channel `channel` of `stack`.
///
/// # Errors
/// [`Error::DimensionMismatch`] when the mask's size differs from the stack's;
/// [`Error::LightsMismatch`] when the light count differs from the image count;
/// [`Error::InvalidParameter`] for invalid options.
///
/// # Example
/// ```
/// use photostereo::{grid::Grid, capture::stack::ImageStack, capture::lights::Lights, progress::Silent};
/// use photostereo::ps::solve::{solve, SolveOptions, PixelStatus};
/// let lights = Lights::ring(8, 45.0, 0.0)?;
/// // A flat patch facing the camera, albedo 0.5: I_k = 0.5 · l_k.z.
/// let images = lights.directions().iter().map(|l| vec![0.5 * l.z as f32; 4]).collect();
/// let stack = ImageStack::from_images(2, 2, 1, images)?;
/// let mask = Grid::new(2, 2, true);
/// let sol = solve(&stack, 0, &lights, &mask, &SolveOptions::default(), &Silent)?;
/// assert_eq!(*sol.status.at(0, 0), PixelStatus::Solved);
/// assert!((sol.g.at(1, 1).z - 0.5).abs() < 1e-6);
/// # Ok::<(), photostereo::Error>(())
/// ```
pub fn solve(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
    progress: &dyn Progress,
) -> Result<Solution> {
    let model = ImageModel::estimate(stack, channel, lights, mask, options)?;
    solve_with_model(stack, channel, lights, mask, options, model, progress)
}

/// [`solve`] with the per-image noise and gains given instead of estimated from `stack`: the
/// solve of one part of a capture whose model was estimated over the whole
/// ([`crate::run::stream`]). With [`SolveOptions::shadow_labels`], the per-pixel solution is
/// then relabelled for cast shadows and refitted ([`crate::ps::shadows::label_shadows`]) over
/// this part's pixels.
///
/// # Errors
/// As [`solve`]; [`Error::InvalidParameter`] when the model's length differs from the image
/// count.
pub fn solve_with_model(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
    model: ImageModel,
    progress: &dyn Progress,
) -> Result<Solution> {
    check_inputs(stack, channel, lights, mask, options)?;
    check_model(&model, stack.count())?;
    let (w, h) = (stack.width(), stack.height());
    let dirs64 = lights.directions();
    let ImageModel {
        sigma,
        gains,
        lobe_limit,
    } = model;
    let per = PerImage {
        dirs: dirs64
            .iter()
            .map(|d| [d.x as f32, d.y as f32, d.z as f32])
            .collect(),
        inv_var: sigma
            .iter()
            .zip(&gains.gains)
            .map(|(s, g)| 1.0 / (s * g).powi(2))
            .collect(),
        dirs64,
        gains: gains.gains.clone(),
        sigma: sigma.clone(),
    };
    let work = blocks(mask, stack.window());
    progress.begin("solve", work.len() as u64);
    let results: Vec<BlockOut> = work
        .into_par_iter()
        .map_init(Scratch::default, |scratch, spans| {
            let (pixels, unsolved) =
                solve_any_block(stack, channel, &per, options, &spans, scratch);
            progress.advance(1);
            BlockOut {
                spans,
                pixels,
                unsolved,
            }
        })
        .collect();
    progress.end();
    let mut sol = Solution::empty(w, h, gains, sigma, options);
    let mut unsolved = Vec::new();
    for block in results {
        let mut pixels = block.pixels.into_iter();
        for sp in &block.spans {
            for p in sp.start..sp.start + sp.len {
                let Some(px) = pixels.next() else { break };
                sol.record(p, &px);
            }
        }
        unsolved.extend(block.unsolved);
    }
    if let Some(labels) = &options.shadow_labels {
        let summary = crate::ps::shadows::label_shadows(
            stack, channel, lights, mask, options, labels, &mut sol,
        )?;
        sol.shadow_labels = Some(summary);
    }
    if options.method == Method::Auto && options.lobes {
        let summary = crate::ps::lobes::refit_with_lobes(
            stack, channel, lights, mask, options, lobe_limit, &mut sol,
        )?;
        sol.lobes = Some(summary);
    }
    // On the final fits of the solved pixels (not the filled ones).
    sol.shadow_light = Some(crate::ps::ambient::measure(
        stack, channel, lights, mask, &sol,
    ));
    sol.light_agreement = Some(crate::ps::light_agreement::measure(
        stack, channel, lights, mask, &sol,
    ));
    // Last: the fill leans on the final estimates of the solved neighbours.
    if options.fill {
        crate::ps::fill::fill(&mut sol, &unsolved);
    }
    Ok(sol)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::Silent;
    use rand::{RngExt, SeedableRng};

    /// The reference rank is ⌈f·n⌉ clamped to [1, n]; the reference level is that rank's
    /// sample among the usable ones (finite, unclipped when clipped samples are rejected),
    /// whether selected or found from its f32 rounding, also when an f32 product overflows.
    #[test]
    fn reference_rank_and_level() {
        assert_eq!(reference_rank(96, 0.1), 10);
        assert_eq!(reference_rank(95, 0.1), 10);
        assert_eq!(reference_rank(12, 0.1), 2);
        assert_eq!(reference_rank(10, 0.1), 1);
        assert_eq!(reference_rank(5, 0.0), 1);
        assert_eq!(reference_rank(0, 0.1), 1);
        assert_eq!(reference_rank(3, 0.49), 2);
        let mut keys = Vec::new();
        // The level selected, and found from its rounding (and from itself).
        let mut check = |values: &[f32], saturated: &[bool], gains: &[f32], f, want: f64| {
            let level = |r: Reference, keys: &mut Vec<u64>| {
                r.level(values, saturated, gains, true, f, keys)
            };
            assert_eq!(level(Reference::Unknown, &mut keys), want);
            assert_eq!(level(Reference::Rounded(want as f32), &mut keys), want);
            assert_eq!(level(Reference::Exact(want), &mut keys), want);
        };
        // 12 samples, rank 2 at f = 0.1: the second brightest usable one.
        let mut values = [0.5, 0.1, 0.9, 0.3, 0.7, 0.7, -1.0, -0.0, 0.2, 0.4, 0.6, 0.8];
        let mut clipped = [false; 12];
        let gains = [1.0; 12];
        check(&values, &clipped, &gains, 0.1, f64::from(0.8f32));
        // The brightest is clipped and NaN is never usable: rank 1 of 10 is 0.8; nor is 0.8 × ∞
        // usable: rank 1 of 9 is 0.7.
        clipped[2] = true;
        values[0] = f32::NAN;
        check(&values, &clipped, &gains, 0.1, f64::from(0.8f32));
        let mut inf_gain = gains;
        inf_gain[11] = f32::INFINITY;
        check(&values, &clipped, &inf_gain, 0.1, f64::from(0.7f32));
        // Negative levels, and none at all.
        check(&[-0.5, -0.25, -1.0], &[false; 3], &[1.0; 3], 0.0, -0.25);
        check(
            &[f32::NAN; 3],
            &[false; 3],
            &[1.0; 3],
            0.1,
            f64::NEG_INFINITY,
        );
        // Products that round to the same f32: the rank among them decides. (1 + 2⁻²³)² and
        // 1 + 2⁻²² both round to 1 + 2⁻²².
        let eps = f32::EPSILON;
        let tie = [1.0 + eps, 1.0 + 2.0 * eps, 0.5, 0.25];
        let gains = [1.0 + eps, 1.0, 1.0, 1.0];
        let (hi, lo) = (f64::from(1.0 + eps).powi(2), f64::from(1.0 + 2.0 * eps));
        assert!(hi > lo && hi as f32 == lo as f32);
        check(&tie, &[false; 4], &gains, 0.0, hi);
        check(&tie, &[false; 4], &gains, 0.49, lo);
        // A product beyond f32's range counts in f64 only: the level is selected, not found from
        // the f32 level (6e38, 4, 2, 1 in f64: rank ⌈1.96⌉ = 2 is 4; in f32 3 usable, rank 2: 2).
        let big = [3e38, 1.0, 2.0, 0.5];
        let level =
            Reference::Rounded(2.0).level(&big, &[false; 4], &[2.0; 4], true, 0.49, &mut keys);
        assert_eq!(level, 4.0);
    }

    /// The kernel's compare-exchange steps keep each pixel's brightest values in descending
    /// order.
    #[test]
    fn compare_exchange_keeps_the_brightest() {
        let (pixels, depth) = (3, 3);
        let mut top = vec![f32::NEG_INFINITY; pixels * depth];
        let samples: [[f32; 3]; 7] = [
            [0.5, 1.0, f32::NEG_INFINITY],
            [0.1, 2.0, f32::NEG_INFINITY],
            [0.9, 3.0, 7.0],
            [0.3, 0.0, f32::NEG_INFINITY],
            [0.7, 5.0, f32::NEG_INFINITY],
            [0.7, 4.0, f32::NEG_INFINITY],
            [-1.0, 6.0, f32::NEG_INFINITY],
        ];
        let mut candidates = vec![0.0; pixels];
        for row in samples {
            candidates.copy_from_slice(&row);
            for q in 0..depth {
                compare_exchange(&mut top[q * pixels..(q + 1) * pixels], &mut candidates);
            }
        }
        let list = |i: usize| [0, 1, 2].map(|q| top[q * pixels + i]);
        assert_eq!(list(0), [0.9, 0.7, 0.7]);
        assert_eq!(list(1), [6.0, 5.0, 4.0]);
        assert_eq!(list(2), [7.0, f32::NEG_INFINITY, f32::NEG_INFINITY]);
    }

    /// Blocked solve equals the per-pixel reference on random data with shadows, NaNs and
    /// saturation, for every method.
    #[test]
    // Pixel p indexes one sample in each of several images.
    #[allow(clippy::needless_range_loop)]
    fn blocked_solve_matches_per_pixel_reference() {
        let lights = Lights::fibonacci(17, 20.0).unwrap();
        let (w, h) = (37, 29);
        let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(7);
        let dirs = lights.directions();
        let mut images = vec![vec![0f32; w * h]; dirs.len()];
        for p in 0..w * h {
            let n = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                1.0,
            )
            .normalize();
            let rho = rng.random_range(0.2..0.9);
            for (k, l) in dirs.iter().enumerate() {
                let v = (rho * n.dot(l)).max(0.0) + rng.random_range(-0.01..0.01);
                images[k][p] = if rng.random_range(0.0..1.0) < 0.02 {
                    f32::NAN
                } else {
                    v as f32
                };
            }
        }
        let mut stack = ImageStack::from_images(w, h, 1, images.clone()).unwrap();
        let mut sat = vec![vec![false; w * h]; dirs.len()];
        for (k, row) in sat.iter_mut().enumerate() {
            for (p, s) in row.iter_mut().enumerate() {
                if (p * 7 + k * 3) % 53 == 0 {
                    *s = true;
                    stack.mark_saturated(k, p);
                }
            }
        }
        let mask = Grid::from_fn(w, h, |x, y| (x * y) % 11 != 3);
        // Every method, without intensity recalibration (the per-pixel form has none) and with
        // a known noise level (the per-pixel form cannot estimate it).
        let (mut boundary, mut escalated) = (0, 0);
        // Without the refit with specular lobes: it judges each pixel against the others,
        // which the per-pixel form cannot (`ps::lobes` has its own tests).
        for opts in Method::ALL.map(|method| SolveOptions {
            method,
            recalibrate: Some(false),
            noise_sigma: Some(0.004),
            lobes: false,
            ..SolveOptions::default()
        }) {
            let sol = solve(&stack, 0, &lights, &mask, &opts, &Silent).unwrap();
            for p in 0..w * h {
                if !mask.data()[p] {
                    assert_eq!(sol.status.data()[p], PixelStatus::Outside);
                    continue;
                }
                let vals: Vec<f32> = images.iter().map(|im| im[p]).collect();
                let sats: Vec<bool> = sat.iter().map(|s| s[p]).collect();
                let r = solve_pixel(&vals, &sats, &lights, &opts).unwrap();
                let r_robust = r.robust && r.status == PixelStatus::Solved;
                if opts.method == Method::Auto {
                    escalated += usize::from(r_robust);
                }
                if opts.method == Method::Auto && sol.robust.data()[p] != r_robust {
                    // The blocked fit test sums in f32: a pixel at the χ² boundary may go
                    // either way. Count these and bound them below.
                    boundary += 1;
                    continue;
                }
                assert_eq!(
                    sol.status.data()[p],
                    r.status,
                    "pixel {p} {}",
                    opts.method.name()
                );
                assert_eq!(sol.samples.data()[p] as usize, r.samples);
                if r.status == PixelStatus::Solved {
                    let g = sol.g.data()[p];
                    for c in 0..3 {
                        assert!((f64::from(g[c]) - r.g[c]).abs() < 1e-4 * r.g.norm());
                    }
                    assert!((f64::from(sol.residual.data()[p]) - r.residual).abs() < 1e-4);
                }
            }
        }
        // Both paths of the automatic method are exercised, and they agree but at the boundary.
        assert!(escalated > 50 && escalated < 900, "{escalated} escalated");
        assert!(boundary <= 5, "{boundary} pixels decided differently");
    }

    #[test]
    fn flags_too_few_and_coplanar_samples() {
        let lights = Lights::ring(6, 30.0, 0.0).unwrap();
        // Only two lit samples.
        let vals = [0.5, 0.4, 0.0, 0.0, 0.0, 0.0];
        let r = solve_pixel(&vals, &[false; 6], &lights, &SolveOptions::default()).unwrap();
        assert_eq!(r.status, PixelStatus::TooFewSamples);
        assert!(r.g.x.is_nan());
        // Coplanar lights (all in the x–z plane).
        let flat = Lights::from_directions(&[
            Vector3::new(1.0, 0.0, 1.0),
            Vector3::new(-1.0, 0.0, 1.0),
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(0.5, 0.0, 1.0),
        ])
        .unwrap();
        let r = solve_pixel(
            &[0.5, 0.5, 0.7, 0.6],
            &[false; 4],
            &flat,
            &SolveOptions::default(),
        )
        .unwrap();
        assert_eq!(r.status, PixelStatus::IllConditioned);
        // Mismatched lengths are an error, not a panic.
        assert!(solve_pixel(&[0.5; 3], &[false; 4], &flat, &SolveOptions::default()).is_err());
    }
}
