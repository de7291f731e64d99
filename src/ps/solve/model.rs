//! The image model: what is estimated once over the whole capture before any pixel is fitted —
//! each image's noise σ for the fit test and its intensity gain ([`ImageModel`]).

use super::*;

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

/// Checks that `model` has one entry per image and a usable lobe limit.
pub(crate) fn check_model(model: &ImageModel, count: usize) -> Result<()> {
    if let Some(l) = model.lobe_limit
        && !(l.is_finite() && l > 0.0)
    {
        return Err(Error::param(
            "model",
            format!("lobe limit {l} is not a finite relative residual > 0"),
        ));
    }
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
    /// [`Method::Auto`] with [`SolveOptions::lobes`]: the relative-residual limit above which a
    /// refit with specular lobes is declined ([`crate::ps::lobes`]), estimated on a sample of
    /// the capture's pixels; `None` when not estimated (a solve then takes it from its own
    /// pixels).
    pub lobe_limit: Option<f64>,
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
        let lobe_limit = (options.method == Method::Auto && options.lobes)
            .then(|| {
                crate::ps::lobes::estimate_limit(
                    stack,
                    channel,
                    lights,
                    mask,
                    options,
                    &sigma,
                    &gains.gains,
                )
            })
            .flatten();
        Ok(ImageModel {
            sigma,
            gains,
            lobe_limit,
        })
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
            lobe_limit: None,
        }
    }
}
