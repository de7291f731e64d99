//! The fit of one pixel: the shadow rule that picks its samples, the estimator ladder (least
//! squares, then the robust fit where the residuals fail the Lambertian fit test) and the
//! per-pixel result ([`PixelSolution`]).

use super::*;

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
pub(super) struct Rule {
    /// Threshold and saturation rejection applies.
    pub(super) reject: bool,
    /// Rows weighted by I (normal equations by I²).
    pub(super) intensity_weight: bool,
    pub(super) relative: f32,
    pub(super) highlight_fraction: f32,
    pub(super) reject_saturated: bool,
}

impl Rule {
    /// The rule of a linear `method` (any other method uses the threshold rule).
    pub(super) fn new(method: Method, o: &SolveOptions) -> Self {
        let reject = method != Method::LeastSquares;
        Rule {
            reject,
            intensity_weight: method == Method::ShadowWeighted,
            relative: o.shadow_threshold,
            highlight_fraction: o.highlight_fraction,
            reject_saturated: reject && o.reject_saturated,
        }
    }

    /// Samples must exceed this, given the pixel's reference level; NaN never does.
    pub(super) fn threshold(&self, reference: f32) -> f32 {
        if self.reject {
            (self.relative * reference).max(0.0)
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
        options.highlight_fraction,
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
            // The same samples again: their reference level is already known.
            escalate(
                f,
                values,
                saturated,
                p,
                options,
                Reference::Exact(f.reference()),
            )
        }
        _ => match options.estimator() {
            Some(e) => f.fit(values, saturated, e),
            None => f.fit(values, saturated, plain(true, false)),
        },
    }
}

/// Whether a Lambertian fit `p` with residual statistic `chi2` fails the fit test at
/// standard-normal deviate `z` (unsolved pixels always do).
pub(super) fn misfit(p: &PixelSolution, chi2: f64, z: f64) -> bool {
    if p.status != PixelStatus::Solved {
        return true;
    }
    let dof = p.samples.saturating_sub(MIN_SAMPLES);
    dof > 0 && chi2 > chi2_upper_quantile(dof as f64, z)
}

/// Refits a pixel that failed the fit test with the robust estimator; keeps the Lambertian
/// fit `lambertian` when the robust one cannot solve the pixel. `reference`: what is known of
/// the pixel's shadow-threshold reference level ([`PixelFitter::fit_with_reference`]).
pub(super) fn escalate(
    f: &mut PixelFitter,
    values: &[f32],
    saturated: &[bool],
    lambertian: PixelSolution,
    options: &SolveOptions,
    reference: Reference,
) -> PixelSolution {
    let Some(estimator) = options.estimator() else {
        return lambertian;
    };
    let q = f.fit_with_reference(values, saturated, estimator, reference);
    if q.status == PixelStatus::Solved || lambertian.status != PixelStatus::Solved {
        q
    } else {
        // Restore the fitter's weights to the fit that is returned.
        let plain = Estimator::Plain {
            reject: true,
            intensity_weight: false,
        };
        let reference = Reference::Exact(f.reference());
        f.fit_with_reference(values, saturated, plain, reference)
    }
}

/// Decides a pixel's outcome: too few samples, ill-conditioned (by the condition number of its
/// used directions, computed by the caller), or solved by `solve`.
pub(super) fn finish_pixel(
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
