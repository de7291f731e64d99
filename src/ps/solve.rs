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
//! condition number above the limit, is flagged and left unsolved rather than guessed.
//!
//! The linear estimators stream through the stack in blocks of masked pixels (each block reads
//! every image's rows once, then solves and measures residuals from cache) and run blocks in
//! parallel; the robust ones gather each block's samples pixel by pixel.

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, ScalarMap, Window};
use crate::linalg::{condition_from_gram, solve_spd};
use crate::progress::Progress;
use crate::ps::robust::{
    DEFAULT_MIN_LIT_COSINE, DEFAULT_SPECULAR_CONE_DEG, DEFAULT_TRIM_HIGH, DEFAULT_TRIM_LOW,
    Estimator, Loss, PixelFitter, chi2_upper_quantile,
};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::Serialize;

/// Fewest usable samples that determine g (three unknowns).
pub const MIN_SAMPLES: usize = 3;
/// Default limit on the condition number of a pixel's used light directions.
pub const DEFAULT_MAX_CONDITION: f64 = 100.0;
/// Default shadow threshold, as a fraction of the pixel's brightest sample.
pub const DEFAULT_SHADOW_THRESHOLD: f32 = 0.1;
/// Pixels per work block: the block's samples for all images should stay in the L2 cache.
const BLOCK_PIXELS: usize = 1024;
/// Default standard-normal deviate of the automatic method's χ² test: a pixel is refitted when
/// its Lambertian residual would occur by noise alone with probability below 0.1%.
pub const DEFAULT_FIT_TEST_Z: f64 = 3.09;
/// Smallest noise level the fit test assumes, relative to an image's median signal: no real
/// surface follows Lambert's law closer than this, so exact synthetic data is not "misfit".
pub const MODEL_TOLERANCE: f32 = 1e-3;

/// The estimator for g.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum Method {
    /// Plain unweighted least squares over all finite samples.
    LeastSquares,
    /// Unweighted least squares over samples that pass shadow and saturation rejection.
    Threshold,
    /// Intensity-weighted (diag(I)) least squares with shadow and saturation rejection.
    ShadowWeighted,
    /// Least squares after dropping the darkest and brightest fractions of the samples.
    Trimmed,
    /// IRLS with the Huber loss over the threshold set.
    Huber,
    /// IRLS with Tukey's biweight over the threshold set.
    Tukey,
    /// IRLS with the L1 loss (least absolute deviations) over the threshold set.
    L1,
    /// Half-vector specular and grazing-angle rejection, then Tukey IRLS.
    Specular,
    /// Threshold least squares where Lambert's law fits (χ² test against the image noise),
    /// [`Method::Specular`] where it does not; light intensities corrected from the data.
    #[default]
    Auto,
}

impl Method {
    /// Every method, in order of model complexity.
    pub const ALL: [Method; 9] = [
        Method::LeastSquares,
        Method::Threshold,
        Method::ShadowWeighted,
        Method::Trimmed,
        Method::Huber,
        Method::Tukey,
        Method::L1,
        Method::Specular,
        Method::Auto,
    ];

    /// The name used on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Method::LeastSquares => "ls",
            Method::Threshold => "threshold",
            Method::ShadowWeighted => "weighted",
            Method::Trimmed => "trim",
            Method::Huber => "huber",
            Method::Tukey => "tukey",
            Method::L1 => "l1",
            Method::Specular => "specular",
            Method::Auto => "auto",
        }
    }

    /// Whether the method is one of the linear estimators of the blocked fast path.
    fn is_linear(self) -> bool {
        matches!(
            self,
            Method::LeastSquares | Method::Threshold | Method::ShadowWeighted
        )
    }
}

/// Parameters of [`solve`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SolveOptions {
    /// The estimator.
    pub method: Method,
    /// Every method but plain least squares: samples at or below this fraction of the pixel's
    /// brightest sample (and all samples ≤ 0) are treated as shadowed and dropped.
    pub shadow_threshold: f32,
    /// Every method but plain least squares: drop samples marked saturated in the stack.
    pub reject_saturated: bool,
    /// Pixels whose used light directions have a condition number above this are flagged.
    pub max_condition: f64,
    /// [`Method::Trimmed`]: fraction of each pixel's samples dropped from the dark end.
    pub trim_low: f32,
    /// [`Method::Trimmed`]: fraction of each pixel's samples dropped from the bright end.
    pub trim_high: f32,
    /// [`Method::Specular`] and [`Method::Auto`]: half-angle in degrees of the cone around the
    /// normal in which a sample's half vector marks it specular.
    pub specular_cone_deg: f64,
    /// [`Method::Specular`] and [`Method::Auto`]: samples with N·l below this are dropped.
    pub min_lit_cosine: f64,
    /// Estimate per-image intensity corrections from the data ([`crate::ps::intensities`]) and
    /// apply them where they converge and fit better than the stated intensities; `None`:
    /// only for [`Method::Auto`]. Never with fewer than [`crate::ps::intensities::MIN_LIGHTS`]
    /// images.
    pub recalibrate: Option<bool>,
    /// [`Method::Auto`]: the noise standard deviation of the (intensity-divided) samples, when
    /// known; `None` estimates it per image ([`crate::ps::noise`]).
    pub noise_sigma: Option<f32>,
    /// [`Method::Auto`]: standard-normal deviate of the χ² fit test (3.09: 0.1% false alarms).
    pub fit_test_z: f64,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            method: Method::default(),
            shadow_threshold: DEFAULT_SHADOW_THRESHOLD,
            reject_saturated: true,
            max_condition: DEFAULT_MAX_CONDITION,
            trim_low: DEFAULT_TRIM_LOW,
            trim_high: DEFAULT_TRIM_HIGH,
            specular_cone_deg: DEFAULT_SPECULAR_CONE_DEG,
            min_lit_cosine: DEFAULT_MIN_LIT_COSINE,
            recalibrate: None,
            noise_sigma: None,
            fit_test_z: DEFAULT_FIT_TEST_Z,
        }
    }
}

impl SolveOptions {
    /// Plain least squares over every sample: the reference estimator.
    pub fn least_squares() -> Self {
        Self::with_method(Method::LeastSquares)
    }

    /// Default parameters with `method`.
    pub fn with_method(method: Method) -> Self {
        SolveOptions {
            method,
            ..SolveOptions::default()
        }
    }

    /// Whether intensity corrections are estimated for a stack of `count` images.
    pub fn recalibrates(&self, count: usize) -> bool {
        self.recalibrate.unwrap_or(self.method == Method::Auto)
            && count >= crate::ps::intensities::MIN_LIGHTS
    }

    /// Checks parameter ranges.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] naming the first parameter out of range.
    pub fn validate(&self) -> Result<()> {
        if !(0.0..1.0).contains(&self.shadow_threshold) {
            return Err(Error::param(
                "shadow-threshold",
                format!("{} is outside [0, 1)", self.shadow_threshold),
            ));
        }
        if self.max_condition.is_nan() || self.max_condition <= 1.0 {
            return Err(Error::param(
                "max-condition",
                format!("{} must be > 1", self.max_condition),
            ));
        }
        for (name, v) in [("trim-low", self.trim_low), ("trim-high", self.trim_high)] {
            if !(0.0..1.0).contains(&v) {
                return Err(Error::param(name, format!("{v} is outside [0, 1)")));
            }
        }
        if self.trim_low + self.trim_high >= 0.9 {
            return Err(Error::param(
                "trim-low/trim-high",
                format!(
                    "{} + {} leaves fewer than 10% of the samples",
                    self.trim_low, self.trim_high
                ),
            ));
        }
        if !(0.0..90.0).contains(&self.specular_cone_deg) {
            return Err(Error::param(
                "specular-cone",
                format!("{}° is outside [0°, 90°)", self.specular_cone_deg),
            ));
        }
        if !(0.0..1.0).contains(&self.min_lit_cosine) {
            return Err(Error::param(
                "min-lit-cosine",
                format!("{} is outside [0, 1)", self.min_lit_cosine),
            ));
        }
        if let Some(s) = self.noise_sigma
            && !(s.is_finite() && s > 0.0)
        {
            return Err(Error::param("noise-sigma", format!("{s} must be > 0")));
        }
        if !(self.fit_test_z.is_finite() && self.fit_test_z > 0.0) {
            return Err(Error::param(
                "fit-test-z",
                format!("{} must be > 0", self.fit_test_z),
            ));
        }
        Ok(())
    }

    /// The robust estimator of a robust method; `None` for the linear ones.
    fn estimator(&self) -> Option<Estimator> {
        let specular = Estimator::Specular {
            cos_cone: self.specular_cone_deg.to_radians().cos(),
            min_cos_lit: self.min_lit_cosine,
        };
        Some(match self.method {
            Method::LeastSquares | Method::Threshold | Method::ShadowWeighted => return None,
            Method::Trimmed => Estimator::Trimmed {
                low: self.trim_low,
                high: self.trim_high,
            },
            Method::Huber => Estimator::Irls(Loss::Huber),
            Method::Tukey => Estimator::Irls(Loss::Tukey),
            Method::L1 => Estimator::Irls(Loss::L1),
            Method::Specular | Method::Auto => specular,
        })
    }
}

/// What happened at a pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum PixelStatus {
    /// Not in the mask.
    #[default]
    Outside,
    /// g was estimated.
    Solved,
    /// Fewer than [`MIN_SAMPLES`] usable samples.
    TooFewSamples,
    /// The used light directions are (nearly) coplanar.
    IllConditioned,
    /// The estimate is zero or not finite (a black pixel).
    Dark,
}

/// Per-pixel result of one solve: g = ρN and its diagnostics.
#[derive(Debug, Clone)]
pub struct Solution {
    /// g = ρN per pixel; NaN where not solved.
    pub g: Grid<Vector3<f32>>,
    /// RMS of I − g·l over the used samples; NaN where not solved.
    pub residual: ScalarMap,
    /// Number of samples used.
    pub samples: Grid<u16>,
    /// Condition number of the used light directions (∞ when fewer than 3).
    pub condition: ScalarMap,
    /// What happened at each pixel.
    pub status: Grid<PixelStatus>,
    /// Pixels fitted by a robust estimator (for [`Method::Auto`]: those whose residuals
    /// failed the Lambertian fit test).
    pub robust: Grid<bool>,
    /// Per-image intensity corrections applied (all 1 unless recalibrated).
    pub gains: crate::ps::intensities::GainEstimate,
    /// Per-image noise standard deviation used by the fit test ([`Method::Auto`]; empty
    /// otherwise).
    pub noise: Vec<f32>,
}

impl Solution {
    /// A `width`×`height` solution with every pixel outside the mask, the gains applied and
    /// the fit test's noise `sigma` (kept for [`Method::Auto`] only).
    pub(crate) fn empty(
        width: usize,
        height: usize,
        gains: crate::ps::intensities::GainEstimate,
        sigma: Vec<f32>,
        options: &SolveOptions,
    ) -> Self {
        Solution {
            g: Grid::new(width, height, Vector3::repeat(f32::NAN)),
            residual: Grid::new(width, height, f32::NAN),
            samples: Grid::new(width, height, 0),
            condition: Grid::new(width, height, f32::NAN),
            status: Grid::new(width, height, PixelStatus::Outside),
            robust: Grid::new(width, height, false),
            gains,
            noise: if options.method == Method::Auto {
                sigma
            } else {
                Vec::new()
            },
        }
    }

    /// Copies every row of `band` (a solution of the same width) into rows `y0..` of this one:
    /// the assembly of a capture solved in row bands ([`crate::run::stream`]).
    ///
    /// # Errors
    /// [`Error::DimensionMismatch`] when the widths differ or the band runs past the last row.
    pub(crate) fn paste_rows(&mut self, band: &Solution, y0: usize) -> Result<()> {
        let (w, h) = (self.g.width(), self.g.height());
        if band.g.width() != w || y0 + band.g.height() > h {
            return Err(Error::DimensionMismatch {
                what: format!("solution band pasted at row {y0}"),
                width: w,
                height: h,
                found_width: band.g.width(),
                found_height: y0 + band.g.height(),
            });
        }
        let r = y0 * w..(y0 + band.g.height()) * w;
        self.g.data_mut()[r.clone()].copy_from_slice(band.g.data());
        self.residual.data_mut()[r.clone()].copy_from_slice(band.residual.data());
        self.samples.data_mut()[r.clone()].copy_from_slice(band.samples.data());
        self.condition.data_mut()[r.clone()].copy_from_slice(band.condition.data());
        self.status.data_mut()[r.clone()].copy_from_slice(band.status.data());
        self.robust.data_mut()[r].copy_from_slice(band.robust.data());
        Ok(())
    }

    /// The first `rows` rows of this solution (all of it when it has fewer).
    pub(crate) fn top_rows(&self, rows: usize) -> Solution {
        fn top<T: Clone>(g: &Grid<T>, rows: usize) -> Grid<T> {
            Grid::from_fn(g.width(), rows, |x, y| g.at(x, y).clone())
        }
        let rows = rows.min(self.g.height());
        Solution {
            g: top(&self.g, rows),
            residual: top(&self.residual, rows),
            samples: top(&self.samples, rows),
            condition: top(&self.condition, rows),
            status: top(&self.status, rows),
            robust: top(&self.robust, rows),
            gains: self.gains.clone(),
            noise: self.noise.clone(),
        }
    }

    /// Records the outcome `px` of pixel `p` (row-major index).
    pub(crate) fn record(&mut self, p: usize, px: &PixelSolution) {
        self.g.data_mut()[p] = px.g.map(|v| v as f32);
        self.residual.data_mut()[p] = px.residual as f32;
        self.samples.data_mut()[p] = px.samples.min(u16::MAX as usize) as u16;
        self.condition.data_mut()[p] = px.condition as f32;
        self.status.data_mut()[p] = px.status;
        self.robust.data_mut()[p] = px.robust && px.status == PixelStatus::Solved;
    }
}

/// Solved pixel, as returned by [`solve_pixel`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelSolution {
    /// The estimate (NaN unless `status` is [`PixelStatus::Solved`]).
    pub g: Vector3<f64>,
    /// RMS residual over used samples.
    pub residual: f64,
    /// Samples used.
    pub samples: usize,
    /// Condition number of the used light directions.
    pub condition: f64,
    /// Outcome.
    pub status: PixelStatus,
    /// Fitted by a robust estimator (for [`Method::Auto`]: escalated from least squares).
    pub robust: bool,
}

/// The sample filter (which samples count as usable) and the weighting.
#[derive(Clone, Copy)]
struct Rule {
    /// Threshold and saturation rejection applies.
    reject: bool,
    /// Rows weighted by I (normal equations by I²).
    intensity_weight: bool,
    relative: f32,
    reject_saturated: bool,
}

impl Rule {
    /// The rule of a linear `method` (any other method uses the threshold rule).
    fn new(method: Method, o: &SolveOptions) -> Self {
        let reject = method != Method::LeastSquares;
        Rule {
            reject,
            intensity_weight: method == Method::ShadowWeighted,
            relative: o.shadow_threshold,
            reject_saturated: reject && o.reject_saturated,
        }
    }

    /// Samples must exceed this; NaN never does.
    fn threshold(&self, pixel_max: f32) -> f32 {
        if self.reject {
            (self.relative * pixel_max).max(0.0)
        } else {
            f32::NEG_INFINITY
        }
    }
}

/// Solves one pixel from its samples `values[k]` under `lights` (values divided by intensity;
/// NaN for missing samples; `saturated[k]` marks clipped ones). This is the plain, unblocked
/// form of [`solve`] without intensity recalibration. For [`Method::Auto`] the fit test uses
/// [`SolveOptions::noise_sigma`], or when it is unset [`MODEL_TOLERANCE`] times the pixel's
/// median positive sample (the image noise is not known from one pixel).
///
/// # Errors
/// [`Error::LightsMismatch`] when `values`, `saturated` and `lights` differ in length;
/// [`Error::InvalidParameter`] for invalid options.
pub fn solve_pixel(
    values: &[f32],
    saturated: &[bool],
    lights: &Lights,
    options: &SolveOptions,
) -> Result<PixelSolution> {
    options.validate()?;
    if values.len() != lights.len() || saturated.len() != lights.len() {
        return Err(Error::LightsMismatch {
            reason: format!(
                "{} samples and {} saturation flags for {} lights",
                values.len(),
                saturated.len(),
                lights.len()
            ),
        });
    }
    let dirs = lights.directions();
    let gains = vec![1.0; values.len()];
    let sigma = match options.noise_sigma {
        Some(s) => s,
        None => {
            let mut pos: Vec<f32> = values
                .iter()
                .copied()
                .filter(|v| v.is_finite() && *v > 0.0)
                .collect();
            let level = crate::stats::median_by(&mut pos, f32::total_cmp).unwrap_or(1.0);
            MODEL_TOLERANCE * level
        }
    };
    let sigma = vec![sigma; values.len()];
    let mut f = fitter(&dirs, &gains, options);
    Ok(fit_with(&mut f, values, saturated, &sigma, options))
}

/// A per-pixel fitter with the rejection parameters of `options`.
pub(crate) fn fitter<'a>(
    dirs: &'a [Vector3<f64>],
    gains: &'a [f32],
    options: &SolveOptions,
) -> PixelFitter<'a> {
    PixelFitter::new(
        dirs,
        gains,
        options.shadow_threshold,
        options.reject_saturated,
        options.max_condition,
    )
}

/// Fits one pixel's gathered samples with the method of `options`, using `f`'s per-image
/// gains; `sigma` is the per-image noise of the samples before gains ([`Method::Auto`] only).
pub(crate) fn fit_with(
    f: &mut PixelFitter,
    values: &[f32],
    saturated: &[bool],
    sigma: &[f32],
    options: &SolveOptions,
) -> PixelSolution {
    let plain = |reject, intensity_weight| Estimator::Plain {
        reject,
        intensity_weight,
    };
    match options.method {
        Method::LeastSquares => f.fit(values, saturated, plain(false, false)),
        Method::Threshold => f.fit(values, saturated, plain(true, false)),
        Method::ShadowWeighted => f.fit(values, saturated, plain(true, true)),
        Method::Auto => {
            let p = f.fit(values, saturated, plain(true, false));
            if !misfit(&p, f.chi2(&p.g, sigma), options.fit_test_z) {
                return p;
            }
            escalate(f, values, saturated, p, options)
        }
        _ => match options.estimator() {
            Some(e) => f.fit(values, saturated, e),
            None => f.fit(values, saturated, plain(true, false)),
        },
    }
}

/// Whether a Lambertian fit `p` with residual statistic `chi2` fails the fit test at
/// standard-normal deviate `z` (unsolved pixels always do).
fn misfit(p: &PixelSolution, chi2: f64, z: f64) -> bool {
    if p.status != PixelStatus::Solved {
        return true;
    }
    let dof = p.samples.saturating_sub(MIN_SAMPLES);
    dof > 0 && chi2 > chi2_upper_quantile(dof as f64, z)
}

/// Refits a pixel that failed the fit test with the robust estimator; keeps the Lambertian
/// fit `lambertian` when the robust one cannot solve the pixel.
fn escalate(
    f: &mut PixelFitter,
    values: &[f32],
    saturated: &[bool],
    lambertian: PixelSolution,
    options: &SolveOptions,
) -> PixelSolution {
    let Some(estimator) = options.estimator() else {
        return lambertian;
    };
    let q = f.fit(values, saturated, estimator);
    if q.status == PixelStatus::Solved || lambertian.status != PixelStatus::Solved {
        q
    } else {
        // Restore the fitter's weights to the fit that is returned.
        f.fit(
            values,
            saturated,
            Estimator::Plain {
                reject: true,
                intensity_weight: false,
            },
        )
    }
}

/// Decides a pixel's outcome: too few samples, ill-conditioned (by the condition number of its
/// used directions, computed by the caller), or solved by `solve`.
fn finish_pixel(
    n: usize,
    condition: f64,
    max_condition: f64,
    solve: impl FnOnce() -> Option<Vector3<f64>>,
) -> (Vector3<f64>, f64, PixelStatus) {
    let nan = Vector3::repeat(f64::NAN);
    if n < MIN_SAMPLES {
        return (nan, f64::INFINITY, PixelStatus::TooFewSamples);
    }
    if condition.is_nan() || condition > max_condition {
        return (nan, condition, PixelStatus::IllConditioned);
    }
    match solve() {
        None => (nan, condition, PixelStatus::IllConditioned),
        Some(g) if g.iter().all(|v| v.is_finite()) && g.norm() > 1e-12 => {
            (g, condition, PixelStatus::Solved)
        }
        Some(_) => (nan, condition, PixelStatus::Dark),
    }
}

/// The condition number and inverse of the last Gram matrix seen: neighbouring pixels usually
/// use the same lights (plain least squares: all pixels), so the eigenvalues and inverse are
/// computed once per distinct light subset rather than per pixel.
struct GramCache {
    key: [f32; 6],
    condition: f64,
    inverse: Option<Matrix3<f64>>,
}

impl GramCache {
    fn new() -> Self {
        GramCache {
            key: [f32::NAN; 6],
            condition: f64::NAN,
            inverse: None,
        }
    }

    fn get(&mut self, key: [f32; 6], gram: &Matrix3<f64>) -> (f64, Option<Matrix3<f64>>) {
        if key != self.key {
            self.key = key;
            self.condition = condition_from_gram(gram);
            self.inverse = gram.try_inverse();
        }
        (self.condition, self.inverse)
    }
}

/// A run of consecutive masked pixels `[start, start + len)` in row-major order, at
/// `[local, local + len)` in the stack's planes.
#[derive(Clone, Copy)]
struct Span {
    start: usize,
    local: usize,
    len: usize,
}

/// Splits the mask into blocks of at most [`BLOCK_PIXELS`] masked pixels made of row spans;
/// `window` (the stack's, covering the mask) gives their place in the planes.
fn blocks(mask: &Mask, window: Window) -> Vec<Vec<Span>> {
    let (w, h) = (mask.width(), mask.height());
    let mut out = Vec::new();
    let mut current = Vec::new();
    let mut filled = 0;
    for y in 0..h {
        let row = &mask.data()[y * w..(y + 1) * w];
        let mut x = 0;
        while x < w {
            if !row[x] {
                x += 1;
                continue;
            }
            let mut end = x;
            while end < w && row[end] {
                end += 1;
            }
            let mut s = x;
            while s < end {
                let take = (end - s).min(BLOCK_PIXELS - filled);
                current.push(Span {
                    start: y * w + s,
                    local: (y - window.y0) * window.width() + (s - window.x0),
                    len: take,
                });
                filled += take;
                s += take;
                if filled == BLOCK_PIXELS {
                    out.push(std::mem::take(&mut current));
                    filled = 0;
                }
            }
            x = end;
        }
    }
    if !current.is_empty() {
        out.push(current);
    }
    out
}

/// Per-block accumulators in structure-of-arrays form (one entry per block pixel).
#[derive(Default)]
struct Scratch {
    threshold: Vec<f32>,
    /// Unweighted Gram matrix of used directions: xx, xy, xz, yy, yz, zz.
    gram: [Vec<f32>; 6],
    /// Weighted normal matrix (same order); equals `gram` for plain least squares.
    a: [Vec<f32>; 6],
    /// Right-hand side.
    b: [Vec<f32>; 3],
    count: Vec<u32>,
    g: Vec<[f32; 3]>,
    ss: Vec<f32>,
    /// Σ r²/σ² over used samples (the fit-test statistic).
    chi2: Vec<f32>,
    /// Gathered samples of the block, [pixel][image], for the per-pixel estimators.
    values: Vec<f32>,
    /// Saturation flags, laid out as `values`.
    saturated: Vec<bool>,
}

impl Scratch {
    fn reset(&mut self, len: usize) {
        for v in self
            .gram
            .iter_mut()
            .chain(self.a.iter_mut())
            .chain(self.b.iter_mut())
            .chain([&mut self.ss, &mut self.chi2, &mut self.threshold])
        {
            v.clear();
            v.resize(len, 0.0);
        }
        self.count.clear();
        self.count.resize(len, 0);
        self.g.clear();
        self.g.resize(len, [f32::NAN; 3]);
    }
}

impl Scratch {
    /// Gathered samples and saturation flags of block pixel `i` (of `k` images).
    fn pixel(&self, i: usize, k: usize) -> (&[f32], &[bool]) {
        (
            &self.values[i * k..(i + 1) * k],
            &self.saturated[i * k..(i + 1) * k],
        )
    }
}

/// Output of one block, scattered into the solution grids afterwards.
struct BlockOut {
    spans: Vec<Span>,
    pixels: Vec<PixelSolution>,
}

/// Whether sample `pixel` of an image with saturation `bits` is clipped.
#[inline(always)]
fn sat_bit(bits: &[u64], pixel: usize) -> bool {
    bits[pixel / 64] >> (pixel % 64) & 1 == 1
}

/// Accumulator slices of one span (all of the span's length).
struct Acc<'a> {
    gram: [&'a mut [f32]; 6],
    a: [&'a mut [f32]; 6],
    b: [&'a mut [f32]; 3],
    count: &'a mut [u32],
}

/// Adds one image's samples `src` (pixels `start..start + src.len()`) with light `l` to the
/// normal equations of the span. `WEIGHTED`: weights v² (diag(I) rows); `SAT`: consult `bits`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn accumulate<const WEIGHTED: bool, const SAT: bool>(
    src: &[f32],
    gain: f32,
    thr: &[f32],
    bits: &[u64],
    start: usize,
    l: &[f32; 3],
    ll: &[f32; 6],
    acc: Acc,
) {
    let n = src.len();
    let Acc { gram, a, b, count } = acc;
    let [g0, g1, g2, g3, g4, g5] = gram;
    let [a0, a1, a2, a3, a4, a5] = a;
    let [b0, b1, b2] = b;
    let (thr, count) = (&thr[..n], &mut count[..n]);
    let (g0, g1, g2, g3, g4, g5) = (
        &mut g0[..n],
        &mut g1[..n],
        &mut g2[..n],
        &mut g3[..n],
        &mut g4[..n],
        &mut g5[..n],
    );
    let (a0, a1, a2, a3, a4, a5) = (
        &mut a0[..n],
        &mut a1[..n],
        &mut a2[..n],
        &mut a3[..n],
        &mut a4[..n],
        &mut a5[..n],
    );
    let (b0, b1, b2) = (&mut b0[..n], &mut b1[..n], &mut b2[..n]);
    for j in 0..n {
        let v = src[j] * gain;
        let ok = v > thr[j] && !(SAT && sat_bit(bits, start + j));
        let u = if ok { 1.0 } else { 0.0 };
        let vv = if ok { v } else { 0.0 };
        count[j] += u32::from(ok);
        g0[j] += u * ll[0];
        g1[j] += u * ll[1];
        g2[j] += u * ll[2];
        g3[j] += u * ll[3];
        g4[j] += u * ll[4];
        g5[j] += u * ll[5];
        let w = if WEIGHTED {
            let w = vv * vv;
            a0[j] += w * ll[0];
            a1[j] += w * ll[1];
            a2[j] += w * ll[2];
            a3[j] += w * ll[3];
            a4[j] += w * ll[4];
            a5[j] += w * ll[5];
            w
        } else {
            u
        };
        let wv = w * vv;
        b0[j] += wv * l[0];
        b1[j] += wv * l[1];
        b2[j] += wv * l[2];
    }
}

/// Adds squared residuals of one image's used samples to `ss`, and divided by the image's
/// noise variance (1/`inv_var`) to `chi2`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn residuals<const SAT: bool>(
    src: &[f32],
    gain: f32,
    inv_var: f32,
    thr: &[f32],
    bits: &[u64],
    start: usize,
    l: &[f32; 3],
    g: &[[f32; 3]],
    ss: &mut [f32],
    chi2: &mut [f32],
) {
    let n = src.len();
    let (thr, g, ss, chi2) = (&thr[..n], &g[..n], &mut ss[..n], &mut chi2[..n]);
    for j in 0..n {
        let v = src[j] * gain;
        let ok = v > thr[j] && !(SAT && sat_bit(bits, start + j));
        let e = v - (g[j][0] * l[0] + g[j][1] * l[1] + g[j][2] * l[2]);
        // Unsolved pixels have NaN g; their sum is discarded.
        let e2 = if ok { e * e } else { 0.0 };
        ss[j] += e2;
        chi2[j] += e2 * inv_var;
    }
}

/// The per-image data of a solve: light directions, gains and noise.
struct PerImage {
    dirs: Vec<[f32; 3]>,
    dirs64: Vec<Vector3<f64>>,
    gains: Vec<f32>,
    /// Noise of the samples before gains (NaN when unused).
    sigma: Vec<f32>,
    /// 1/(σ_k·gain_k)².
    inv_var: Vec<f32>,
}

#[allow(clippy::too_many_arguments)]
fn solve_block(
    stack: &ImageStack,
    channel: usize,
    per: &PerImage,
    rule: Rule,
    max_condition: f64,
    spans: &[Span],
    s: &mut Scratch,
) -> Vec<PixelSolution> {
    let len: usize = spans.iter().map(|sp| sp.len).sum();
    s.reset(len);
    s.threshold.fill(f32::NEG_INFINITY);
    // Pass 1: per-pixel threshold from the brightest finite sample.
    if rule.reject {
        for k in 0..stack.count() {
            let plane = stack.plane(k, channel);
            let mut off = 0;
            for sp in spans {
                let src = &plane[sp.local..sp.local + sp.len];
                let gain = per.gains[k];
                for (t, &v) in s.threshold[off..off + sp.len].iter_mut().zip(src) {
                    // NaN compares false and is skipped.
                    let v = v * gain;
                    *t = if v > *t { v } else { *t };
                }
                off += sp.len;
            }
        }
        for t in &mut s.threshold {
            *t = rule.threshold(*t);
        }
    }
    // Pass 2: accumulate the normal equations image by image.
    for (k, l) in per.dirs.iter().enumerate() {
        let gain = per.gains[k];
        let plane = stack.plane(k, channel);
        let bits = if rule.reject_saturated {
            stack.saturation_bits(k)
        } else {
            None
        };
        let ll = [
            l[0] * l[0],
            l[0] * l[1],
            l[0] * l[2],
            l[1] * l[1],
            l[1] * l[2],
            l[2] * l[2],
        ];
        let mut off = 0;
        for sp in spans {
            let src = &plane[sp.local..sp.local + sp.len];
            let r = off..off + sp.len;
            let [g0, g1, g2, g3, g4, g5] = &mut s.gram;
            let [a0, a1, a2, a3, a4, a5] = &mut s.a;
            let [b0, b1, b2] = &mut s.b;
            let acc = Acc {
                gram: [
                    &mut g0[r.clone()],
                    &mut g1[r.clone()],
                    &mut g2[r.clone()],
                    &mut g3[r.clone()],
                    &mut g4[r.clone()],
                    &mut g5[r.clone()],
                ],
                a: [
                    &mut a0[r.clone()],
                    &mut a1[r.clone()],
                    &mut a2[r.clone()],
                    &mut a3[r.clone()],
                    &mut a4[r.clone()],
                    &mut a5[r.clone()],
                ],
                b: [&mut b0[r.clone()], &mut b1[r.clone()], &mut b2[r.clone()]],
                count: &mut s.count[r.clone()],
            };
            let thr = &s.threshold[r];
            match (rule.intensity_weight, bits) {
                (true, Some(bits)) => {
                    accumulate::<true, true>(src, gain, thr, bits, sp.start, l, &ll, acc)
                }
                (true, None) => {
                    accumulate::<true, false>(src, gain, thr, &[], sp.start, l, &ll, acc)
                }
                (false, Some(bits)) => {
                    accumulate::<false, true>(src, gain, thr, bits, sp.start, l, &ll, acc)
                }
                (false, None) => {
                    accumulate::<false, false>(src, gain, thr, &[], sp.start, l, &ll, acc)
                }
            }
            off += sp.len;
        }
    }
    // Solve each pixel.
    let mut out = Vec::with_capacity(len);
    let mut cache = GramCache::new();
    for i in 0..len {
        let key = [0, 1, 2, 3, 4, 5].map(|q| s.gram[q][i]);
        let sym = |e: [f32; 6]| {
            let e = e.map(f64::from);
            Matrix3::new(e[0], e[1], e[2], e[1], e[3], e[4], e[2], e[4], e[5])
        };
        let gram = sym(key);
        let b = Vector3::new(
            f64::from(s.b[0][i]),
            f64::from(s.b[1][i]),
            f64::from(s.b[2][i]),
        );
        let n = s.count[i] as usize;
        let (condition, inverse) = if n >= MIN_SAMPLES {
            cache.get(key, &gram)
        } else {
            (f64::INFINITY, None)
        };
        let (g, condition, status) = finish_pixel(n, condition, max_condition, || {
            if rule.intensity_weight {
                solve_spd(sym([0, 1, 2, 3, 4, 5].map(|q| s.a[q][i])), b)
            } else {
                inverse.map(|m| m * b)
            }
        });
        if status == PixelStatus::Solved {
            s.g[i] = [g.x as f32, g.y as f32, g.z as f32];
        }
        out.push(PixelSolution {
            g,
            residual: f64::NAN,
            samples: n,
            condition,
            status,
            robust: false,
        });
    }
    // Pass 3: residuals over the used samples.
    for (k, l) in per.dirs.iter().enumerate() {
        let (gain, inv_var) = (per.gains[k], per.inv_var[k]);
        let plane = stack.plane(k, channel);
        let bits = if rule.reject_saturated {
            stack.saturation_bits(k)
        } else {
            None
        };
        let mut off = 0;
        for sp in spans {
            let src = &plane[sp.local..sp.local + sp.len];
            let r = off..off + sp.len;
            let (thr, g) = (&s.threshold[r.clone()], &s.g[r.clone()]);
            let (ss, chi2) = (&mut s.ss[r.clone()], &mut s.chi2[r]);
            match bits {
                Some(bits) => {
                    residuals::<true>(src, gain, inv_var, thr, bits, sp.start, l, g, ss, chi2)
                }
                None => residuals::<false>(src, gain, inv_var, thr, &[], sp.start, l, g, ss, chi2),
            }
            off += sp.len;
        }
    }
    for (i, p) in out.iter_mut().enumerate() {
        if p.status == PixelStatus::Solved {
            p.residual = (f64::from(s.ss[i]) / p.samples as f64).sqrt();
        }
    }
    out
}

/// Copies the block's samples into `s.values`/`s.saturated` as [pixel][image].
fn gather_block(stack: &ImageStack, channel: usize, spans: &[Span], s: &mut Scratch) {
    let k = stack.count();
    let len: usize = spans.iter().map(|sp| sp.len).sum();
    s.values.clear();
    s.values.resize(len * k, f32::NAN);
    s.saturated.clear();
    s.saturated.resize(len * k, false);
    for img in 0..k {
        let plane = stack.plane(img, channel);
        let bits = stack.saturation_bits(img);
        let mut i = 0;
        for sp in spans {
            for (p, &v) in (sp.start..).zip(&plane[sp.local..sp.local + sp.len]) {
                s.values[i * k + img] = v;
                s.saturated[i * k + img] = bits.is_some_and(|b| sat_bit(b, p));
                i += 1;
            }
        }
    }
}

/// Solves one block with the method of `options`.
fn solve_any_block(
    stack: &ImageStack,
    channel: usize,
    per: &PerImage,
    options: &SolveOptions,
    spans: &[Span],
    s: &mut Scratch,
) -> Vec<PixelSolution> {
    let k = stack.count();
    let method = options.method;
    if method.is_linear() || method == Method::Auto {
        let rule = Rule::new(method, options);
        let mut out = solve_block(stack, channel, per, rule, options.max_condition, spans, s);
        if method != Method::Auto {
            return out;
        }
        let escalated: Vec<usize> = (0..out.len())
            .filter(|&i| misfit(&out[i], f64::from(s.chi2[i]), options.fit_test_z))
            .collect();
        if escalated.is_empty() {
            return out;
        }
        gather_block(stack, channel, spans, s);
        let mut f = fitter(&per.dirs64, &per.gains, options);
        for i in escalated {
            let (v, sat) = s.pixel(i, k);
            out[i] = escalate(&mut f, v, sat, out[i], options);
        }
        return out;
    }
    gather_block(stack, channel, spans, s);
    let mut f = fitter(&per.dirs64, &per.gains, options);
    let len = s.values.len() / k.max(1);
    (0..len)
        .map(|i| {
            let (v, sat) = s.pixel(i, k);
            fit_with(&mut f, v, sat, &per.sigma, options)
        })
        .collect()
}

/// Per-image noise for the fit test: the user's σ, or the estimate of [`crate::ps::noise`] with
/// [`MODEL_TOLERANCE`] times the image's median signal as a floor.
pub(crate) fn test_sigmas(
    stack: &ImageStack,
    channel: usize,
    mask: &Mask,
    options: &SolveOptions,
) -> Vec<f32> {
    if let Some(s) = options.noise_sigma {
        return vec![s; stack.count()];
    }
    crate::ps::noise::stack_noise(stack, channel, mask)
        .into_iter()
        .map(|n| {
            let floor = if n.level.is_finite() {
                MODEL_TOLERANCE * n.level
            } else {
                f32::MIN_POSITIVE
            };
            if n.sigma.is_finite() {
                n.sigma.max(floor)
            } else {
                floor
            }
        })
        .collect()
}

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

/// The per-image noise of the fit test (NaN unless [`Method::Auto`]) and the intensity gains
/// (estimated when [`SolveOptions::recalibrates`], unit otherwise) for channel `channel`.
pub(crate) fn noise_and_gains(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
) -> (Vec<f32>, crate::ps::intensities::GainEstimate) {
    let k = stack.count();
    let sigma = if options.method == Method::Auto {
        test_sigmas(stack, channel, mask, options)
    } else {
        vec![f32::NAN; k]
    };
    let gains = if options.recalibrates(k) {
        crate::ps::intensities::estimate_gains_with(stack, channel, lights, mask, options, &sigma)
    } else {
        crate::ps::intensities::GainEstimate::unit(k)
    };
    (sigma, gains)
}

/// Checks that `model` has one entry per image.
pub(crate) fn check_model(model: &ImageModel, count: usize) -> Result<()> {
    if model.sigma.len() != count || model.gains.gains.len() != count {
        return Err(Error::param(
            "model",
            format!(
                "{} noise levels and {} gains for {count} images",
                model.sigma.len(),
                model.gains.gains.len()
            ),
        ));
    }
    Ok(())
}

/// What a solve estimates once over the whole capture before fitting pixels: each image's
/// noise σ (for [`Method::Auto`]'s fit test) and its intensity gain (when
/// [`SolveOptions::recalibrates`]). [`solve`] estimates it from the stack it is given; a solve
/// of the capture in parts ([`crate::run::stream`]) estimates it once, from a sample of rows, and
/// hands it to [`solve_with_model`] for every part, so that every part is fitted alike.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageModel {
    /// Noise σ per image (NaN when the method does not use it).
    pub sigma: Vec<f32>,
    /// Intensity gains per image (unit when not recalibrated).
    pub gains: crate::ps::intensities::GainEstimate,
}

impl ImageModel {
    /// Estimates the model of channel `channel` of `stack` over `mask`: noise σ per image for
    /// [`Method::Auto`] ([`crate::ps::noise`]), intensity gains when `options` recalibrates
    /// ([`crate::ps::intensities`]); NaN and unit gains otherwise.
    ///
    /// # Errors
    /// As [`solve`]: mismatched sizes or counts, invalid options.
    pub fn estimate(
        stack: &ImageStack,
        channel: usize,
        lights: &Lights,
        mask: &Mask,
        options: &SolveOptions,
    ) -> Result<Self> {
        check_inputs(stack, channel, lights, mask, options)?;
        let (sigma, gains) = noise_and_gains(stack, channel, lights, mask, options);
        Ok(ImageModel { sigma, gains })
    }

    /// Whether `options` needs a model estimated from the data for `count` images (otherwise
    /// [`ImageModel::unit`] is exact).
    pub fn needed(options: &SolveOptions, count: usize) -> bool {
        options.method == Method::Auto || options.recalibrates(count)
    }

    /// The model that needs no data: NaN σ, unit gains, for `count` images.
    pub fn unit(count: usize) -> Self {
        ImageModel {
            sigma: vec![f32::NAN; count],
            gains: crate::ps::intensities::GainEstimate::unit(count),
        }
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
/// ([`crate::run::stream`]).
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
    let ImageModel { sigma, gains } = model;
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
            let pixels = solve_any_block(stack, channel, &per, options, &spans, scratch);
            progress.advance(1);
            BlockOut { spans, pixels }
        })
        .collect();
    progress.end();
    let mut sol = Solution::empty(w, h, gains, sigma, options);
    for block in results {
        let mut pixels = block.pixels.into_iter();
        for sp in &block.spans {
            for p in sp.start..sp.start + sp.len {
                let Some(px) = pixels.next() else { break };
                sol.record(p, &px);
            }
        }
    }
    Ok(sol)
}

/// Counts of pixel outcomes in a [`Solution`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct StatusCounts {
    /// Pixels in the mask.
    pub masked: usize,
    /// Pixels solved.
    pub solved: usize,
    /// Pixels with fewer than 3 usable samples.
    pub too_few_samples: usize,
    /// Pixels whose used lights were ill-conditioned.
    pub ill_conditioned: usize,
    /// Pixels whose estimate was zero.
    pub dark: usize,
}

impl StatusCounts {
    /// Tallies a status grid.
    pub fn from_grid(status: &Grid<PixelStatus>) -> Self {
        let mut c = StatusCounts::default();
        for s in status.data() {
            match s {
                PixelStatus::Outside => continue,
                PixelStatus::Solved => c.solved += 1,
                PixelStatus::TooFewSamples => c.too_few_samples += 1,
                PixelStatus::IllConditioned => c.ill_conditioned += 1,
                PixelStatus::Dark => c.dark += 1,
            }
            c.masked += 1;
        }
        c
    }

    /// Adds the counts of another part of the image (a band of rows).
    pub fn add(&mut self, other: &StatusCounts) {
        self.masked += other.masked;
        self.solved += other.solved;
        self.too_few_samples += other.too_few_samples;
        self.ill_conditioned += other.ill_conditioned;
        self.dark += other.dark;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::Silent;
    use rand::{RngExt, SeedableRng};

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
        for opts in Method::ALL.map(|method| SolveOptions {
            method,
            recalibrate: Some(false),
            noise_sigma: Some(0.004),
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
