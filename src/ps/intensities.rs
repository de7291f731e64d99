//! Relative light intensities estimated from the images themselves: semi-calibrated
//! photometric stereo, I_k = e_k·ρ·max(0, N·l_k) with unknown per-image factors e_k.
//!
//! Cho, Matsushita, Tai & Kweon (2018), "Semi-calibrated photometric stereo", TPAMI 42(1),
//! show that the e_k are determined up to one global scale when the lights are not coplanar.
//! This module estimates them by alternation on a regular subsample of the mask, in two
//! nested loops:
//! - the outer loop fits g per pixel with the chosen estimator under the current gains, which
//!   decides each sample's weight (shadow, highlight, outlier);
//! - the inner loop holds those weights fixed and alternates: set each image's correction to
//!   the median of I_k/(g·l_k) over the samples that the fit used and that are well lit
//!   (N·l_k ≥ 0.3), normalise the corrections to median 1, then refit g by weighted least
//!   squares, until the largest correction is below [`TOLERANCE`].
//!
//! An image off as a whole (one wrong row of an intensity file) is an outlier in every pixel
//! to a robust fit, which then sets all its samples aside: it gives no ratio and its gain
//! stays 1. Such an image is measured afterwards over all its well-lit unsaturated samples,
//! under the final fits ([`set_aside_gains`]), where those ratios agree as closely as the
//! other images' do (an image the fits set aside because it is mostly in shadow does not: its
//! ratios spread); the measurement is reported in [`GainEstimate::estimated`] and never
//! applied.
//!
//! The estimate has converged when the first correction after a robust refit is below
//! [`TOLERANCE`], i.e. the robust fits under the gains reproduce them. The inner loop is a
//! 3×3 solve per pixel, so the slow linear convergence of the alternation costs little; the
//! outer loop converges as fast as the sample selection settles (2 refits on DiLiGenT cat,
//! 5 on bear, whose first 20 images are 10–26% dimmer than their stated intensities). The
//! median makes the estimate insensitive to the pixels where the model fails (shadows,
//! highlights), which a linear joint solve is not.
//!
//! The corrections are reported as gains (the factors the images are multiplied by), so a
//! capture whose intensity file is right gets gains near 1, and a wrong entry shows up as a
//! gain far from it.

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::error::Result;
use crate::grid::Mask;
use crate::linalg::solve_spd;
use crate::ps::robust::half_vector;
use crate::ps::solve::{PixelStatus, SolveOptions, fit_with, fitter};
use crate::stats::median_by;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::Serialize;

/// Fewest lights for which the factors are estimated (with few lights the fit absorbs them).
pub const MIN_LIGHTS: usize = 8;
/// Pixels of the regular subsample used for the estimate. An image is typically well lit
/// and used in half of them, so its correction is a median of about 1500 ratios: with a
/// 5% spread of the ratios its standard error is about 0.2%, below [`TOLERANCE`].
pub const SAMPLE_PIXELS: usize = 3000;
/// Most gain updates in all.
pub const MAX_ROUNDS: usize = 30;
/// Most robust refits of the subsample.
pub const MAX_REFITS: usize = 8;
/// The alternation stops when no factor changes by more than this (relative).
pub const TOLERANCE: f64 = 0.005;
/// Smallest N·l_k of a sample whose ratio counts (dim samples carry ambient light and noise).
const MIN_RATIO_COSINE: f64 = 0.3;
/// Fewest ratios for an image's factor to be estimated; otherwise it keeps its gain.
const MIN_RATIOS: usize = 30;

/// Estimated per-image gains.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GainEstimate {
    /// Factor each image's samples are multiplied by: the estimate when it was
    /// [`GainEstimate::applied`], otherwise all 1.
    pub gains: Vec<f32>,
    /// The estimated factors (median 1, or about 1 where an image set aside whole is
    /// measured), applied or not; for an image that the robust fits set aside whole, its
    /// measurement over all its well-lit samples, never applied (where it differs from
    /// [`GainEstimate::gains`] when the rest is).
    pub estimated: Vec<f32>,
    /// Whether the estimate replaced the stated intensities: it converged and the median
    /// relative residual of the robust fits on the subsample is lower under it than under
    /// unit gains. A runaway estimate (e.g. from a surface whose highlights defeat the
    /// robust fit) is thus reported but not used.
    pub applied: bool,
    /// Gain updates made.
    pub rounds: usize,
    /// Robust refits of the subsample (the sample selection is redone under the current
    /// gains; between refits the gains and g alternate with the selection held fixed).
    pub refits: usize,
    /// Whether the first update after the last robust refit changed no factor by more than
    /// [`TOLERANCE`].
    pub converged: bool,
    /// Pixels in the subsample.
    pub pixels: usize,
    /// Median over the subsample of the robust fit's RMS residual divided by its albedo,
    /// under unit gains.
    pub unit_misfit: f64,
    /// The same under the last gains the subsample was fitted with.
    pub misfit: f64,
}

impl GainEstimate {
    /// Unit gains (no correction) for `count` images.
    pub fn unit(count: usize) -> Self {
        GainEstimate {
            gains: vec![1.0; count],
            estimated: vec![1.0; count],
            applied: false,
            rounds: 0,
            refits: 0,
            converged: true,
            pixels: 0,
            unit_misfit: f64::NAN,
            misfit: f64::NAN,
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
/// `options` (its recalibration setting is ignored; for [`crate::ps::solve::Method::Auto`] the fit
/// test uses the noise estimated from the images, as [`crate::ps::solve::solve`] does).
///
/// # Errors
/// [`crate::Error::LightsMismatch`] when the light count differs from the image count;
/// [`crate::Error::DimensionMismatch`] for a mask of another size; [`crate::Error::InvalidParameter`] for a
/// bad channel or options.
pub fn estimate_gains(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
) -> Result<GainEstimate> {
    crate::ps::solve::check_inputs(stack, channel, lights, mask, options)?;
    let sigma = crate::ps::solve::test_sigmas(stack, channel, mask, options);
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
    // Gather the subsample as [pixel][image] (the pixels in parallel: each reads one value from
    // every image, far apart in memory).
    let mut values = vec![0f32; n * k];
    let mut saturated = vec![false; n * k];
    values
        .par_chunks_mut(k.max(1))
        .zip(saturated.par_chunks_mut(k.max(1)))
        .zip(pixels.par_iter())
        .for_each(|((v, s), &p)| {
            let local = stack.local(p);
            for img in 0..k {
                v[img] = local.map_or(f32::NAN, |i| stack.plane(img, channel)[i]);
                s[img] = stack.is_saturated(img, p);
            }
        });
    let dirs = lights.directions();
    let ratio_rule = RatioRule::new(&dirs, options.specular_cone_deg);
    let mut gains = vec![1.0f32; k];
    // Per pixel: the robust fit's g (None when unsolved) and its sample weights.
    let mut fits: Vec<Option<Vector3<f64>>> = vec![None; n];
    let mut weights = vec![0f64; n * k];
    let mut rounds = 0;
    let mut refits = 0;
    let mut converged = false;
    // Median relative residual of the robust fits: under unit gains, and the latest.
    let mut misfit = vec![f64::NAN; n];
    let (mut unit_misfit, mut last_misfit) = (f64::NAN, f64::NAN);
    while refits < MAX_REFITS && rounds < MAX_ROUNDS {
        refits += 1;
        let start = gains.clone();
        fits.par_iter_mut()
            .zip(weights.par_chunks_mut(k))
            .zip(misfit.par_iter_mut())
            .zip(values.par_chunks(k).zip(saturated.par_chunks(k)))
            .for_each_init(
                || fitter(&dirs, &start, options),
                |f, (((fit, w), e), (v, s))| {
                    let sol = fit_with(f, v, s, sigma, options);
                    let solved = sol.status == PixelStatus::Solved;
                    *fit = solved.then_some(sol.g);
                    *e = if solved {
                        sol.residual / sol.g.norm()
                    } else {
                        f64::NAN
                    };
                    w.copy_from_slice(f.weights());
                },
            );
        let mut finite: Vec<f64> = misfit.iter().copied().filter(|e| e.is_finite()).collect();
        last_misfit = median_by(&mut finite, f64::total_cmp).unwrap_or(f64::NAN);
        if refits == 1 {
            unit_misfit = last_misfit;
        }
        // Alternate gains and g with these sample weights held fixed. The first update
        // measures how far the robust fit is from consistency with the gains.
        rounds += 1;
        let first = update_gains(&fits, &weights, &values, &ratio_rule, &mut gains);
        if first < TOLERANCE {
            converged = true;
            break;
        }
        while rounds < MAX_ROUNDS {
            refit_fixed(&mut fits, &weights, &values, &dirs, &gains);
            rounds += 1;
            if update_gains(&fits, &weights, &values, &ratio_rule, &mut gains) < TOLERANCE {
                break;
            }
        }
    }
    // The images the fits set aside whole, measured over all their well-lit samples: reported,
    // not applied (the loop's gains, and so the fits and `applied`, are untouched).
    let aside = set_aside_gains(&fits, &weights, (&values, &saturated), &ratio_rule, &gains);
    // Report gains with median 1.
    let median = median_by(&mut gains.clone(), f32::total_cmp).unwrap_or(1.0);
    if median > 0.0 {
        for g in &mut gains {
            *g /= median;
        }
    }
    let mut estimated = gains.clone();
    for (img, g) in aside {
        if median > 0.0 {
            estimated[img] = g / median;
        }
    }
    // The simpler model (the stated intensities) stands unless the estimate converged and
    // the robust fits under it explain the subsample better.
    let applied = converged && last_misfit < unit_misfit;
    GainEstimate {
        gains: if applied { gains } else { vec![1.0; k] },
        estimated,
        applied,
        rounds,
        refits,
        converged,
        pixels: n,
        unit_misfit,
        misfit: last_misfit,
    }
}

/// One gain update: each image's correction is the median of I_k/(g·l_k) over the samples of
/// the fits that used it and are well lit; the corrections are normalised to median 1 and
/// divided out of `gains`. Returns the largest relative correction.
fn update_gains(
    fits: &[Option<Vector3<f64>>],
    weights: &[f64],
    values: &[f32],
    rule: &RatioRule,
    gains: &mut [f32],
) -> f64 {
    let k = gains.len();
    let normals = normals_of(fits);
    // Each image's median ratio, the images in parallel (the ratios are gathered in pixel
    // order, so the medians do not depend on the threads).
    let mut factors: Vec<f64> = (0..k)
        .into_par_iter()
        .map_init(Vec::new, |ratios: &mut Vec<f64>, img| {
            let used = |at: usize| weights[at] > 0.0;
            ratios_of(&normals, rule, values, (img, gains[img]), used, ratios);
            if ratios.len() < MIN_RATIOS {
                f64::NAN
            } else {
                median_by(ratios, f64::total_cmp).unwrap_or(f64::NAN)
            }
        })
        .collect();
    let mut known: Vec<f64> = factors.iter().copied().filter(|f| f.is_finite()).collect();
    let Some(median) = median_by(&mut known, f64::total_cmp) else {
        return 0.0;
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
    largest
}

/// Each subsample pixel's unit normal and albedo, from its fit's g (`None` where unsolved).
fn normals_of(fits: &[Option<Vector3<f64>>]) -> Vec<Option<(Vector3<f64>, f64)>> {
    fits.iter()
        .map(|fit| {
            fit.map(|g| {
                let rho = g.norm();
                (g / rho, rho)
            })
        })
        .collect()
}

/// Image `img`'s ratios I_k · gain / (ρ N·l_k), into `ratios` (cleared first), in pixel order:
/// over the samples (index `pixel × images + img` into `values`) that are `usable` and that
/// the `rule` counts.
fn ratios_of(
    normals: &[Option<(Vector3<f64>, f64)>],
    rule: &RatioRule,
    values: &[f32],
    (img, gain): (usize, f32),
    usable: impl Fn(usize) -> bool,
    ratios: &mut Vec<f64>,
) {
    let k = rule.dirs.len();
    let gain = f64::from(gain);
    ratios.clear();
    for (i, nr) in normals.iter().enumerate() {
        let Some((normal, rho)) = nr else { continue };
        let at = i * k + img;
        if !usable(at) {
            continue;
        }
        let c = normal.dot(&rule.dirs[img]);
        if rule.counts(normal, img, c) {
            ratios.push(f64::from(values[at]) * gain / (rho * c));
        }
    }
}

/// How far the ratios of an image set aside whole may spread, relative to the median spread of
/// the images measured from their used samples: a wrong intensity scales every sample of an
/// image alike, so its ratios spread as the others' do (noise, model error); ratios that
/// spread more come from samples the fits set aside for reasons of their own (shadows,
/// interreflections, clipping without a saturation level). Three: a median absolute
/// deviation's sampling spread, not a property of any capture.
const SET_ASIDE_SPREAD: f64 = 3.0;

/// The gains of the images that the fits (their `weights`) used in fewer than [`MIN_RATIOS`]
/// well-lit samples, measured over all their well-lit, unsaturated, finite samples under the
/// final `fits` and `gains`: image and gain (in the scale of `gains`), for each such image
/// whose ratios number at least [`MIN_RATIOS`] and spread (1.4826 × median absolute deviation
/// over the median) no more than [`SET_ASIDE_SPREAD`] times the median spread of the other
/// images' used ratios or than [`TOLERANCE`], whichever is larger.
fn set_aside_gains(
    fits: &[Option<Vector3<f64>>],
    weights: &[f64],
    (values, saturated): (&[f32], &[bool]),
    rule: &RatioRule,
    gains: &[f32],
) -> Vec<(usize, f32)> {
    let k = gains.len();
    let normals = normals_of(fits);
    // Per image: the median and relative spread of its ratios, over the used samples or (for
    // `all`) over every well-lit unsaturated finite one.
    let measure = |img: usize, all: bool| -> Option<(f64, f64)> {
        let mut ratios = Vec::new();
        let usable = |at: usize| {
            if all {
                !saturated[at] && values[at].is_finite()
            } else {
                weights[at] > 0.0
            }
        };
        ratios_of(
            &normals,
            rule,
            values,
            (img, gains[img]),
            usable,
            &mut ratios,
        );
        if ratios.len() < MIN_RATIOS {
            return None;
        }
        let centre = median_by(&mut ratios, f64::total_cmp)?;
        let mut deviations: Vec<f64> = ratios.iter().map(|r| (r - centre).abs()).collect();
        let spread = crate::ps::robust::MAD_TO_SIGMA * median_by(&mut deviations, f64::total_cmp)?;
        (centre > 0.0).then_some((centre, spread / centre))
    };
    let used: Vec<Option<(f64, f64)>> = (0..k).into_par_iter().map(|i| measure(i, false)).collect();
    if used.iter().all(|u| u.is_some()) {
        return Vec::new();
    }
    let (mut centres, mut spreads): (Vec<f64>, Vec<f64>) = used.iter().flatten().copied().unzip();
    let (Some(centre), Some(spread)) = (
        median_by(&mut centres, f64::total_cmp),
        median_by(&mut spreads, f64::total_cmp),
    ) else {
        return Vec::new();
    };
    let limit = (SET_ASIDE_SPREAD * spread).max(TOLERANCE);
    (0..k)
        .filter(|&img| used[img].is_none())
        .filter_map(|img| {
            let (c, s) = measure(img, true)?;
            // The correction relative to the measured images', as the update normalises it.
            let gain = (f64::from(gains[img]) * centre / c) as f32;
            (s <= limit && gain.is_finite() && gain > 0.0).then_some((img, gain))
        })
        .collect()
}

/// Which samples a gain ratio is taken from: well lit (N·l ≥ [`MIN_RATIO_COSINE`]) and outside
/// the specular cone (angle(N, h) above the cone of the specular estimator, with h the half
/// vector of light and view). A highlight that the pixel's fit kept would otherwise read as a
/// brighter image: on a rendered Blinn–Phong scene with k_s = 0.4 and exact intensities the
/// gains strayed 10% from 1 without this rule.
struct RatioRule<'a> {
    dirs: &'a [Vector3<f64>],
    halves: Vec<Vector3<f64>>,
    cos_cone: f64,
}

impl<'a> RatioRule<'a> {
    fn new(dirs: &'a [Vector3<f64>], cone_deg: f64) -> Self {
        RatioRule {
            dirs,
            halves: dirs.iter().map(half_vector).collect(),
            cos_cone: cone_deg.to_radians().cos(),
        }
    }

    /// Whether image `img`'s sample at normal `normal` (with N·l = `cosine`) gives a ratio.
    fn counts(&self, normal: &Vector3<f64>, img: usize, cosine: f64) -> bool {
        cosine >= MIN_RATIO_COSINE && normal.dot(&self.halves[img]) < self.cos_cone
    }
}

/// Refits every solved pixel's g by weighted least squares under new `gains`, with the
/// sample weights of its last robust fit.
fn refit_fixed(
    fits: &mut [Option<Vector3<f64>>],
    weights: &[f64],
    values: &[f32],
    dirs: &[Vector3<f64>],
    gains: &[f32],
) {
    let k = gains.len();
    fits.par_iter_mut()
        .zip(weights.par_chunks(k).zip(values.par_chunks(k)))
        .for_each(|(fit, (w, v))| {
            if fit.is_none() {
                return;
            }
            let mut a = Matrix3::zeros();
            let mut b = Vector3::zeros();
            for img in 0..k {
                if w[img] > 0.0 {
                    let l = &dirs[img];
                    a += l * l.transpose() * w[img];
                    b += l * (w[img] * f64::from(v[img]) * f64::from(gains[img]));
                }
            }
            *fit = solve_spd(a, b).or(*fit);
        });
}

/// Semi-calibrated estimation on noise-free synthetic Lambertian stacks: gains put on some
/// images lead to an estimate that converges and is applied under the module's rules, exact
/// intensities keep gains of 1 that are not applied (the simpler model stands), with fewer than
/// [`MIN_LIGHTS`] images nothing is estimated, and bad inputs are refused. The accuracy of the
/// recovered gains is checked by an ignored test: it fails today (see its reason).
#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;
    use crate::ps::solve::Method;
    use crate::synth::test_support::{lambertian_stack, sphere};

    /// `count` lights at 30°–90° elevation and a 24×24 sphere with normals up to 70° from the
    /// view (332 pixels): each image is well lit (N·l ≥ 0.3) in far more than [`MIN_RATIOS`].
    fn scene(count: usize) -> (Lights, Grid<Vector3<f64>>, Mask) {
        let lights = Lights::fibonacci(count, 30.0).unwrap();
        let (normals, mask) = sphere(24, 70.0);
        (lights, normals, mask)
    }

    /// Per-image brightness factors for `count` images: images 1, 4, 7 and 10 read 0.8, 1.25,
    /// 0.9 and 1.15 times their stated intensity, the others (the majority, hence the median)
    /// exactly it. The gains that undo this are 1/factor, and the normalisation to median 1
    /// leaves them unscaled.
    fn wrong_intensities(count: usize) -> Vec<f64> {
        let mut scale = vec![1.0; count];
        for (k, s) in [(1, 0.8), (4, 1.25), (7, 0.9), (10, 1.15)] {
            scale[k] = s;
        }
        scale
    }

    /// The largest relative error of the estimated gains against 1/`scale`.
    fn worst_gain_error(e: &GainEstimate, scale: &[f64]) -> f64 {
        e.estimated
            .iter()
            .zip(scale)
            .map(|(g, s)| (f64::from(*g) * s - 1.0).abs())
            .fold(0.0, f64::max)
    }

    /// Twelve images, four of them with wrong intensities: for the default estimator and for
    /// threshold least squares the estimate uses every pixel, converges, explains the data
    /// better than unit gains (a lower median relative misfit of the robust fits) and is
    /// therefore applied, and its factors have median exactly 1.
    #[test]
    fn wrong_intensities_give_an_applied_estimate() {
        let (lights, normals, mask) = scene(12);
        let scale = wrong_intensities(12);
        let stack = lambertian_stack(&normals, &mask, &lights, &[0.6], &scale);
        for method in [Method::Auto, Method::Threshold] {
            let e = estimate_gains(
                &stack,
                0,
                &lights,
                &mask,
                &SolveOptions::with_method(method),
            )
            .unwrap();
            println!(
                "{}: misfit {:.2e} vs unit {:.2e}, worst gain error {:.2e}, {} rounds, {} refits",
                method.name(),
                e.misfit,
                e.unit_misfit,
                worst_gain_error(&e, &scale),
                e.rounds,
                e.refits
            );
            assert_eq!(e.pixels, mask.count(), "every pixel is in the subsample");
            assert!(e.converged, "{}: {e:?}", method.name());
            assert!(e.misfit < e.unit_misfit, "{}: {e:?}", method.name());
            assert!(e.applied, "{}: {e:?}", method.name());
            assert_eq!(e.gains, e.estimated);
            let mut sorted = e.estimated.clone();
            sorted.sort_by(f32::total_cmp);
            assert_eq!(sorted[sorted.len() / 2], 1.0, "{}: {e:?}", method.name());
        }
    }

    /// One image off as a whole among 16, 15% brighter (and, in a second capture, 15% dimmer)
    /// than its light says: the default estimator's robust fits set aside every sample of it,
    /// which used to leave its gain at 1, unmeasured, and the run silent. It is measured over
    /// all its well-lit samples (within 0.1% on exact data, every other gain within 0.1% of 1),
    /// not applied (the fits that set it aside stand), and the run names it with that factor.
    #[test]
    fn an_image_off_as_a_whole_is_measured_and_named() {
        use crate::capture::Capture;
        use crate::progress::Silent;
        use crate::run::pipeline::{Config, reconstruct_normals};
        use crate::run::warnings::Warning;
        let (lights, normals, mask) = scene(16);
        for factor in [1.15, 0.85] {
            let mut scale = vec![1.0; 16];
            scale[5] = factor;
            let stack = lambertian_stack(&normals, &mask, &lights, &[0.6], &scale);
            let e = estimate_gains(&stack, 0, &lights, &mask, &SolveOptions::default()).unwrap();
            let worst = worst_gain_error(&e, &scale);
            assert!(worst < 1e-3, "{factor}: {worst:.2e} {e:?}");
            assert!(!e.applied && e.gains.iter().all(|&g| g == 1.0), "{e:?}");
            let capture = Capture::from_stack(stack, lights.clone(), Some(mask.clone())).unwrap();
            let config = Config {
                integration: None,
                ..Config::default()
            };
            let run = reconstruct_normals(&capture, &config, &Silent).unwrap();
            assert!(
                !run.warnings
                    .iter()
                    .any(|w| matches!(w, Warning::IntensitiesCorrected { .. })),
                "{:?}",
                run.warnings
            );
            let named = run.warnings.iter().find_map(|w| match w {
                Warning::IntensitiesNotApplied { images, worst } => Some((images, *worst)),
                _ => None,
            });
            let (images, gain) = named.unwrap_or_else(|| panic!("{factor}: {:?}", run.warnings));
            assert_eq!(images, &vec![5], "{factor}");
            assert!(
                (f64::from(gain) * factor - 1.0).abs() < 1e-3,
                "{factor}: {gain}"
            );
        }
    }

    /// An image the fits set aside because it is in shadow, not because it is off: image 6 of
    /// 16 lit in only a few pixels of the sphere and at a small constant level (shadow,
    /// interreflected light) elsewhere. Its ratios over all its well-lit samples spread far
    /// more than the other images' (the constant level over ρ N·l), so it is not measured:
    /// its estimate stays within 10% of 1 and nothing is applied (a first version of the
    /// measurement read it as 19 times too dim and applied that).
    #[test]
    fn an_image_in_shadow_is_not_taken_for_one_off_as_a_whole() {
        let (lights, normals, mask) = scene(16);
        let (w, h) = (mask.width(), mask.height());
        let dirs = lights.directions();
        let lit: Vec<usize> = (0..w * h).filter(|&p| mask.data()[p]).collect();
        let image = |k: usize, level: Option<(f32, usize)>| -> Vec<f32> {
            (0..w * h)
                .map(|p| {
                    let v = if mask.data()[p] {
                        (0.6 * normals.data()[p].dot(&dirs[k]).max(0.0)) as f32
                    } else {
                        0.0
                    };
                    match level {
                        Some((l, keep)) if v > 0.0 && !lit[..keep.min(lit.len())].contains(&p) => l,
                        _ => v,
                    }
                })
                .collect()
        };
        for level in [0.005f32, 0.02, 0.05] {
            for keep in [0, 20, 40] {
                let images = (0..16)
                    .map(|k| image(k, (k == 5).then_some((level, keep))))
                    .collect();
                let stack = ImageStack::from_images(w, h, 1, images).unwrap();
                let e =
                    estimate_gains(&stack, 0, &lights, &mask, &SolveOptions::default()).unwrap();
                let off = (e.estimated[5] - 1.0).abs();
                assert!(off < 0.1, "level {level}, {keep} lit: {e:?}");
                assert!(e.gains.iter().all(|g| (g - 1.0).abs() < 0.1), "{e:?}");
            }
        }
    }

    /// The estimate should recover the gains put on the images (1/0.8, 1/1.25, 1/0.9, 1/1.15
    /// and eight 1s) within [`TOLERANCE`]: on exact data the true gains are an exact fixed point
    /// of the alternation (every ratio is 1), which stops once an update corrects no gain by
    /// more than [`TOLERANCE`]; a contracting alternation (rate below 1/2) then leaves an error
    /// below that last correction. Checked for 12 and 32 lights, default and threshold
    /// estimators.
    ///
    /// It fails today: near the true gains the fixed-weight alternation is not a contraction:
    /// a 10⁻³ perturbation of the true gains grows to 3·10⁻² in 50 rounds, so where
    /// [`TOLERANCE`] stops it decides the error (12 lights: 0.91% for the default estimator,
    /// 4.4% for threshold least squares; 32 lights, threshold: 1.3%). (Until 2026-12-08 it
    /// failed a second way: with 32 lights the default estimator's robust fit rejected the four
    /// wrong images as outliers, so they got no ratios and kept gain 1, a 25% error; they are
    /// now measured over all their well-lit samples, within 10⁻⁷, though not applied: the
    /// robust fits that set them aside stand.)
    #[test]
    #[ignore = "known failure: the gain alternation does not contract near the true gains (see \
                the doc comment)"]
    fn wrong_intensities_are_recovered_within_the_tolerance() {
        let mut failures = Vec::new();
        for count in [12, 32] {
            let (lights, normals, mask) = scene(count);
            let scale = wrong_intensities(count);
            let stack = lambertian_stack(&normals, &mask, &lights, &[0.6], &scale);
            for method in [Method::Auto, Method::Threshold] {
                let options = SolveOptions::with_method(method);
                let e = estimate_gains(&stack, 0, &lights, &mask, &options).unwrap();
                let worst = worst_gain_error(&e, &scale);
                println!(
                    "{count} lights, {}: worst gain error {worst:.2e}, {e:?}",
                    method.name()
                );
                if !(worst < TOLERANCE && e.converged && e.applied) {
                    failures.push(format!("{count} lights, {}: {worst:.2e}", method.name()));
                }
            }
        }
        assert!(
            failures.is_empty(),
            "gain errors above {TOLERANCE}: {failures:?}"
        );
    }

    /// Exact intensities: the first update already finds nothing to correct (every ratio is 1
    /// to f32 rounding), so the estimate converges after one refit and one round with factors
    /// of 1 to within the rounding of the samples (κ·u with κ ≈ 2 the condition number of the
    /// lights and u = 2⁻²⁴; 10⁻⁶ allows κ up to 16). Its misfit is the unit misfit, so it does
    /// not explain the data better and is not applied: the gains used are exactly 1.
    #[test]
    fn exact_intensities_keep_unit_gains_unapplied() {
        let (lights, normals, mask) = scene(12);
        let stack = lambertian_stack(&normals, &mask, &lights, &[0.6], &[1.0; 12]);
        let e = estimate_gains(&stack, 0, &lights, &mask, &SolveOptions::default()).unwrap();
        let worst = e
            .estimated
            .iter()
            .map(|g| (g - 1.0).abs())
            .fold(0.0f32, f32::max);
        println!("exact: estimated within {worst:.2e} of 1, {e:?}");
        assert!(e.converged && e.refits == 1 && e.rounds == 1, "{e:?}");
        assert!(worst < 1e-6, "{e:?}");
        assert_eq!(e.misfit, e.unit_misfit);
        assert!(!e.applied);
        assert!(e.gains.iter().all(|&g| g == 1.0));
        assert!(e.outliers(0.0).is_empty());
    }

    /// With one light fewer than [`MIN_LIGHTS`] the factors are not estimated, however wrong
    /// an intensity is: the estimate is [`GainEstimate::unit`].
    #[test]
    fn too_few_lights_are_not_estimated() {
        let (lights, normals, mask) = scene(MIN_LIGHTS - 1);
        let mut scale = vec![1.0; MIN_LIGHTS - 1];
        scale[2] = 1.5;
        let stack = lambertian_stack(&normals, &mask, &lights, &[0.6], &scale);
        let e = estimate_gains(&stack, 0, &lights, &mask, &SolveOptions::default()).unwrap();
        // NaN misfits compare unequal: check them apart.
        assert!(e.misfit.is_nan() && e.unit_misfit.is_nan(), "{e:?}");
        let finite = |e: GainEstimate| GainEstimate {
            misfit: 0.0,
            unit_misfit: 0.0,
            ..e
        };
        assert_eq!(finite(e), finite(GainEstimate::unit(MIN_LIGHTS - 1)));
    }

    /// The checks of the public entry: a light count or mask size that differs from the stack's
    /// and a channel the stack does not have are refused.
    #[test]
    fn refuses_inputs_that_do_not_fit() {
        let (lights, normals, mask) = scene(12);
        let stack = lambertian_stack(&normals, &mask, &lights, &[0.6], &[1.0; 12]);
        let options = SolveOptions::default();
        let eleven = Lights::fibonacci(11, 30.0).unwrap();
        let e = estimate_gains(&stack, 0, &eleven, &mask, &options).unwrap_err();
        assert!(
            matches!(&e, crate::Error::LightsMismatch { reason } if reason.contains("11 lights for 12 images")),
            "{e}"
        );
        let narrow = Grid::new(23, 24, true);
        let e = estimate_gains(&stack, 0, &lights, &narrow, &options).unwrap_err();
        assert!(
            matches!(
                e,
                crate::Error::DimensionMismatch {
                    found_width: 23,
                    ..
                }
            ),
            "{e}"
        );
        let e = estimate_gains(&stack, 1, &lights, &mask, &options).unwrap_err();
        assert!(
            matches!(
                e,
                crate::Error::InvalidParameter {
                    name: "channel",
                    ..
                }
            ),
            "{e}"
        );
    }
}
