//! What a solve produces: per-pixel outcomes ([`PixelStatus`]), the solution maps of a channel
//! ([`Solution`]) and their counts ([`StatusCounts`]).

use super::*;

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
    /// Too few usable samples or ill-conditioned lights to be solved alone; g was filled in
    /// from the samples it has and its solved neighbours ([`crate::ps::fill`]).
    Filled,
}

impl PixelStatus {
    /// Whether the pixel has an estimate of g (solved from its own samples, or filled).
    pub fn has_normal(self) -> bool {
        matches!(self, PixelStatus::Solved | PixelStatus::Filled)
    }
}

/// Per-pixel result of one solve: g = ρN and its diagnostics.
#[derive(Debug, Clone)]
pub struct Solution {
    /// g = ρN per pixel; NaN where there is no estimate ([`PixelStatus::has_normal`]).
    pub g: Grid<Vector3<f32>>,
    /// RMS of I − g·l over the used samples; NaN where not solved. For a pixel refitted with
    /// specular lobes ([`crate::ps::lobes`]), the lobe model's weighted RMS residual.
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
    /// What the shadow labelling pass changed, when it ran
    /// ([`SolveOptions::shadow_labels`], [`crate::ps::shadows`]).
    pub shadow_labels: Option<crate::ps::shadows::ShadowSummary>,
    /// What the refit with specular lobes did, when it ran ([`SolveOptions::lobes`],
    /// [`crate::ps::lobes`]).
    pub lobes: Option<crate::ps::lobes::LobeSummary>,
    /// The light in attached shadows and the bias it predicts ([`crate::ps::ambient`]).
    pub shadow_light: Option<crate::ps::ambient::ShadowLight>,
    /// Each light checked against the others ([`crate::ps::light_agreement`]).
    pub light_agreement: Option<crate::ps::light_agreement::LightAgreement>,
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
            shadow_labels: None,
            lobes: None,
            shadow_light: None,
            light_agreement: None,
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
        if let Some(b) = &band.shadow_labels {
            self.shadow_labels.get_or_insert_default().add(b);
        }
        if let Some(b) = &band.lobes {
            self.lobes.get_or_insert_default().add(b);
        }
        if let Some(b) = &band.shadow_light {
            self.shadow_light.get_or_insert_default().add(b);
        }
        if let Some(b) = &band.light_agreement {
            self.light_agreement.get_or_insert_default().add(b);
        }
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
            shadow_labels: self.shadow_labels,
            lobes: self.lobes,
            shadow_light: self.shadow_light.clone(),
            light_agreement: self.light_agreement.clone(),
        }
    }

    /// Pixel `p` (row-major index) when it is inside `mask` and solved, with a finite g ≠ 0:
    /// its index in `stack`'s window, its albedo ρ = |g| and its unit normal g/ρ (as the
    /// passes that run after a solve read it).
    pub(crate) fn solved_pixel(
        &self,
        stack: &crate::capture::stack::ImageStack,
        mask: &crate::grid::Mask,
        p: usize,
    ) -> Option<(usize, f64, Vector3<f64>)> {
        if !mask.data()[p] || self.status.data()[p] != PixelStatus::Solved {
            return None;
        }
        let local = stack.local(p)?;
        let g = self.g.data()[p].cast::<f64>();
        let rho = g.norm();
        (rho.is_finite() && rho > 0.0).then(|| (local, rho, g / rho))
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

/// Counts of pixel outcomes in a [`Solution`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, serde::Deserialize)]
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
    /// Pixels filled in from their few samples and their solved neighbours (not counted in
    /// `solved`, `too_few_samples` or `ill_conditioned`).
    pub filled: usize,
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
                PixelStatus::Filled => c.filled += 1,
            }
            c.masked += 1;
        }
        c
    }

    /// Adds the counts of another part of the image (a band of rows), each saturating at
    /// `usize::MAX` (which counts of one image's pixels cannot reach; counts read from
    /// elsewhere are added with [`Self::try_add`], which says when they overflow).
    pub fn add(&mut self, other: &StatusCounts) {
        self.masked = self.masked.saturating_add(other.masked);
        self.solved = self.solved.saturating_add(other.solved);
        self.too_few_samples = self.too_few_samples.saturating_add(other.too_few_samples);
        self.ill_conditioned = self.ill_conditioned.saturating_add(other.ill_conditioned);
        self.dark = self.dark.saturating_add(other.dark);
        self.filled = self.filled.saturating_add(other.filled);
    }

    /// [`Self::add`], or `None` (and `self` unchanged) when a count overflows.
    pub fn try_add(&mut self, other: &StatusCounts) -> Option<()> {
        *self = StatusCounts {
            masked: self.masked.checked_add(other.masked)?,
            solved: self.solved.checked_add(other.solved)?,
            too_few_samples: self.too_few_samples.checked_add(other.too_few_samples)?,
            ill_conditioned: self.ill_conditioned.checked_add(other.ill_conditioned)?,
            dark: self.dark.checked_add(other.dark)?,
            filled: self.filled.checked_add(other.filled)?,
        };
        Some(())
    }

    /// Pixels of the mask without an estimate of g.
    pub fn unsolved(&self) -> usize {
        // Saturating: counts added up from parts (`crate::run::CaptureChecks`) may be built by
        // hand.
        self.too_few_samples
            .saturating_add(self.ill_conditioned)
            .saturating_add(self.dark)
    }
}
