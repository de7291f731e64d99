//! Each light checked against the others: the direction that best explains each image, given
//! the normals the other images give.
//!
//! A row of the lights file that is wrong — a typo, two rows swapped, a lamp moved after the
//! calibration, an image from another session — leaves no trace in the normals that a user
//! could see: the robust fit treats that image's samples as outliers, or bends the normals a
//! little towards them. Yet the other images say where that light must have been. For each
//! solved pixel, the weighted least-squares normal of its usable samples without image k,
//! g₋ₖ = (M − w_k l_k l_kᵀ)⁻¹(b − w_k y_k l_k) with M = Σ w l lᵀ and b = Σ w y l over the
//! samples it uses (y the sample over the pixel's albedo; w Tukey's biweight of its residual,
//! so that a wrong light does not bend the normals the other lights are judged by), predicts
//! image k's sample as g₋ₖ·l_k; the direction
//! s_k that best fits image k's samples over all pixels, by least squares (Σ g₋ₖ g₋ₖᵀ) s_k =
//! Σ g₋ₖ y_k, is where the other images put its light (leaving image k out keeps a wrong light
//! from bending the normals it is judged by). The angle between s_k and the given l_k is the
//! light's **disagreement**.
//!
//! **Usable samples**: finite, not saturated, facing the light by the solved normal
//! (n·l > [`LIT`]), brighter than [`DARK`] of the albedo (a cast shadow is not Lambertian), and
//! not brighter than a surface facing the light can be ([`BRIGHTEST`] of the albedo: above it a
//! sample holds a highlight). Pixels whose remaining lights barely span three dimensions
//! (a bound of the leave-one-out system's smallest eigenvalue under [`MIN_EIGEN`]) are skipped
//! for that light. Leaving one sample out is a rank-one downdate of the pixel's fit
//! (Sherman–Morrison): g₋ₖ = g − M⁻¹l_k r_k/(1 − h_k), r_k the sample's residual and h_k its
//! leverage (weighted: w_k r_k over 1 − w_k h_k).
//!
//! **Which light disagrees.** Every light disagrees a little: noise, and what Lambert's law
//! leaves out (highlights under the cap, interreflections, the lamp's size). Take each light's
//! disagreement as the length of a two-dimensional Gaussian error, the same for every light:
//! its upper quartile then gives the common σ (Q₃ = σ√(2 ln 4), a Rayleigh distribution; the
//! quartile rather than the median, because lights near the view are explained better than
//! grazing ones, and the spread that matters is the grazing ones'), and a light whose
//! disagreement exceeds σ√(2 ln(K/α)) is one the others would reach by chance with probability
//! α over all K lights, α = [`FALSE_ALARM`] (0.1%, the rate of `auto`'s fit test; nominal:
//! σ rests on one order statistic, so with few lights the rate is several times that where the
//! floor below does not bind).
//! Such a light is named, with what the images say, only when its disagreement is also at least
//! [`WRONG_LIGHT_DEG`]: the calibration's own line between an accepted light and a wrong one
//! ([`crate::calibrate`]). Measured (`docs/photometric-stereo.md`): on DiLiGenT cat, bear and
//! reading with their lights the largest disagreements are 1.8°, 1.7° and 3.8°, none named; a
//! row of cat's lights turned by 5° or 10° is named at 3.5° and 8.6°, two swapped rows at
//! 26–27°.
//!
//! **Where it breaks.** It compares the lights with each other: an error that all of them share
//! (a rotation of the whole set, a wrong camera axis) moves the normals and leaves no
//! disagreement. With few lights each one's error spreads into the normals the others give, and
//! with lights near the viewer highlights sit inside the cap over much of the object, so the
//! disagreements grow (the classic 12-light set: medians 0.6–2.0°, up to 7°). Two swapped rows
//! among fewer than about 8 lights can both sit in the upper quartile σ is taken from, and then
//! neither is named.
//!
//! **Near lights** ([`measure_near`]): a positioned light's direction and irradiance change
//! across the object, so its position is what is fitted, and the disagreement is the angle
//! between the given and the fitted position seen from the object's centre; the same test
//! names it. A near check is of a whole image (a near run is not split): it holds no sums,
//! and is not carried by [`crate::run::CaptureChecks`].
//!
//! Each row's sums are taken in floating point and added to the totals in fixed point, so
//! that the row bands of a streamed run add up to the whole exactly and the result does not
//! depend on the threads.

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::grid::Mask;
use crate::ps::solve::Solution;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// A sample counts for its light where the solved normal faces it by more than this (n·l).
pub const LIT: f64 = 0.1;
/// A sample darker than this fraction of its pixel's albedo is taken for a cast shadow.
pub const DARK: f64 = 0.02;
/// A sample brighter than this fraction of its pixel's albedo holds more than Lambert's law
/// allows a surface facing its light (cos θ ≤ 1), with a margin for noise: a highlight.
pub const BRIGHTEST: f64 = 1.05;
/// A pixel's leave-one-out system counts where a lower bound of its smallest eigenvalue (of
/// Σ w l lᵀ over the remaining lights, w their Tukey weights; 4 det / trace²) is at least this.
pub const MIN_EIGEN: f64 = 0.02;
/// The check reads every `STRIDE`-th column of the image's grid (every row: a band of rows
/// then reads the pixels the whole reads). Against every pixel (47 ms on DiLiGenT cat), a
/// quarter of them moved the disagreements of cat, bear and reading by at most 0.06°, 0.07°
/// and 0.36° (against thresholds of 2.3–5.4°).
const STRIDE: usize = 4;
/// Fewest pixels from which a light's direction is fitted.
pub const MIN_PIXELS: usize = 50;
/// The false-alarm rate of the test over all the lights of a capture.
pub const FALSE_ALARM: f64 = 1e-3;
/// A light is named as disagreeing only from this many degrees: the calibration's line between
/// an accepted light and a wrong one (no accepted light more than 2° off).
pub const WRONG_LIGHT_DEG: f64 = 2.0;
/// Fewest lights for the test: with fewer, the upper quartile of the disagreements says little
/// about their spread.
pub const MIN_LIGHTS: usize = 6;

/// Totals in fixed point, units of 2⁻⁴⁰ (a row's sums: of order its pixel count at most).
const UNIT: f64 = 1_099_511_627_776.0;

/// What the other images say of one light.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LightFit {
    /// The unit direction that best explains the light's image (camera frame, as the lights).
    pub direction: [f64; 3],
    /// Its angle from the given direction, degrees.
    pub disagreement_deg: f64,
    /// Pixels whose samples of this light entered the fit.
    pub pixels: usize,
    /// For a near light ([`measure_near`]): the position that best explains the light's image
    /// (camera frame, the units of the given positions); `direction` is then the direction to
    /// it from the object's centre, and the disagreement the angle there between the given
    /// position and this one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub position: Option<[f64; 3]>,
}

/// Each light of a solve checked against the others ([`crate::ps::light_agreement`]), summable
/// over the row bands of a streamed run.
#[derive(Clone, Default, PartialEq, Serialize)]
pub struct LightAgreement {
    /// Per light (in the lights' order), what the other images say of it; `None` with fewer
    /// than [`MIN_PIXELS`] pixels.
    pub lights: Vec<Option<LightFit>>,
    /// The median disagreement over the fitted lights, degrees.
    pub median_deg: Option<f64>,
    /// The disagreement above which a light is one the others would reach by chance with
    /// probability [`FALSE_ALARM`] over all the lights (from their upper quartile; at least
    /// [`WRONG_LIGHT_DEG`]); `None` with fewer than [`MIN_LIGHTS`] fitted lights.
    pub threshold_deg: Option<f64>,
    /// The lights (indices) whose disagreement is above the threshold.
    pub disagreeing: Vec<usize>,
    /// Per light: Σ g₋ₖ g₋ₖᵀ (six entries of the symmetric matrix), Σ g₋ₖ y_k and the pixels, in
    /// fixed point.
    #[serde(skip)]
    sums: Vec<([i128; 9], usize)>,
    /// The given directions (unit).
    #[serde(skip)]
    given: Vec<Vector3<f64>>,
}

impl std::fmt::Debug for LightAgreement {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LightAgreement")
            .field("lights", &self.lights)
            .field("median_deg", &self.median_deg)
            .field("threshold_deg", &self.threshold_deg)
            .field("disagreeing", &self.disagreeing)
            .finish_non_exhaustive()
    }
}

/// The sums a [`LightAgreement`] is judged from, which add up over the parts of a capture (for
/// [`crate::run::checks`]).
#[derive(Serialize, Deserialize)]
pub(crate) struct LightAgreementSums {
    sums: Vec<([i128; 9], usize)>,
    /// The given directions' bits (text keeps every bit of an integer, not of every float).
    given: Vec<[u64; 3]>,
}

impl LightAgreement {
    /// The largest disagreement over the fitted lights, degrees (0 with none fitted).
    pub fn largest_deg(&self) -> f64 {
        self.lights
            .iter()
            .flatten()
            .map(|f| f.disagreement_deg)
            .fold(0.0, f64::max)
    }

    /// Its sums, to be added to another part's.
    pub(crate) fn sums(&self) -> LightAgreementSums {
        LightAgreementSums {
            sums: self.sums.clone(),
            given: self
                .given
                .iter()
                .map(|l| [l.x.to_bits(), l.y.to_bits(), l.z.to_bits()])
                .collect(),
        }
    }

    /// The check the sums give; `None` when they do not hold one sum per given light, or not
    /// the sums of a check: a part holds at most 2⁴⁸ pixels a light, and each of its sums at
    /// most 2¹⁰ a pixel (a pixel's terms are products of a unit-scale fit and a sample of at
    /// most [`BRIGHTEST`]), in units of 2⁻⁴⁰ — so that 2²⁹ parts add up in range.
    pub(crate) fn from_sums(sums: LightAgreementSums) -> Option<LightAgreement> {
        const LIMIT: usize = 1 << 48;
        let bound = |n: usize| (n.max(1) as i128) << 50;
        if sums.sums.len() != sums.given.len()
            || sums
                .sums
                .iter()
                .any(|(s, n)| *n > LIMIT || s.iter().any(|v| v.unsigned_abs() > bound(*n) as u128))
        {
            return None;
        }
        let mut out = LightAgreement {
            sums: sums.sums,
            given: sums
                .given
                .iter()
                .map(|l| {
                    Vector3::new(
                        f64::from_bits(l[0]),
                        f64::from_bits(l[1]),
                        f64::from_bits(l[2]),
                    )
                })
                .collect(),
            ..LightAgreement::default()
        };
        out.finish();
        Some(out)
    }

    /// Adds another part's sums (checked against the same lights), `None` (and nothing
    /// added) where a sum would overflow.
    pub(crate) fn try_add(&mut self, other: &LightAgreement) -> Option<()> {
        if self.sums.is_empty() {
            self.clone_from(other);
            return Some(());
        }
        let sums = self
            .sums
            .iter()
            .zip(&other.sums)
            .map(|(a, b)| {
                let mut out = [0i128; 9];
                for (o, (x, y)) in out.iter_mut().zip(a.0.iter().zip(&b.0)) {
                    *o = x.checked_add(*y)?;
                }
                Some((out, a.1.checked_add(b.1)?))
            })
            .collect::<Option<Vec<_>>>()?;
        self.sums = sums;
        self.finish();
        Some(())
    }

    /// Whether this is a near-light check ([`measure_near`]: positions, no sums).
    pub(crate) fn is_near(&self) -> bool {
        self.lights.iter().flatten().any(|f| f.position.is_some())
    }

    /// The given directions the check was made against.
    pub(crate) fn given(&self) -> &[Vector3<f64>] {
        &self.given
    }

    /// Adds another band's sums and updates the fits: [`Self::try_add`], whose overflow the
    /// bands of one capture cannot reach (its pixel count bounds every sum far below i128's
    /// range); were it reached, the total would stay as it was.
    pub(crate) fn add(&mut self, other: &LightAgreement) {
        let _ = self.try_add(other);
    }

    /// The fits from the sums, then the median, the threshold and the lights named.
    fn finish(&mut self) {
        self.lights = self
            .sums
            .iter()
            .zip(&self.given)
            .map(|((s, pixels), l)| {
                if *pixels < MIN_PIXELS {
                    return None;
                }
                let v = |i: usize| s[i] as f64 / UNIT;
                let a = Matrix3::new(v(0), v(1), v(2), v(1), v(3), v(4), v(2), v(4), v(5));
                let c = Vector3::new(v(6), v(7), v(8));
                let d = a.cholesky()?.solve(&c);
                let norm = d.norm();
                if !(norm.is_finite() && norm > 0.0) {
                    return None;
                }
                let d = d / norm;
                Some(LightFit {
                    direction: [d.x, d.y, d.z],
                    disagreement_deg: d.dot(l).clamp(-1.0, 1.0).acos().to_degrees(),
                    pixels: *pixels,
                    position: None,
                })
            })
            .collect();
        self.judge();
    }

    /// The median, the threshold and the lights named, from the fits.
    fn judge(&mut self) {
        let mut angles: Vec<f64> = self
            .lights
            .iter()
            .flatten()
            .map(|f| f.disagreement_deg)
            .collect();
        self.median_deg = None;
        self.threshold_deg = None;
        self.disagreeing.clear();
        if angles.is_empty() {
            return;
        }
        let count = angles.len();
        let (low, mid, _) = angles.select_nth_unstable_by(count / 2, f64::total_cmp);
        let median = if count.is_multiple_of(2) {
            0.5 * (*mid + low.iter().copied().fold(f64::NEG_INFINITY, f64::max))
        } else {
            *mid
        };
        self.median_deg = Some(median);
        if count < MIN_LIGHTS {
            return;
        }
        // Rayleigh: the upper quartile is σ√(2 ln 4); P(X > x) = exp(−x²/2σ²) = α/K at the
        // threshold.
        let upper = *angles
            .select_nth_unstable_by((3 * count / 4).min(count - 1), f64::total_cmp)
            .1;
        let sigma = upper / (2.0 * (4f64).ln()).sqrt();
        let threshold =
            (sigma * (2.0 * (count as f64 / FALSE_ALARM).ln()).sqrt()).max(WRONG_LIGHT_DEG);
        self.threshold_deg = Some(threshold);
        self.disagreeing = self
            .lights
            .iter()
            .enumerate()
            .filter(|(_, f)| f.as_ref().is_some_and(|f| f.disagreement_deg > threshold))
            .map(|(k, _)| k)
            .collect();
    }
}

/// Checks each light of channel `channel` of `stack` against the others, on the solution `sol`
/// of that channel (its solved pixels inside `mask`): see the module documentation. The samples
/// are taken as the solve used them, times the solution's gains. The caller has checked that
/// the stack, lights, mask and solution agree (the solve's inputs).
pub(crate) fn measure(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    sol: &Solution,
) -> LightAgreement {
    let dirs = lights.directions();
    let count = dirs.len();
    let gains = &sol.gains.gains;
    let width = mask.width();
    let q = |v: f64| (v * UNIT).round() as i128;
    let zero = || vec![([0i128; 9], 0usize); count];
    let sums = (0..mask.height())
        .into_par_iter()
        .fold(zero, |mut sums, y| {
            // The row's sums in floating point (the same whichever band holds the row), then
            // into the fixed-point totals once per row.
            let mut row = vec![([0f64; 9], 0usize); count];
            let mut used: Vec<(usize, f64, f64)> = Vec::with_capacity(count);
            let mut scratch: Vec<f64> = Vec::with_capacity(count);
            for x in (0..width).step_by(STRIDE) {
                let p = y * width + x;
                let Some((local, rho, n)) = sol.solved_pixel(stack, mask, p) else {
                    continue;
                };
                used.clear();
                for (k, l) in dirs.iter().enumerate() {
                    let at = Sample {
                        stack,
                        channel,
                        k,
                        p,
                        local,
                    };
                    if let Some(rel) = at.usable(&n, l, |v| v * f64::from(gains[k]) / rho) {
                        used.push((k, rel, 1.0));
                    }
                }
                if used.len() < 4 {
                    continue;
                }
                // The pixel's own fit, robust: Tukey weights from its residuals (so that one
                // wrong light does not bend the normals the others are judged by).
                let Some((m, inv, fit)) = robust_fit(&dirs, &mut used, &mut scratch) else {
                    continue;
                };
                let det = m.determinant();
                for &(k, rel, w) in &used {
                    let Some(gk) = leave_out(&m, &inv, &fit, det, &dirs[k], rel, w) else {
                        continue;
                    };
                    let s = &mut row[k];
                    s.0[0] += gk.x * gk.x;
                    s.0[1] += gk.x * gk.y;
                    s.0[2] += gk.x * gk.z;
                    s.0[3] += gk.y * gk.y;
                    s.0[4] += gk.y * gk.z;
                    s.0[5] += gk.z * gk.z;
                    s.0[6] += gk.x * rel;
                    s.0[7] += gk.y * rel;
                    s.0[8] += gk.z * rel;
                    s.1 += 1;
                }
            }
            for (total, r) in sums.iter_mut().zip(&row) {
                if r.1 > 0 {
                    for (t, v) in total.0.iter_mut().zip(&r.0) {
                        *t += q(*v);
                    }
                    total.1 += r.1;
                }
            }
            sums
        })
        .reduce(zero, |mut a, b| {
            // Integer sums: the result depends neither on the threads nor on the bands.
            for (x, y) in a.iter_mut().zip(&b) {
                for (u, v) in x.0.iter_mut().zip(&y.0) {
                    *u += v;
                }
                x.1 += y.1;
            }
            a
        });
    let mut out = LightAgreement {
        sums,
        given: dirs,
        ..LightAgreement::default()
    };
    out.finish();
    out
}

/// Most Gauss–Newton passes of [`measure_near`]'s position fits.
const NEAR_PASSES: usize = 4;
/// [`measure_near`] stops once no light's last step turned it, seen from the object's centre,
/// by more than this fraction of [`WRONG_LIGHT_DEG`]: a step that small cannot change which
/// lights are named. (Under the right positions one pass does.)
const NEAR_SETTLED: f64 = 0.01;

/// Checks each near light of a near-light solve against the others (see the module
/// documentation for the distant case): `sol` is the solve of channel `channel` of `stack` at
/// the absolute depth `depth` seen through `camera`, under `lights` (each with a position, as
/// the near solve requires). A pixel's samples are taken relative to the irradiance the given
/// light sends to its point X (y / (a_k(X) ρ), with the unit directions l_k(X) of
/// [`crate::synth::near::near_light_at`]); each sample's leave-one-out prediction g₋ₖ then
/// depends on light k only through its position P_k, and the position and a relative intensity
/// (1 + ε) that best explain image k over all pixels, Σ ((1 + ε) a_k(X; P) l_k(X; P)·g₋ₖ /
/// a_k(X; P_k) − y)², are found by Gauss–Newton from the given position (at most
/// [`NEAR_PASSES`] passes, until no light moves by [`NEAR_SETTLED`] of the naming line; each
/// step at most half the light's distance from the object's centre; the derivatives by central
/// differences; every [`STRIDE`]-th row and column). The light's disagreement is the angle, seen from the
/// object's centre (the mean of the sampled points), between the given position and the fitted
/// one — what a distant light's disagreement is, so that the same test names it.
pub(crate) fn measure_near(
    stack: &ImageStack,
    channel: usize,
    lights: &[crate::capture::lights::Light],
    mask: &Mask,
    sol: &Solution,
    depth: &crate::grid::ScalarMap,
    camera: &crate::camera::Intrinsics,
) -> LightAgreement {
    use crate::synth::near::near_light_at;
    use nalgebra::{Matrix4, Vector4};
    let count = lights.len();
    let width = mask.width();
    let given: Vec<Option<Vector3<f64>>> = lights.iter().map(|l| l.position).collect();
    // One pass over the sampled pixels at the positions `at` (and intensities 1 + `scale`):
    // per light, the Gauss–Newton system (4×4 and right-hand side) and its pixels, and the sum
    // of the sampled points and their count.
    type Sums = (Vec<([f64; 14], usize)>, Vector3<f64>, usize);
    let pass = |at: &[Option<Vector3<f64>>], scale: &[f64]| -> Sums {
        // Every STRIDE-th row and column: a near run is solved whole, and the positions are
        // fitted in several passes over the samples.
        let rows: Vec<Sums> = (0..mask.height())
            .into_par_iter()
            .step_by(STRIDE)
            .map(|y| {
                let mut row = vec![([0f64; 14], 0usize); count];
                let mut centre = (Vector3::zeros(), 0usize);
                let mut dirs = vec![Vector3::z(); count];
                let mut falls = vec![0f64; count];
                let mut used: Vec<(usize, f64, f64)> = Vec::with_capacity(count);
                let mut scratch: Vec<f64> = Vec::with_capacity(count);
                let mut moved = lights.to_vec();
                for x in (0..width).step_by(STRIDE) {
                    let p = y * width + x;
                    let Some((local, rho, n)) = sol.solved_pixel(stack, mask, p) else {
                        continue;
                    };
                    let d = f64::from(depth.data()[p]);
                    if !(d.is_finite() && d > 0.0) {
                        continue;
                    }
                    let point = Vector3::from(camera.unproject(x as f64, y as f64, 1.0)) * d;
                    used.clear();
                    for (k, light) in lights.iter().enumerate() {
                        let Some((fall, l)) = near_light_at(light, &point) else {
                            continue;
                        };
                        dirs[k] = l;
                        falls[k] = fall;
                        if fall.is_nan() || fall <= 0.0 {
                            continue;
                        }
                        let at = Sample {
                            stack,
                            channel,
                            k,
                            p,
                            local,
                        };
                        if let Some(rel) = at.usable(&n, &l, |v| v / (fall * rho)) {
                            used.push((k, rel, 1.0));
                        }
                    }
                    if used.len() < 4 {
                        continue;
                    }
                    let Some((m, inv, fit)) = robust_fit(&dirs, &mut used, &mut scratch) else {
                        continue;
                    };
                    centre.0 += point;
                    centre.1 += 1;
                    let det = m.determinant();
                    for &(k, rel, w) in &used {
                        let (Some(pk), Some(p0)) = (at[k], given[k]) else {
                            continue;
                        };
                        let Some(gk) = leave_out(&m, &inv, &fit, det, &dirs[k], rel, w) else {
                            continue;
                        };
                        // The sample's model at position q, relative to the given light's
                        // irradiance at the point.
                        let light = &mut moved[k];
                        let mut model = |q: Vector3<f64>| {
                            light.position = Some(q);
                            near_light_at(light, &point)
                                .map(|(fall, l)| fall / falls[k] * l.dot(&gk))
                        };
                        let h = 1e-4 * (pk - point).norm();
                        let Some(here) = model(pk) else {
                            continue;
                        };
                        let mut grad = Vector3::zeros();
                        let mut ok = true;
                        for i in 0..3 {
                            let mut e = Vector3::zeros();
                            e[i] = h;
                            match (model(pk + e), model(pk - e)) {
                                (Some(a), Some(b)) => grad[i] = (a - b) / (2.0 * h),
                                _ => ok = false,
                            }
                        }
                        light.position = Some(p0);
                        if !ok {
                            continue;
                        }
                        let s = 1.0 + scale[k];
                        let phi = Vector4::new(s * grad.x, s * grad.y, s * grad.z, here);
                        let e = rel - s * here;
                        // A sample the model cannot evaluate says nothing (and would void the
                        // light's whole system).
                        if !(phi.iter().all(|v| v.is_finite()) && e.is_finite()) {
                            continue;
                        }
                        let sums = &mut row[k];
                        let mut i = 0;
                        for a in 0..4 {
                            for b in a..4 {
                                sums.0[i] += phi[a] * phi[b];
                                i += 1;
                            }
                        }
                        for a in 0..4 {
                            sums.0[10 + a] += phi[a] * e;
                        }
                        sums.1 += 1;
                    }
                }
                (row, centre.0, centre.1)
            })
            .collect();
        // Rows in order: the same sums whatever the threads.
        let mut total = (vec![([0f64; 14], 0usize); count], Vector3::zeros(), 0usize);
        for (row, c, n) in rows {
            for (t, r) in total.0.iter_mut().zip(&row) {
                for (a, b) in t.0.iter_mut().zip(&r.0) {
                    *a += b;
                }
                t.1 += r.1;
            }
            total.1 += c;
            total.2 += n;
        }
        total
    };
    let mut at = given.clone();
    let mut scale = vec![0f64; count];
    let mut pixels = vec![0usize; count];
    let mut centre = None;
    for _ in 0..NEAR_PASSES {
        let (sums, c, n) = pass(&at, &scale);
        if n == 0 {
            break;
        }
        let c = *centre.get_or_insert(c / n as f64);
        let mut largest = 0f64;
        for (k, (s, used)) in sums.iter().enumerate() {
            pixels[k] = *used;
            let Some(pk) = at[k] else {
                continue;
            };
            if *used < MIN_PIXELS {
                at[k] = None;
                continue;
            }
            let mut a = Matrix4::zeros();
            let mut i = 0;
            for r in 0..4 {
                for q in r..4 {
                    a[(r, q)] = s[i];
                    a[(q, r)] = s[i];
                    i += 1;
                }
            }
            let b = Vector4::new(s[10], s[11], s[12], s[13]);
            let Some(step) = a.cholesky().map(|f| f.solve(&b)) else {
                at[k] = None;
                continue;
            };
            let mut move_by = Vector3::new(step.x, step.y, step.z);
            let limit = 0.5 * (pk - c).norm();
            // A capped step is shortened as a whole: its intensity change with its move.
            let fraction = if move_by.norm() > limit {
                limit / move_by.norm()
            } else {
                1.0
            };
            move_by *= fraction;
            if move_by.iter().all(|v| v.is_finite()) && step.w.is_finite() {
                let next = pk + move_by;
                largest = largest.max((pk - c).angle(&(next - c)).to_degrees());
                at[k] = Some(next);
                scale[k] += fraction * step.w;
            } else {
                at[k] = None;
            }
        }
        if largest < NEAR_SETTLED * WRONG_LIGHT_DEG {
            break;
        }
    }
    let mut out = LightAgreement::default();
    let Some(c) = centre else {
        out.lights = vec![None; count];
        out.judge();
        return out;
    };
    out.lights = (0..count)
        .map(|k| {
            let (Some(p), Some(p0)) = (at[k], given[k]) else {
                return None;
            };
            if pixels[k] < MIN_PIXELS {
                return None;
            }
            let d = (p - c).try_normalize(0.0)?;
            let d0 = (p0 - c).try_normalize(0.0)?;
            Some(LightFit {
                direction: [d.x, d.y, d.z],
                disagreement_deg: d.dot(&d0).clamp(-1.0, 1.0).acos().to_degrees(),
                pixels: pixels[k],
                position: Some([p.x, p.y, p.z]),
            })
        })
        .collect();
    out.judge();
    out
}

/// Image `k`'s sample of pixel `p` (row-major; `local` its index in the stack's planes).
struct Sample<'a> {
    stack: &'a ImageStack,
    channel: usize,
    k: usize,
    p: usize,
    local: usize,
}

impl Sample<'_> {
    /// The sample relative to what a unit albedo facing the light shows (`relative` of the
    /// stored value: times the light's gain, over the pixel's albedo), where it is usable
    /// against the solved normal `n` and the light's direction `l` (the module documentation's
    /// usable samples): `None` where the surface faces away from the light, the sample is
    /// saturated or not finite, or it is a cast shadow or a highlight.
    fn usable(
        &self,
        n: &Vector3<f64>,
        l: &Vector3<f64>,
        relative: impl Fn(f64) -> f64,
    ) -> Option<f64> {
        if n.dot(l) <= LIT || self.stack.is_saturated(self.k, self.p) {
            return None;
        }
        let rel = relative(f64::from(
            self.stack.plane(self.k, self.channel)[self.local],
        ));
        (rel.is_finite() && rel > DARK && rel < BRIGHTEST).then_some(rel)
    }
}

/// A pixel's fit without one of its samples (light `l`, relative brightness `rel`, weight `w`),
/// from its weighted normal matrix `m` (determinant `det`), inverse `inv` and fit `fit`; `None`
/// where the remaining lights barely span three dimensions or the fit does not face `l`.
///
/// Sherman–Morrison: g₋ₖ = g − M⁻¹l w r/(1 − w h), with the leverage h = lᵀM⁻¹l and the
/// residual r = y − lᵀg. The remaining system's determinant is det M (1 − w h), and for a 3×3
/// positive definite matrix λ_min ≥ 4 det / trace², a cheap bound on its conditioning.
fn leave_out(
    m: &Matrix3<f64>,
    inv: &Matrix3<f64>,
    fit: &Vector3<f64>,
    det: f64,
    l: &Vector3<f64>,
    rel: f64,
    w: f64,
) -> Option<Vector3<f64>> {
    let ml = inv * l;
    let free = 1.0 - w * l.dot(&ml);
    let trace = m.trace() - w;
    if !(free > 0.0 && 4.0 * det * free >= MIN_EIGEN * trace * trace) {
        return None;
    }
    let gk = fit - ml * (w * (rel - l.dot(fit)) / free);
    (gk.iter().all(|v| v.is_finite()) && gk.dot(l) > LIT * gk.norm()).then_some(gk)
}

/// Tukey's biweight tuning constant (95% efficiency under Gaussian noise).
const TUKEY: f64 = 4.685;
/// Floor of a pixel's residual scale, relative to its albedo (below it the weights would
/// follow the noise of nearly exact fits).
const SCALE_FLOOR: f64 = 1e-3;
/// Reweighting steps of a pixel's robust fit.
const ROBUST_STEPS: usize = 2;

/// A pixel's least-squares fit of g from its samples `used` (light, relative brightness,
/// weight), reweighted [`ROBUST_STEPS`] times by Tukey's biweight of the residuals over
/// 1.4826 × their median absolute value (at least [`SCALE_FLOOR`]); the weights are left in
/// `used`. Returns the weighted normal matrix, its inverse and the fit; `None` when it is
/// singular.
fn robust_fit(
    dirs: &[Vector3<f64>],
    used: &mut [(usize, f64, f64)],
    scratch: &mut Vec<f64>,
) -> Option<(Matrix3<f64>, Matrix3<f64>, Vector3<f64>)> {
    let solve = |used: &[(usize, f64, f64)]| {
        let mut m = Matrix3::zeros();
        let mut b = Vector3::zeros();
        for &(k, rel, w) in used {
            let l = &dirs[k];
            m += l * l.transpose() * w;
            b += l * (rel * w);
        }
        let inv = m.try_inverse()?;
        Some((m, inv, inv * b))
    };
    let mut out = solve(used)?;
    for _ in 0..ROBUST_STEPS {
        scratch.clear();
        scratch.extend(
            used.iter()
                .map(|&(k, rel, _)| (rel - dirs[k].dot(&out.2)).abs()),
        );
        let mid = scratch.len() / 2;
        let median = *scratch.select_nth_unstable_by(mid, f64::total_cmp).1;
        let scale = (1.4826 * median).max(SCALE_FLOOR) * TUKEY;
        for u in used.iter_mut() {
            let r = (u.1 - dirs[u.0].dot(&out.2)) / scale;
            u.2 = if r.abs() < 1.0 {
                (1.0 - r * r).powi(2)
            } else {
                0.0
            };
        }
        out = solve(used)?;
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::lights::Light;
    use crate::ps::test_support::{band, rendered_and_solved, sphere_for_bands};
    use crate::synth::reflectance::{BlinnPhong, Material, Specular};
    use crate::synth::render::RenderOptions;
    use crate::synth::scene::{Albedo, SceneKind};

    /// `l` turned by `deg` about the axis across it and the view.
    fn turned(l: &Vector3<f64>, deg: f64) -> Vector3<f64> {
        let axis = l.cross(&Vector3::z()).normalize();
        nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), deg.to_radians())
            * l
    }

    /// Renders `kind` at 96² under `count` lights with `material` and 0.5% noise, solves it
    /// with `given` (the rendered lights with some rows changed) and checks the lights.
    fn checked(
        kind: SceneKind,
        material: Material,
        count: usize,
        given: impl Fn(&[Vector3<f64>]) -> Vec<Vector3<f64>>,
    ) -> (LightAgreement, Vec<Vector3<f64>>) {
        let scene = kind.build(96, Albedo::Constant(0.7), material);
        let lights = Lights::fibonacci(count, 25.0).unwrap();
        let truth = lights.directions();
        let used = Lights::new(given(&truth).into_iter().map(Light::new).collect()).unwrap();
        let options = RenderOptions {
            noise_sigma: 0.005,
            seed: 9,
            ..RenderOptions::default()
        };
        let (_, _, sol) = rendered_and_solved(&scene, &lights, &used, &options);
        (sol.light_agreement.clone().unwrap(), truth)
    }

    fn angle(a: &[f64; 3], b: &Vector3<f64>) -> f64 {
        Vector3::new(a[0], a[1], a[2])
            .dot(b)
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees()
    }

    /// Under the lights they were rendered with, matte and glossy (Blinn–Phong, k_s 0.3,
    /// exponent 40) scenes name no light; one light turned by 10° is named, alone, and the
    /// direction its image gives is within a quarter of the turn of where it was (measured:
    /// 0.04–0.66°, the glossy relief under 12 lights 2.2°); under 12 lights as under 24.
    #[test]
    fn a_wrong_light_is_named_and_the_right_ones_are_not() {
        let glossy = Material::with_specular(Specular::BlinnPhong(BlinnPhong {
            ks: 0.3,
            exponent: 40.0,
        }));
        for kind in [SceneKind::Sphere, SceneKind::Relief, SceneKind::Bust] {
            for (name, material) in [("matte", Material::lambertian()), ("glossy", glossy)] {
                for count in [12, 24] {
                    let (right, _) = checked(kind, material, count, |t| t.to_vec());
                    let worst = right.largest_deg();
                    let (wrong, truth) = checked(kind, material, count, |t| {
                        let mut v = t.to_vec();
                        v[5] = turned(&v[5], 10.0);
                        v
                    });
                    let fit = wrong.lights[5].as_ref().unwrap();
                    println!(
                        "{kind:?} {name} {count} lights: right median {:.2}°, worst {worst:.2}°, threshold {:.2}°; light 5 turned 10°: {:.2}° (threshold {:.2}°), {:.2}° from the truth",
                        right.median_deg.unwrap(),
                        right.threshold_deg.unwrap(),
                        fit.disagreement_deg,
                        wrong.threshold_deg.unwrap(),
                        angle(&fit.direction, &truth[5])
                    );
                    assert!(
                        right.disagreeing.is_empty(),
                        "{kind:?} {name} {count}: {right:?}"
                    );
                    assert_eq!(
                        wrong.disagreeing,
                        vec![5],
                        "{kind:?} {name} {count}: {wrong:?}"
                    );
                    // The images put it back most of the way: within a quarter of the turn.
                    assert!(
                        angle(&fit.direction, &truth[5]) < 2.5,
                        "{kind:?} {name} {count}: {fit:?}"
                    );
                }
            }
        }
    }

    /// Two rows swapped: both lights are named.
    #[test]
    fn swapped_rows_are_both_named() {
        let (a, _) = checked(SceneKind::Relief, Material::lambertian(), 16, |t| {
            let mut v = t.to_vec();
            v.swap(2, 9);
            v
        });
        assert_eq!(a.disagreeing, vec![2, 9], "{a:?}");
    }

    /// Measured in two bands of rows and added, the check is the whole's, bit for bit (the sums
    /// are integers); with fewer than [`MIN_LIGHTS`] lights nothing is named.
    #[test]
    fn bands_add_up_to_the_whole_and_few_lights_name_none() {
        let lights = Lights::fibonacci(12, 25.0).unwrap();
        let (mask, stack, sol) = sphere_for_bands(&lights, 0.0);
        let mask = &mask;
        let whole = measure(&stack, 0, &lights, mask, &sol);
        let split = |y0, y1| measure(&stack, 0, &lights, &band(mask, y0, y1), &sol);
        let mut sum = LightAgreement::default();
        sum.add(&split(0, 27));
        sum.add(&split(27, 64));
        assert_eq!(sum, whole);
        assert!(whole.threshold_deg.is_some());

        let five = Lights::fibonacci(5, 25.0).unwrap();
        let (_, stack, sol) = sphere_for_bands(&five, 0.0);
        let few = measure(&stack, 0, &five, mask, &sol);
        assert!(
            few.threshold_deg.is_none() && few.disagreeing.is_empty(),
            "{few:?}"
        );
    }
}
