//! Light where no lamp shines: the level of the samples in attached shadow, and how far such an
//! offset bends the normals.
//!
//! Lambert's law, I_k = ρ max(0, n·l_k), gives 0 wherever a surface faces away from lamp k.
//! Light that every image shares — the room's light, a camera's black level, a screen's glow —
//! adds the same a·ρ (ambient light, reflected by the surface) or b (a black level) to every
//! sample instead, and the least-squares fit takes it for a brighter surface turned towards
//! the mean of its lit lights: the normals flatten. Photometric stereo has no term for it; the
//! remedy is an image taken with every lamp off, subtracted from every image
//! ([`crate::capture::stack::load_stack_with_ambient`]).
//!
//! **Measured** after every distant-light solve: over the solved pixels, the samples whose
//! lamp the solved normal faces away from by a margin (n·l < −[`ATTACHED_MARGIN`], so that
//! a normal error of several degrees does not count a lit sample), divided by the pixel's
//! albedo: the fraction of a lit, facing surface's brightness that arrives without a lamp.
//! Each pixel with at least two such samples gives their median, and the capture's level is
//! the median of those over the pixels (a histogram of fixed bins, so that the bands of a
//! streamed run add up).
//!
//! **What it bends.** An offset a·ρ on every lit sample moves the least-squares g by
//! a·ρ (LᵀL)⁻¹ Lᵀ1 over the pixel's lit lights L, so the normal turns by about
//! a·|((LᵀL)⁻¹Lᵀ1)⊥n|, the part of that vector across the normal (first order in a; the
//! albedo cancels). Its mean over the pixels times the level is the report's predicted bias.
//! On rendered scenes (sphere, bust, relief and torus under 8, 16 and 48 lights, ambient 0.02,
//! 0.05 and 0.1, 0.5% noise) the level came out 1–13% under the ambient term (the solved
//! albedo holds the offset's share too, more so the larger it is) and the predicted bias
//! 10–30% under the error the ambient term added; the median over the pixels is robust to the
//! few whose attached shadows hold interreflected light.
//!
//! **Where it breaks.** Interreflections and subsurface scattering also light attached
//! shadows, and only where the surface sees itself: the level then says that light reaches
//! the shadows, not where from, and subtracting it would be wrong (DiLiGenT cat, bear and
//! reading: 1.3%, 1.8% and 2.5%, where a subtraction made every object worse). So the run
//! reports it and warns when the predicted bias is large; it never subtracts it on its own.
//! A normal wrong by more than the margin puts lit samples among the shadowed ones.

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::grid::Mask;
use crate::ps::solve::Solution;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// A sample counts as in attached shadow where n·l < −`ATTACHED_MARGIN` (about 11.5° beyond
/// the terminator).
pub const ATTACHED_MARGIN: f64 = 0.2;

/// A light counts as lighting a pixel, for the predicted bias, where n·l > this.
const LIT: f64 = 0.05;

/// A pixel's lever is capped at this (a pixel whose lit lights barely span three dimensions
/// would otherwise weigh in the mean without bound; the solve leaves such pixels unsolved or
/// fills them, but its set of lights is not exactly this one).
const LEVER_CAP: f64 = 10.0;

/// Levers are summed in fixed point, units of 2⁻³² (exact and in any order, so that the
/// bands of a streamed run add up to the whole whatever their heights).
const LEVER_UNIT: f64 = 4_294_967_296.0;

/// Fewest pixels with shadowed samples from which a level is stated (with its standard error,
/// which says how far to trust it).
pub const MIN_PIXELS: usize = 20;

/// Histogram bins of the per-pixel levels: [`LEVEL_LOW`, `LEVEL_HIGH`) in steps of
/// [`LEVEL_STEP`] (levels outside are counted in the end bins).
const LEVEL_LOW: f64 = -0.25;
const LEVEL_HIGH: f64 = 1.0;
const LEVEL_STEP: f64 = 0.0005;
const BINS: usize = ((LEVEL_HIGH - LEVEL_LOW) / LEVEL_STEP) as usize;

/// The light in a solve's attached shadows, summable over the row bands of a streamed run.
#[derive(Clone, PartialEq, Serialize)]
pub struct ShadowLight {
    /// Pixels with at least two samples in attached shadow.
    pub pixels: usize,
    /// The median over those pixels of their shadowed samples' median level, as a fraction of
    /// the pixel's albedo (of a lit surface's brightness facing a unit lamp); `None` with fewer
    /// than [`MIN_PIXELS`] pixels.
    pub level: Option<f64>,
    /// The level's standard error: 1.2533 σ/√pixels, the median's, with σ the per-pixel
    /// levels' spread (their interquartile range over 1.349).
    pub level_se: Option<f64>,
    /// The mean angle (degrees) by which an offset of `level` turns the least-squares normals
    /// of the solved pixels ([`crate::ps::ambient`]); `None` with no level.
    pub predicted_bias_deg: Option<f64>,
    /// Per-pixel levels, by bin.
    #[serde(skip)]
    histogram: Vec<u32>,
    /// Σ over the pixels with three lit lights of |((LᵀL)⁻¹Lᵀ1)⊥n| (capped at [`LEVER_CAP`],
    /// in units of 1/[`LEVER_UNIT`]), and their count.
    #[serde(skip)]
    lever: (u128, usize),
}

impl std::fmt::Debug for ShadowLight {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ShadowLight")
            .field("pixels", &self.pixels)
            .field("level", &self.level)
            .field("level_se", &self.level_se)
            .field("predicted_bias_deg", &self.predicted_bias_deg)
            .finish_non_exhaustive()
    }
}

impl Default for ShadowLight {
    fn default() -> Self {
        ShadowLight {
            pixels: 0,
            level: None,
            level_se: None,
            predicted_bias_deg: None,
            histogram: vec![0; BINS],
            lever: (0, 0),
        }
    }
}

/// Most pixels a part's counts may hold ([`ShadowLight::from_counts`]).
const PART_LIMIT: usize = 1 << 48;

/// The counts a [`ShadowLight`] is judged from, which add up over the parts of a capture (for
/// [`crate::run::checks`]).
#[derive(Serialize, Deserialize)]
pub(crate) struct ShadowLightCounts {
    pixels: usize,
    histogram: Vec<u32>,
    lever: (u128, usize),
}

impl ShadowLight {
    /// Its counts, to be added to another part's.
    pub(crate) fn counts(&self) -> ShadowLightCounts {
        ShadowLightCounts {
            pixels: self.pixels,
            histogram: self.histogram.clone(),
            lever: self.lever,
        }
    }

    /// The measurement the counts give; `None` when they are not of this build's histogram,
    /// or not the counts of a measurement (the pixels are the histogram's total; a part holds
    /// at most 2⁴⁸ pixels, so that any number of parts a machine can hold adds up in range).
    pub(crate) fn from_counts(counts: ShadowLightCounts) -> Option<ShadowLight> {
        let total: u64 = counts.histogram.iter().map(|&c| u64::from(c)).sum();
        if counts.histogram.len() != BINS
            || total != counts.pixels as u64
            || counts.pixels > PART_LIMIT
            || counts.lever.1 > PART_LIMIT
            || counts.lever.0 > (PART_LIMIT as u128) << 40
        {
            return None;
        }
        let mut out = ShadowLight {
            pixels: counts.pixels,
            histogram: counts.histogram,
            lever: counts.lever,
            ..ShadowLight::default()
        };
        out.finish();
        Some(out)
    }

    /// Adds another part's counts, `None` (and nothing added) where a count would overflow.
    pub(crate) fn try_add(&mut self, other: &ShadowLight) -> Option<()> {
        let pixels = self.pixels.checked_add(other.pixels)?;
        let histogram = self
            .histogram
            .iter()
            .zip(&other.histogram)
            .map(|(a, b)| a.checked_add(*b))
            .collect::<Option<Vec<u32>>>()?;
        let lever = (
            self.lever.0.checked_add(other.lever.0)?,
            self.lever.1.checked_add(other.lever.1)?,
        );
        pixels.checked_mul(3)?;
        self.pixels = pixels;
        self.histogram = histogram;
        self.lever = lever;
        self.finish();
        Some(())
    }

    /// Adds another band's counts and updates the level and bias: [`Self::try_add`], whose
    /// overflow the bands of one capture in memory cannot reach; were it reached, the total
    /// would stay as it was.
    pub(crate) fn add(&mut self, other: &ShadowLight) {
        let _ = self.try_add(other);
    }

    /// The level (the histogram's median, at its bin's centre), its standard error and the
    /// bias from the counts.
    fn finish(&mut self) {
        self.level = None;
        self.level_se = None;
        self.predicted_bias_deg = None;
        if self.pixels < MIN_PIXELS {
            return;
        }
        let (q1, median, q3) = (
            self.quantile(self.pixels / 4),
            self.quantile(self.pixels / 2),
            self.quantile(3 * self.pixels / 4),
        );
        self.level = Some(median);
        // The spread of the per-pixel levels, at least a bin.
        let sigma = ((q3 - q1) / 1.349).max(LEVEL_STEP);
        self.level_se = Some(1.2533 * sigma / (self.pixels as f64).sqrt());
        self.predicted_bias_deg = self.bias_deg(median);
    }

    /// The per-pixel level of rank `rank` (from 0), at its bin's centre.
    fn quantile(&self, rank: usize) -> f64 {
        let mut seen = 0usize;
        for (bin, &c) in self.histogram.iter().enumerate() {
            seen += c as usize;
            if seen > rank {
                return LEVEL_LOW + (bin as f64 + 0.5) * LEVEL_STEP;
            }
        }
        LEVEL_HIGH
    }

    /// The mean angle (degrees) by which an offset of `level` (a fraction of the albedo) turns
    /// the solved pixels' least-squares normals, to first order: atan(|level| × the mean lever).
    /// It leans high a little (it leaves out the offset's share along the normal, 1 + a·n·d in
    /// the denominator, and takes the angle of the mean rather than the mean of the angles);
    /// measured, it fell 10–30% under the error an ambient term added, the offset also moving
    /// which samples the fit keeps. `None` when no pixel had three lit lights.
    pub fn bias_deg(&self, level: f64) -> Option<f64> {
        (self.lever.1 > 0).then(|| {
            let lever = self.lever.0 as f64 / LEVER_UNIT / self.lever.1 as f64;
            (level.abs() * lever).atan().to_degrees()
        })
    }

    /// The bias at the level's end nearer to zero of its two-standard-error interval (0 when
    /// the interval holds zero): what the data show at least.
    pub fn confident_bias_deg(&self) -> Option<f64> {
        let (level, se) = (self.level?, self.level_se?);
        self.bias_deg((level.abs() - 2.0 * se).max(0.0))
    }
}

/// The bin of a per-pixel level.
fn bin(level: f64) -> usize {
    (((level - LEVEL_LOW) / LEVEL_STEP).floor().max(0.0) as usize).min(BINS - 1)
}

/// Measures the light in attached shadows of channel `channel` of `stack` under `lights` and
/// the solution `sol` of that channel (its solved pixels inside `mask`): see the module
/// documentation. The samples are taken as the solve used them, times the solution's gains.
/// The caller has checked that the stack, lights, mask and solution agree (the solve's
/// inputs).
pub(crate) fn measure(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    sol: &Solution,
) -> ShadowLight {
    let dirs = lights.directions();
    let gains = &sol.gains.gains;
    let width = mask.width();
    // Per row: the bins of its pixels' levels, and its Σ and count of levers.
    let rows: Vec<(Vec<u32>, u128, usize)> = (0..mask.height())
        .into_par_iter()
        .map(|y| {
            let mut bins = Vec::new();
            let (mut lever, mut levered) = (0u128, 0usize);
            let mut shadowed: Vec<f64> = Vec::with_capacity(dirs.len());
            for x in 0..width {
                let p = y * width + x;
                let Some((local, rho, n)) = sol.solved_pixel(stack, mask, p) else {
                    continue;
                };
                shadowed.clear();
                let mut m = Matrix3::zeros();
                let mut v = Vector3::zeros();
                let mut lit = 0usize;
                for (k, l) in dirs.iter().enumerate() {
                    let nl = n.dot(l);
                    if nl < -ATTACHED_MARGIN {
                        let value = f64::from(stack.plane(k, channel)[local]);
                        if value.is_finite() && !stack.is_saturated(k, p) {
                            shadowed.push(value * f64::from(gains[k]) / rho);
                        }
                    } else if nl > LIT {
                        m += l * l.transpose();
                        v += l;
                        lit += 1;
                    }
                }
                if shadowed.len() >= 2 {
                    // The median; of an even count, the mean of the middle two (the upper
                    // one alone, the larger of two samples, would be biased upwards by the
                    // noise).
                    let (count, mid) = (shadowed.len(), shadowed.len() / 2);
                    let (low, upper, _) = shadowed.select_nth_unstable_by(mid, f64::total_cmp);
                    let upper = *upper;
                    let level = if count % 2 == 0 {
                        let lower = low.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                        0.5 * (lower + upper)
                    } else {
                        upper
                    };
                    bins.push(bin(level) as u32);
                }
                if lit >= 3
                    && let Some(inv) = m.try_inverse()
                {
                    let d = inv * v;
                    let across = (d - n * n.dot(&d)).norm();
                    if across.is_finite() {
                        lever += (across.min(LEVER_CAP) * LEVER_UNIT).round() as u128;
                        levered += 1;
                    }
                }
            }
            (bins, lever, levered)
        })
        .collect();
    // Integer sums: the result depends neither on the threads nor on the bands.
    let mut out = ShadowLight::default();
    for (bins, lever, levered) in rows {
        for b in &bins {
            out.histogram[*b as usize] += 1;
        }
        out.pixels += bins.len();
        out.lever.0 += lever;
        out.lever.1 += levered;
    }
    out.finish();
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::metrics::angular_errors;
    use crate::ps::test_support::{band, rendered_and_solved, sphere_for_bands};
    use crate::synth::reflectance::Material;
    use crate::synth::render::RenderOptions;
    use crate::synth::scene::{Albedo, SceneKind};

    /// Renders `kind` at 96² under 16 lights with ambient term `ambient` and 0.5% noise,
    /// solves it with the defaults, and returns what [`measure`] finds and the mean normal
    /// error.
    fn measured(kind: SceneKind, ambient: f32) -> (ShadowLight, f64) {
        let scene = kind.build(96, Albedo::Constant(0.7), Material::lambertian());
        let lights = Lights::fibonacci(16, 25.0).unwrap();
        let options = RenderOptions {
            noise_sigma: 0.005,
            ambient,
            seed: 5,
            ..RenderOptions::default()
        };
        let (r, _, sol) = rendered_and_solved(&scene, &lights, &lights, &options);
        let mask = &r.truth.mask;
        let normals = crate::ps::normals::albedo_and_normals(&sol).1;
        let error = angular_errors(&normals, &r.truth.normals, mask)
            .unwrap()
            .mean_deg;
        (sol.shadow_light.clone().unwrap(), error)
    }

    /// The level is the ambient term (about 0 without one; at most 15% under it, since the
    /// solved albedo holds the offset's share too), and the bias it predicts is what the
    /// ambient term adds to the normals' error, within a factor 2, on a sphere and on a relief
    /// of dimples and bumps on a plane.
    #[test]
    fn the_level_is_the_ambient_light_and_its_bias_what_it_costs() {
        for kind in [SceneKind::Sphere, SceneKind::Relief] {
            let (dark, base) = measured(kind, 0.0);
            let level = dark.level.unwrap();
            assert!(level.abs() < 0.002, "{kind:?}: {dark:?}");
            assert!(dark.predicted_bias_deg.unwrap() < 0.1, "{kind:?}: {dark:?}");
            for ambient in [0.05, 0.1] {
                let (lit, error) = measured(kind, ambient);
                let level = lit.level.unwrap();
                let a = f64::from(ambient);
                let added = error - base;
                let bias = lit.predicted_bias_deg.unwrap();
                println!(
                    "{kind:?} ambient {a}: level {level:.4} over {} pixels, predicted {bias:.2}°, added {added:.2}°",
                    lit.pixels
                );
                assert!(
                    level > 0.85 * a && level < 1.02 * a,
                    "{kind:?} ambient {ambient}: {lit:?}"
                );
                assert!(
                    bias > 0.5 * added && bias < 2.0 * added,
                    "{kind:?} ambient {ambient}: predicted {bias:.2}°, added {added:.2}° ({base:.2}° → {error:.2}°)"
                );
            }
        }
    }

    /// Measured in two bands of rows and added, the summary is the whole's, bit for bit (the
    /// histogram and the fixed-point levers add exactly); too few shadowed pixels state no
    /// level.
    #[test]
    fn bands_add_up_to_the_whole() {
        let lights = Lights::fibonacci(12, 25.0).unwrap();
        let (mask, stack, sol) = sphere_for_bands(&lights, 0.05);
        let mask = &mask;
        let whole = measure(&stack, 0, &lights, mask, &sol);
        let split = |y0, y1| measure(&stack, 0, &lights, &band(mask, y0, y1), &sol);
        let (top, bottom) = (split(0, 30), split(30, 64));
        assert!(top.pixels > 0 && bottom.pixels > 0);
        let mut sum = top.clone();
        sum.add(&bottom);
        assert_eq!(sum, whole);
        // A band of a few rows holds fewer than MIN_PIXELS shadowed pixels.
        let thin = split(0, 3);
        assert!(thin.pixels < MIN_PIXELS && thin.level.is_none(), "{thin:?}");
    }
}
