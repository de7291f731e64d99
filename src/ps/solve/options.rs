//! What a solve is asked to do: the estimator ([`Method`]) and its parameters ([`SolveOptions`]),
//! with their defaults.

use super::*;

/// Fewest usable samples that determine g (three unknowns).
pub const MIN_SAMPLES: usize = 3;
/// Default limit on the condition number of a pixel's used light directions.
pub const DEFAULT_MAX_CONDITION: f64 = 100.0;
/// Default shadow threshold, as a fraction of the pixel's reference level (its brightest
/// usable sample once the brightest [`DEFAULT_HIGHLIGHT_FRACTION`] are set aside).
pub const DEFAULT_SHADOW_THRESHOLD: f32 = 0.1;
/// Default fraction of a pixel's usable samples set aside, brightest first, before its
/// brightest remaining sample becomes the reference of the shadow threshold: a specular
/// highlight can be tens of times the diffuse level, and a threshold relative to it drops the
/// diffuse samples the fit needs. Chosen on rendered glossy scenes (`bench specularity`,
/// Blinn–Phong and Torrance–Sparrow, k_s up to 0.8, 12, 32 and 96 lights): the smallest
/// fraction at which the error stops falling for every light count (`docs/photometric-stereo.md`).
pub const DEFAULT_HIGHLIGHT_FRACTION: f32 = 0.1;
/// Default standard-normal deviate of the automatic method's χ² test: a pixel is refitted when
/// its Lambertian residual would occur by noise alone with probability below 0.1%.
pub const DEFAULT_FIT_TEST_Z: f64 = 3.09;
/// Smallest noise level the fit test assumes, relative to an image's median signal: no real
/// surface follows Lambert's law closer than this, so exact synthetic data is not "misfit".
pub const MODEL_TOLERANCE: f32 = 1e-3;

/// The rank, counted from 1 at the brightest, of the sample that sets the shadow threshold's
/// reference among `usable` samples when a fraction `highlight_fraction` of them may be
/// highlights: ⌈f·n⌉, at least 1 (and at most `usable` when there are any).
pub fn reference_rank(usable: usize, highlight_fraction: f32) -> usize {
    // In f32, where the fraction was given: 0.1·10 is 1, not the 1.000000015 of its f64 image.
    let r = (highlight_fraction * usable as f32).ceil() as usize;
    r.clamp(1, usable.max(1))
}

/// A key whose unsigned order is the numeric order of the non-NaN `x` (−0 just below +0), so
/// that order statistics are selected with integer comparisons.
#[inline(always)]
fn order_key(x: f64) -> u64 {
    let bits = x.to_bits();
    if bits >> 63 == 1 {
        !bits
    } else {
        bits | 1 << 63
    }
}

/// The value whose [`order_key`] is `key`.
#[inline(always)]
fn from_order_key(key: u64) -> f64 {
    f64::from_bits(if key >> 63 == 1 {
        key & !(1 << 63)
    } else {
        !key
    })
}

/// The reference level of a pixel whose usable samples are given as [`order_key`]s in `keys`
/// (reordered): its [`reference_rank`]-th brightest sample; `None` without usable samples.
fn reference_level(keys: &mut [u64], highlight_fraction: f32) -> Option<f64> {
    let n = keys.len();
    if n == 0 {
        return None;
    }
    Some(nth_largest(keys, reference_rank(n, highlight_fraction)))
}

/// What is known of a pixel's shadow-threshold reference level (its [`reference_rank`]-th
/// brightest usable sample) before the per-pixel fitter forms it over the exact products
/// f64(I)·f64(gain) of its samples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Reference {
    /// Nothing: the fitter selects it.
    Unknown,
    /// The level itself (from an earlier fit of the same samples).
    Exact(f64),
    /// The level over the f32 products I·gain, as the block kernel forms it: the exact level
    /// rounded to f32.
    Rounded(f32),
}

impl Reference {
    /// The exact reference level of a pixel with samples `values` (before the per-image
    /// `gains`; NaN: missing) and saturation flags `saturated`: the [`reference_rank`]-th
    /// brightest of its usable samples (finite, and unclipped when `reject_saturated`); −∞
    /// without usable samples. `keys` is scratch.
    ///
    /// From [`Reference::Rounded`] no selection is needed: a product of two f32 is exact in
    /// f64 and rounding to f32 is monotone, so the exact level is among the samples whose f32
    /// product equals the rounded level (almost always one), at the rank left once those above
    /// it are counted. When the two precisions disagree on which samples are usable (an f32
    /// overflow), or the rounded level does not fit the samples, the level is selected.
    pub(crate) fn level(
        self,
        values: &[f32],
        saturated: &[bool],
        gains: &[f32],
        reject_saturated: bool,
        highlight_fraction: f32,
        keys: &mut Vec<u64>,
    ) -> f64 {
        let k = values.len();
        let (saturated, gains) = (&saturated[..k], &gains[..k]);
        let rounded = match self {
            Reference::Exact(level) => return level,
            Reference::Rounded(level) => level,
            Reference::Unknown => {
                keys.clear();
                keys.resize(k, 0);
                // Branch-free compaction: each key is written and kept when usable.
                let mut n = 0;
                for j in 0..k {
                    let x = f64::from(values[j]) * f64::from(gains[j]);
                    keys[n] = order_key(x);
                    n += usize::from(x.is_finite() && !(reject_saturated && saturated[j]));
                }
                return reference_level(&mut keys[..n], highlight_fraction)
                    .unwrap_or(f64::NEG_INFINITY);
            }
        };
        // One pass of counts and extremes, without stores: the samples usable (in f64), those
        // whose f32 product is above the rounded level and those equal to it (the ties, among
        // which the exact level is), the largest and smallest tie, and the samples on which
        // the two precisions disagree about finiteness.
        let (mut usable, mut above, mut ties, mut disagree) = (0u32, 0u32, 0u32, 0u32);
        let (mut tie_max, mut tie_min) = (f64::NEG_INFINITY, f64::INFINITY);
        for j in 0..k {
            let (v, g) = (values[j], gains[j]);
            let (x, y) = (f64::from(v) * f64::from(g), v * g);
            let ok = x.is_finite() & !(reject_saturated & saturated[j]);
            disagree += u32::from(x.is_finite() != y.is_finite());
            usable += u32::from(ok);
            above += u32::from(ok & (y > rounded));
            let tie = ok & (y == rounded);
            ties += u32::from(tie);
            tie_max = if tie & (x > tie_max) { x } else { tie_max };
            tie_min = if tie & (x < tie_min) { x } else { tie_min };
        }
        let (usable, above, ties) = (usable as usize, above as usize, ties as usize);
        let rank = reference_rank(usable, highlight_fraction);
        if usable == 0 {
            return f64::NEG_INFINITY;
        }
        if disagree == 0 && above < rank && rank - above <= ties {
            // The (rank − above)-th largest tie. The largest or the smallest covers every tie
            // of one or two samples; a longer one, in the middle, is selected below.
            if rank - above == 1 {
                return tie_max;
            }
            if rank - above == ties {
                return tie_min;
            }
        }
        Reference::Unknown.level(
            values,
            saturated,
            gains,
            reject_saturated,
            highlight_fraction,
            keys,
        )
    }
}

/// The `rank`-th largest (counted from 1, at most `keys.len()`) of the values whose
/// [`order_key`]s are `keys` (reordered).
fn nth_largest(keys: &mut [u64], rank: usize) -> f64 {
    let n = keys.len();
    let (_, &mut key, _) = keys.select_nth_unstable(n - rank);
    from_order_key(key)
}

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
    pub(super) fn is_linear(self) -> bool {
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
    /// reference level (and all samples ≤ 0) are treated as shadowed and dropped. The reference
    /// is the ⌈f·n⌉-th brightest of the pixel's n usable samples (finite, and not dropped as
    /// saturated), f = [`SolveOptions::highlight_fraction`]: see [`reference_rank`].
    pub shadow_threshold: f32,
    /// Fraction f of a pixel's usable samples that may be highlights and so do not set the
    /// shadow threshold's reference (0: the brightest usable sample is the reference).
    pub highlight_fraction: f32,
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
    /// Fill the pixels too poorly determined to be solved alone from their samples and their
    /// solved neighbours ([`crate::ps::fill`]), marked [`PixelStatus::Filled`]; `false` (strict)
    /// leaves them without a normal.
    pub fill: bool,
    /// After the solve, label shadows as regions and refit from the labels
    /// ([`crate::ps::shadows`]); `None` (the default): off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shadow_labels: Option<crate::ps::shadows::ShadowLabelOptions>,
    /// [`Method::Auto`]: refit the pixels that fail the Lambertian fit test with a diffuse term
    /// plus specular lobes and keep the refit where it explains them ([`crate::ps::lobes`]);
    /// default on.
    pub lobes: bool,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            method: Method::default(),
            shadow_threshold: DEFAULT_SHADOW_THRESHOLD,
            highlight_fraction: DEFAULT_HIGHLIGHT_FRACTION,
            reject_saturated: true,
            max_condition: DEFAULT_MAX_CONDITION,
            trim_low: DEFAULT_TRIM_LOW,
            trim_high: DEFAULT_TRIM_HIGH,
            specular_cone_deg: DEFAULT_SPECULAR_CONE_DEG,
            min_lit_cosine: DEFAULT_MIN_LIT_COSINE,
            recalibrate: None,
            noise_sigma: None,
            fit_test_z: DEFAULT_FIT_TEST_Z,
            fill: true,
            shadow_labels: None,
            lobes: true,
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
        if !(0.0..0.5).contains(&self.highlight_fraction) {
            return Err(Error::param(
                "highlight-fraction",
                format!("{} is outside [0, 0.5)", self.highlight_fraction),
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
        if let Some(labels) = &self.shadow_labels {
            labels.validate()?;
        }
        Ok(())
    }

    /// The robust estimator of a robust method; `None` for the linear ones.
    pub(super) fn estimator(&self) -> Option<Estimator> {
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
