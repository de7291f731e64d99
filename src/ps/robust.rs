//! Robust per-pixel estimators of g = ρN for samples that break the Lambertian model: cast
//! shadows, specular highlights, interreflections, miscalibrated lights.
//!
//! Every estimator starts from the samples that pass shadow and saturation rejection (the
//! [`crate::ps::solve::Method::Threshold`] set) and then decides, sample by sample, how much each
//! one counts:
//! - **Rank trimming**: drop the darkest and brightest fractions of a pixel's samples and fit
//!   the rest by least squares (the order-statistics filter used since Coleman & Jain 1982,
//!   "Obtaining 3-dimensional shape of textured and specular surfaces using four-source
//!   photometry").
//! - **IRLS** with a Huber, Tukey-biweight or L1 loss: iteratively reweighted least squares
//!   with weights w = ψ(u)/u of the residual u = r/s, the scale s re-estimated each iteration
//!   as 1.4826·median|r| (Holland & Welsch 1977, "Robust regression using iteratively
//!   reweighted least-squares"). The L1 loss is the convex relaxation of the sparse-error model
//!   of Ikehata et al. 2012 ("Robust photometric stereo using sparse regression").
//! - **Specular rejection by half-vector geometry**: a sample whose half vector
//!   h = (l + v)/|l + v| lies within a cone of the current normal (n·h ≥ cos θ_cone) is in the
//!   specular lobe of any glossy isotropic BRDF and is dropped, as are grazing samples
//!   (n·l < [`DEFAULT_MIN_LIT_COSINE`]) where real diffuse reflection departs from Lambert's
//!   cosine. The rest are fitted with Tukey IRLS, and the selection is redone with each new
//!   normal. This is the low-frequency-region idea of Shi et al. 2014 ("Bi-polynomial
//!   modeling of low-frequency reflectances", TPAMI 36(6)), with Lambert's law as the model
//!   of that region.
//!
//! Where a robust selection leaves fewer than [`MIN_ROBUST_SAMPLES`] samples, the estimator
//! falls back to the threshold set rather than guessing from too little.

// The per-sample loops index several parallel arrays (directions, values, flags, weights) by
// the image number; iterator chains over four zips would hide that.
#![allow(clippy::needless_range_loop)]

use crate::linalg::{condition_at_most, condition_from_gram, solve_spd};
use crate::ps::solve::{MIN_SAMPLES, PixelSolution, PixelStatus, Reference};
use nalgebra::{Matrix3, Vector3};
use serde::Serialize;

/// Tukey biweight tuning constant: 95% efficiency at the normal distribution.
pub const TUKEY_C: f64 = 4.685;
/// Huber tuning constant: 95% efficiency at the normal distribution.
pub const HUBER_K: f64 = 1.345;
/// Converts a median absolute deviation to a standard deviation (normal distribution).
pub const MAD_TO_SIGMA: f64 = 1.4826;
/// Most IRLS iterations per pixel.
pub const MAX_IRLS_ITERATIONS: usize = 20;
/// Relative change of g below which IRLS stops.
const IRLS_TOLERANCE: f64 = 1e-6;
/// Relative change of g below which the specular estimator's selection-and-refit stops:
/// about 0.1° of normal direction and 0.2% of albedo, far below the errors of real captures
/// (the IRLS limit of [`IRLS_TOLERANCE`] costs three times the rounds for no measurable gain
/// on DiLiGenT: the selections of many pixels keep flipping a sample in and out).
const SPECULAR_TOLERANCE: f64 = 2e-3;
/// L1 weights are 1/max(|u|, this): bounds the weight of samples that fit exactly.
const L1_FLOOR: f64 = 1e-3;
/// Default half-angle of the specular cone around the normal, in degrees: samples with
/// angle(n, h) below it are treated as specular.
pub const DEFAULT_SPECULAR_CONE_DEG: f64 = 30.0;
/// Default smallest n·l of a sample the specular-rejecting estimator keeps.
pub const DEFAULT_MIN_LIT_COSINE: f64 = 0.1;
/// Fewest samples a robust selection must keep; below this the threshold set is used.
pub const MIN_ROBUST_SAMPLES: usize = 6;
/// Default fraction of a pixel's samples that rank trimming drops from the dark end.
pub const DEFAULT_TRIM_LOW: f32 = 0.2;
/// Default fraction of a pixel's samples that rank trimming drops from the bright end.
pub const DEFAULT_TRIM_HIGH: f32 = 0.1;
/// Selection-and-refit rounds of the specular-rejecting estimator.
const SPECULAR_ROUNDS: usize = 10;
/// The specular cone is narrowed in this many steps (to none) until the kept samples are
/// numerous and spread enough.
const CONE_STEPS: usize = 3;
/// Largest condition number of the kept light directions for a specular cone to be accepted:
/// a wider cone that leaves only clustered lights trades a highlight bias for noise gain.
pub const SELECTION_MAX_CONDITION: f64 = 20.0;

/// The loss of an IRLS estimator.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Loss {
    /// Quadratic within [`HUBER_K`]·s, linear beyond: bounded influence, convex.
    Huber,
    /// Tukey's biweight: samples beyond [`TUKEY_C`]·s get zero weight (redescending).
    Tukey,
    /// Least absolute deviations.
    L1,
}

impl Loss {
    /// IRLS weight ψ(u)/u of a standardised residual u.
    pub fn weight(self, u: f64) -> f64 {
        let a = u.abs();
        match self {
            Loss::Huber => {
                if a <= HUBER_K {
                    1.0
                } else {
                    HUBER_K / a
                }
            }
            Loss::Tukey => {
                if a < TUKEY_C {
                    let t = 1.0 - (u / TUKEY_C).powi(2);
                    t * t
                } else {
                    0.0
                }
            }
            Loss::L1 => 1.0 / a.max(L1_FLOOR),
        }
    }
}

/// A robust estimator and its parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Estimator {
    /// Least squares over the threshold set (every finite sample when `reject` is false),
    /// rows weighted by the sample itself when `intensity_weight` is set.
    Plain {
        reject: bool,
        intensity_weight: bool,
    },
    /// Drop the `low` darkest and `high` brightest fractions of the valid samples.
    Trimmed { low: f32, high: f32 },
    /// Iteratively reweighted least squares over the threshold set.
    Irls(Loss),
    /// Half-vector specular rejection plus grazing rejection, then Tukey IRLS.
    Specular { cos_cone: f64, min_cos_lit: f64 },
}

/// Per-pixel robust fitting with reusable buffers. Values passed in are multiplied by the
/// per-image `gains` first (intensity corrections; all ones when uncalibrated).
pub(crate) struct PixelFitter<'a> {
    dirs: &'a [Vector3<f64>],
    /// The six distinct entries of l·lᵀ for each light.
    outer: Vec<Sym3>,
    halves: Vec<Vector3<f64>>,
    gains: &'a [f32],
    shadow_threshold: f32,
    highlight_fraction: f32,
    reject_saturated: bool,
    max_condition: f64,
    v: Vec<f64>,
    base: Vec<bool>,
    /// The threshold set of the current pixel, packed for the IRLS and specular estimators.
    compact: Compact,
    w: Vec<f64>,
    order: Vec<usize>,
    /// Scratch for the selection of the shadow threshold's reference level.
    keys: Vec<u64>,
    /// The reference level of the loaded pixel (−∞ without usable samples or rejection).
    reference: f64,
}

impl<'a> PixelFitter<'a> {
    /// A fitter for light directions `dirs` (orthographic view v = (0, 0, 1)).
    pub(crate) fn new(
        dirs: &'a [Vector3<f64>],
        gains: &'a [f32],
        shadow_threshold: f32,
        highlight_fraction: f32,
        reject_saturated: bool,
        max_condition: f64,
    ) -> Self {
        let halves = dirs.iter().map(half_vector).collect();
        let k = dirs.len();
        PixelFitter {
            dirs,
            outer: dirs.iter().map(Sym3::outer).collect(),
            halves,
            gains,
            shadow_threshold,
            highlight_fraction,
            reject_saturated,
            max_condition,
            v: vec![0.0; k],
            base: vec![false; k],
            compact: Compact::default(),
            w: vec![0.0; k],
            order: Vec::with_capacity(k),
            keys: Vec::with_capacity(k),
            reference: f64::NEG_INFINITY,
        }
    }

    /// Sets the direction `view` (unit, towards the camera) of a perspective camera's ray
    /// through the pixel, for the half vectors of the specular estimator (the default is the
    /// orthographic view (0, 0, 1)).
    pub(crate) fn set_view(&mut self, view: &Vector3<f64>) {
        for (h, l) in self.halves.iter_mut().zip(self.dirs) {
            *h = (l + view).try_normalize(1e-12).unwrap_or(*view);
        }
    }

    /// The weights of the last fit (0 for unused samples).
    pub(crate) fn weights(&self) -> &[f64] {
        &self.w
    }

    /// The shadow threshold's reference level of the pixel last loaded (by a fit): its
    /// [`crate::ps::solve::reference_rank`]-th brightest usable sample, −∞ when it has none
    /// or the fit rejected nothing. To be passed back to [`PixelFitter::fit_with_reference`]
    /// as [`Reference::Exact`] when the same pixel is fitted again.
    pub(crate) fn reference(&self) -> f64 {
        self.reference
    }

    /// Loads a pixel's samples and marks the threshold set (finite, unsaturated, above the
    /// shadow threshold relative to the pixel's reference level: the
    /// [`crate::ps::solve::reference_rank`]-th brightest usable sample), or every finite
    /// sample when `reject` is false; `reference` is what is known of the reference level of
    /// these samples. Returns the threshold set's size.
    fn load(
        &mut self,
        values: &[f32],
        saturated: &[bool],
        reject: bool,
        reference: Reference,
    ) -> usize {
        for (k, &v) in values.iter().enumerate() {
            self.v[k] = f64::from(v) * f64::from(self.gains[k]);
        }
        self.reference = if reject {
            reference.level(
                values,
                saturated,
                self.gains,
                self.reject_saturated,
                self.highlight_fraction,
                &mut self.keys,
            )
        } else {
            f64::NEG_INFINITY
        };
        let t = (f64::from(self.shadow_threshold) * self.reference).max(0.0);
        let mut n = 0;
        for (k, &s) in saturated.iter().enumerate() {
            let x = self.v[k];
            let ok = x.is_finite() && (!reject || (x > t && !(self.reject_saturated && s)));
            self.base[k] = ok;
            n += usize::from(ok);
        }
        n
    }

    /// The normal equations Σ l·lᵀ (xx, xy, xz, yy, yz, zz) and Σ l·I of a pixel's usable
    /// samples (the threshold set, or every finite sample when `reject` is false), and their
    /// count: the data a pixel too poorly determined to solve alone still brings to
    /// [`crate::ps::fill`].
    pub(crate) fn usable_normal_equations(
        &mut self,
        values: &[f32],
        saturated: &[bool],
        reject: bool,
    ) -> ([f64; 6], [f64; 3], usize) {
        let n = self.load(values, saturated, reject, Reference::Unknown);
        let mut a = Sym3::default();
        let mut b = Vector3::zeros();
        for (k, l) in self.dirs.iter().enumerate() {
            if self.base[k] {
                a.add(&self.outer[k]);
                b += l * self.v[k];
            }
        }
        (a.0, b.into(), n)
    }

    /// Σ r_k²/(σ_k·gain_k)² over the samples the last fit used: the χ² statistic of its
    /// residuals under per-image noise `sigma` (of the samples before gains).
    pub(crate) fn chi2(&self, g: &Vector3<f64>, sigma: &[f32]) -> f64 {
        let mut sum = 0.0;
        for (k, l) in self.dirs.iter().enumerate() {
            if self.w[k] > 0.0 {
                let s = f64::from(sigma[k]) * f64::from(self.gains[k]);
                sum += ((self.v[k] - g.dot(l)) / s).powi(2);
            }
        }
        sum
    }

    /// Weighted least squares with the current weights: g and the number of used samples.
    fn wls(&self) -> (Option<Vector3<f64>>, usize) {
        let mut a = Sym3::default();
        let mut b = Vector3::zeros();
        let mut n = 0;
        for (k, l) in self.dirs.iter().enumerate() {
            let w = self.w[k];
            if w <= 0.0 {
                continue;
            }
            a.add_scaled(&self.outer[k], w);
            b += l * (w * self.v[k]);
            n += 1;
        }
        let g = if n >= MIN_SAMPLES {
            solve_spd(a.matrix(), b)
        } else {
            None
        };
        (g, n)
    }

    /// Unweighted Gram matrix Σ l·lᵀ of the samples with positive weight, and their count.
    fn used_gram(&self) -> (Matrix3<f64>, usize) {
        let mut gram = Sym3::default();
        let mut n = 0;
        for (o, &w) in self.outer.iter().zip(&self.w) {
            if w > 0.0 {
                gram.add(o);
                n += 1;
            }
        }
        (gram.matrix(), n)
    }

    /// Sets weights to the threshold set (1 inside, 0 outside).
    fn weights_from_base(&mut self) {
        for (w, &b) in self.w.iter_mut().zip(&self.base) {
            *w = if b { 1.0 } else { 0.0 };
        }
    }

    /// Fits one pixel with `estimator`.
    pub(crate) fn fit(
        &mut self,
        values: &[f32],
        saturated: &[bool],
        estimator: Estimator,
    ) -> PixelSolution {
        self.fit_with_reference(values, saturated, estimator, Reference::Unknown)
    }

    /// [`PixelFitter::fit`] with what is known of the pixel's shadow-threshold reference level
    /// ([`Reference`]: the block kernel's, or [`PixelFitter::reference`] after an earlier fit
    /// of the same samples that rejected samples).
    pub(crate) fn fit_with_reference(
        &mut self,
        values: &[f32],
        saturated: &[bool],
        estimator: Estimator,
        reference: Reference,
    ) -> PixelSolution {
        let reject = !matches!(estimator, Estimator::Plain { reject: false, .. });
        let n_base = self.load(values, saturated, reject, reference);
        match estimator {
            Estimator::Plain {
                intensity_weight, ..
            } => {
                for k in 0..self.v.len() {
                    self.w[k] = match (self.base[k], intensity_weight) {
                        (false, _) => 0.0,
                        (true, false) => 1.0,
                        (true, true) => self.v[k] * self.v[k],
                    };
                }
                let (g, _) = self.wls();
                let mut p = self.finish_with(g);
                p.robust = false;
                p
            }
            Estimator::Trimmed { low, high } => self.trimmed(saturated, low, high),
            Estimator::Irls(loss) => {
                if n_base < MIN_SAMPLES {
                    return self.finish(None);
                }
                self.packed(|c| c.irls(loss))
            }
            Estimator::Specular {
                cos_cone,
                min_cos_lit,
            } => {
                if n_base < MIN_SAMPLES {
                    return self.finish(None);
                }
                self.packed(|c| {
                    // Start from the darker half of the samples (highlights only ever add
                    // light), or the L1 fit when that half is too small or clustered: least
                    // squares would lean towards a highlight, and a cone around a leaning
                    // normal keeps the highlight and drops the samples that disagree with it.
                    let first = c.dark_half().or_else(|| c.irls(Loss::L1))?;
                    Some(c.refine(first, cos_cone, min_cos_lit))
                })
            }
        }
    }

    fn trimmed(&mut self, saturated: &[bool], low: f32, high: f32) -> PixelSolution {
        self.order.clear();
        for k in 0..self.v.len() {
            if self.v[k].is_finite() && !(self.reject_saturated && saturated[k]) {
                self.order.push(k);
            }
        }
        let v = &self.v;
        self.order.sort_by(|&a, &b| v[a].total_cmp(&v[b]));
        let n = self.order.len();
        let drop_low = (f64::from(low) * n as f64).floor() as usize;
        let drop_high = (f64::from(high) * n as f64).floor() as usize;
        self.w.fill(0.0);
        if drop_low + drop_high < n {
            for &k in &self.order[drop_low..n - drop_high] {
                self.w[k] = 1.0;
            }
        }
        let (g, _) = self.wls();
        self.finish_with(g)
    }

    /// Runs `estimate` on the packed threshold set and finishes with its weights.
    fn packed(
        &mut self,
        estimate: impl FnOnce(&mut Compact) -> Option<Vector3<f64>>,
    ) -> PixelSolution {
        let mut c = std::mem::take(&mut self.compact);
        c.load(self);
        let g = estimate(&mut c);
        c.scatter_weights(&mut self.w);
        self.compact = c;
        self.finish_with(g)
    }

    fn finish(&mut self, g: Option<Vector3<f64>>) -> PixelSolution {
        self.weights_from_base();
        self.finish_with(g)
    }

    /// Decides the outcome from the samples with positive weight and measures their RMS
    /// residual.
    fn finish_with(&self, g: Option<Vector3<f64>>) -> PixelSolution {
        let (gram, used) = self.used_gram();
        let nan = Vector3::repeat(f64::NAN);
        let unsolved = |status, condition| PixelSolution {
            g: nan,
            residual: f64::NAN,
            samples: used,
            condition,
            status,
            robust: true,
        };
        if used < MIN_SAMPLES {
            return unsolved(PixelStatus::TooFewSamples, f64::INFINITY);
        }
        let condition = condition_from_gram(&gram);
        if condition.is_nan() || condition > self.max_condition {
            return unsolved(PixelStatus::IllConditioned, condition);
        }
        let Some(g) = g else {
            return unsolved(PixelStatus::IllConditioned, condition);
        };
        if !g.iter().all(|v| v.is_finite()) || g.norm() <= 1e-12 {
            return unsolved(PixelStatus::Dark, condition);
        }
        let mut ss = 0.0;
        for (k, l) in self.dirs.iter().enumerate() {
            if self.w[k] > 0.0 {
                ss += (self.v[k] - g.dot(l)).powi(2);
            }
        }
        PixelSolution {
            g,
            residual: (ss / used as f64).sqrt(),
            samples: used,
            condition,
            status: PixelStatus::Solved,
            robust: true,
        }
    }
}

/// The threshold-set samples of one pixel as packed columns (structure of arrays), so the
/// per-sample loops of the IRLS and specular estimators run over contiguous memory without
/// branches.
#[derive(Default)]
struct Compact {
    /// Light index of each packed sample.
    idx: Vec<usize>,
    /// Light direction components.
    l: [Vec<f64>; 3],
    /// Half-vector components.
    h: [Vec<f64>; 3],
    /// Sample values (after gains).
    v: Vec<f64>,
    /// Current weights, and those of the last solvable fit.
    w: Vec<f64>,
    previous_w: Vec<f64>,
    /// Selection flags as 0/1.
    keep: Vec<f64>,
    /// Residuals under the current estimate.
    r: Vec<f64>,
    /// n·l and n·h under the current normal.
    nl: Vec<f64>,
    nh: Vec<f64>,
    /// Scratch for medians and ranks.
    scratch: Vec<f64>,
    /// Scratch for the median of |r| as bit patterns.
    abs_bits: Vec<u64>,
}

impl Compact {
    /// Packs the threshold set of the pixel loaded in `f`.
    fn load(&mut self, f: &PixelFitter) {
        self.idx.clear();
        self.idx.extend((0..f.v.len()).filter(|&k| f.base[k]));
        let m = self.idx.len();
        for d in 0..3 {
            self.l[d].clear();
            self.l[d].extend(self.idx.iter().map(|&k| f.dirs[k][d]));
            self.h[d].clear();
            self.h[d].extend(self.idx.iter().map(|&k| f.halves[k][d]));
        }
        self.v.clear();
        self.v.extend(self.idx.iter().map(|&k| f.v[k]));
        for buf in [
            &mut self.w,
            &mut self.previous_w,
            &mut self.keep,
            &mut self.r,
            &mut self.nl,
            &mut self.nh,
        ] {
            buf.clear();
            buf.resize(m, 0.0);
        }
    }

    /// Writes the packed weights back as per-light weights (0 outside the threshold set).
    fn scatter_weights(&self, w: &mut [f64]) {
        w.fill(0.0);
        for (&p, &k) in self.w.iter().zip(&self.idx) {
            w[k] = p;
        }
    }

    /// Σ sel_j · l_j·l_jᵀ and Σ sel_j.
    fn gram(&self, sel: &[f64]) -> (Matrix3<f64>, f64) {
        let [x, y, z] = &self.l;
        let mut acc = [[0.0; LANES]; 7];
        let chunks = sel
            .chunks_exact(LANES)
            .zip(x.chunks_exact(LANES))
            .zip(y.chunks_exact(LANES).zip(z.chunks_exact(LANES)));
        for ((s, x), (y, z)) in chunks {
            let [xx, xy, xz, yy, yz, zz, n] = &mut acc;
            for lane in 0..LANES {
                let (sx, sy, sz) = (s[lane] * x[lane], s[lane] * y[lane], s[lane] * z[lane]);
                xx[lane] += sx * x[lane];
                xy[lane] += sx * y[lane];
                xz[lane] += sx * z[lane];
                yy[lane] += sy * y[lane];
                yz[lane] += sy * z[lane];
                zz[lane] += sz * z[lane];
                n[lane] += s[lane];
            }
        }
        let mut sums = acc.map(|a| a.iter().sum::<f64>());
        for j in sel.len() - sel.len() % LANES..sel.len() {
            let (s, x, y, z) = (sel[j], x[j], y[j], z[j]);
            for (e, t) in [
                s * x * x,
                s * x * y,
                s * x * z,
                s * y * y,
                s * y * z,
                s * z * z,
                s,
            ]
            .into_iter()
            .enumerate()
            {
                sums[e] += t;
            }
        }
        let [a0, a1, a2, a3, a4, a5, count] = sums;
        (Sym3([a0, a1, a2, a3, a4, a5]).matrix(), count)
    }

    /// Weighted least squares with the packed weights; `None` with fewer than
    /// [`MIN_SAMPLES`] samples of positive weight or a singular system.
    fn wls(&self) -> Option<Vector3<f64>> {
        let used = self.w.iter().filter(|&&w| w > 0.0).count();
        if used < MIN_SAMPLES {
            return None;
        }
        // Normal matrix Σ w·l·lᵀ and right-hand side Σ w·v·l in one pass.
        let [x, y, z] = &self.l;
        let mut acc = [[0.0; LANES]; 9];
        let chunks = self
            .w
            .chunks_exact(LANES)
            .zip(self.v.chunks_exact(LANES))
            .zip(
                x.chunks_exact(LANES)
                    .zip(y.chunks_exact(LANES).zip(z.chunks_exact(LANES))),
            );
        for ((w, v), (x, (y, z))) in chunks {
            let [xx, xy, xz, yy, yz, zz, bx, by, bz] = &mut acc;
            for lane in 0..LANES {
                let (wx, wy, wz) = (w[lane] * x[lane], w[lane] * y[lane], w[lane] * z[lane]);
                xx[lane] += wx * x[lane];
                xy[lane] += wx * y[lane];
                xz[lane] += wx * z[lane];
                yy[lane] += wy * y[lane];
                yz[lane] += wy * z[lane];
                zz[lane] += wz * z[lane];
                bx[lane] += wx * v[lane];
                by[lane] += wy * v[lane];
                bz[lane] += wz * v[lane];
            }
        }
        let mut sums = acc.map(|a| a.iter().sum::<f64>());
        for j in self.w.len() - self.w.len() % LANES..self.w.len() {
            let (wx, wy, wz) = (self.w[j] * x[j], self.w[j] * y[j], self.w[j] * z[j]);
            for (e, t) in [
                wx * x[j],
                wx * y[j],
                wx * z[j],
                wy * y[j],
                wy * z[j],
                wz * z[j],
                wx * self.v[j],
                wy * self.v[j],
                wz * self.v[j],
            ]
            .into_iter()
            .enumerate()
            {
                sums[e] += t;
            }
        }
        let [a0, a1, a2, a3, a4, a5, b0, b1, b2] = sums;
        solve_spd(
            Sym3([a0, a1, a2, a3, a4, a5]).matrix(),
            Vector3::new(b0, b1, b2),
        )
    }

    /// Least squares over the darker half of the samples, when it has at least
    /// [`MIN_ROBUST_SAMPLES`] samples with condition number ≤ [`SELECTION_MAX_CONDITION`].
    fn dark_half(&mut self) -> Option<Vector3<f64>> {
        let half = self.v.len().div_ceil(2);
        if half < MIN_ROBUST_SAMPLES {
            return None;
        }
        // The half-th smallest value; ties at it are taken in sample order up to `half`.
        self.scratch.clear();
        self.scratch.extend_from_slice(&self.v);
        let (_, &mut t, _) = self
            .scratch
            .select_nth_unstable_by(half - 1, f64::total_cmp);
        let below = self.v.iter().filter(|&&x| x < t).count();
        let mut ties = half - below;
        for (w, &x) in self.w.iter_mut().zip(&self.v) {
            *w = if x < t {
                1.0
            } else if x == t && ties > 0 {
                ties -= 1;
                1.0
            } else {
                0.0
            };
        }
        let (gram, _) = self.gram(&self.w);
        if !condition_at_most(&gram, SELECTION_MAX_CONDITION) {
            return None;
        }
        self.wls()
    }

    /// Iteratively reweighted least squares with `loss` over every packed sample, from the
    /// unweighted fit; leaves the final weights in `w`.
    fn irls(&mut self, loss: Loss) -> Option<Vector3<f64>> {
        self.w.fill(1.0);
        self.keep.fill(1.0);
        let mut current = self.wls()?;
        for _ in 0..MAX_IRLS_ITERATIONS {
            self.residuals(&current);
            let s = self.scale();
            if s.is_nan() || s <= 1e-12 * current.norm() {
                break;
            }
            self.previous_w.copy_from_slice(&self.w);
            for (w, r) in self.w.iter_mut().zip(&self.r) {
                *w = loss.weight(r / s);
            }
            let Some(next) = self.wls() else {
                // Too few samples kept weight: return to the last solvable weights.
                std::mem::swap(&mut self.w, &mut self.previous_w);
                break;
            };
            let change = (next - current).norm();
            current = next;
            if change <= IRLS_TOLERANCE * current.norm() {
                break;
            }
        }
        Some(current)
    }

    /// Residuals r_j = v_j − g·l_j of every sample into `r`.
    fn residuals(&mut self, g: &Vector3<f64>) {
        let [x, y, z] = &self.l;
        let rows = x.iter().zip(y.iter().zip(z));
        for ((r, v), (x, (y, z))) in self.r.iter_mut().zip(&self.v).zip(rows) {
            *r = v - (g.x * x + g.y * y + g.z * z);
        }
    }

    /// Robust scale 1.4826·median|r| of the residuals of the samples with `keep`.
    fn scale(&mut self) -> f64 {
        // |r| has a clear sign bit, and for such values the order of the IEEE-754 bit patterns
        // is the numeric (total) order: selecting on integers gives the same median, faster.
        self.abs_bits.clear();
        let kept = self.r.iter().zip(&self.keep).filter(|(_, k)| **k > 0.0);
        self.abs_bits.extend(kept.map(|(r, _)| r.abs().to_bits()));
        let median = crate::stats::median_by(&mut self.abs_bits, u64::cmp).map(f64::from_bits);
        MAD_TO_SIGMA * median.unwrap_or(0.0)
    }

    /// For the estimate `g`, in one pass: n·l and n·h of every sample under its normal
    /// n = g/|g|, and the residuals r = v − g·l (as v − |g|·n·l).
    fn project(&mut self, g: &Vector3<f64>) {
        let norm = g.norm();
        let n = g / norm;
        let [lx, ly, lz] = &self.l;
        let [hx, hy, hz] = &self.h;
        let out = self.nl.iter_mut().zip(self.nh.iter_mut().zip(&mut self.r));
        let light = lx.iter().zip(ly.iter().zip(lz));
        let half = hx.iter().zip(hy.iter().zip(hz));
        for (((nl, (nh, r)), (x, (y, z))), ((hx, (hy, hz)), v)) in
            out.zip(light).zip(half.zip(&self.v))
        {
            let d = n.x * x + n.y * y + n.z * z;
            *nl = d;
            *nh = n.x * hx + n.y * hy + n.z * hz;
            *r = v - norm * d;
        }
    }

    /// Selects, from the n·l and n·h of the last [`Compact::project`], the widest specular
    /// cone (full, 2/3, 1/3, none) that leaves at least [`MIN_ROBUST_SAMPLES`] lit samples
    /// with condition number at most [`SELECTION_MAX_CONDITION`]; with none, every sample.
    /// Leaves the selection in `keep`.
    fn select(&mut self, cones: &[f64; CONE_STEPS + 1], min_cos_lit: f64) {
        for &cos_c in cones {
            for (k, (nl, nh)) in self.keep.iter_mut().zip(self.nl.iter().zip(&self.nh)) {
                *k = if *nl > min_cos_lit && *nh < cos_c {
                    1.0
                } else {
                    0.0
                };
            }
            let (gram, count) = self.gram(&self.keep);
            if count >= MIN_ROBUST_SAMPLES as f64
                && condition_at_most(&gram, SELECTION_MAX_CONDITION)
            {
                return;
            }
        }
        self.keep.fill(1.0);
    }

    /// Alternates specular selection and Tukey IRLS from the estimate `start`, fitted with
    /// the current weights, for at most [`SPECULAR_ROUNDS`] rounds; leaves the final weights
    /// in `w` and returns the estimate.
    fn refine(&mut self, start: Vector3<f64>, cos_cone: f64, min_cos_lit: f64) -> Vector3<f64> {
        let mut current = start;
        self.previous_w.copy_from_slice(&self.w);
        // Cosines of the cone half-angles, widest first; the last step keeps every lit sample.
        let cone = cos_cone.acos();
        let cones: [f64; CONE_STEPS + 1] = std::array::from_fn(|step| {
            if step == CONE_STEPS {
                f64::INFINITY
            } else {
                (cone * (CONE_STEPS - step) as f64 / CONE_STEPS as f64).cos()
            }
        });
        for round in 0..SPECULAR_ROUNDS {
            self.project(&current);
            self.select(&cones, min_cos_lit);
            let s = if round == 0 { 0.0 } else { self.scale() };
            if s > 1e-12 * current.norm() {
                // Tukey's weight (1 − u²)² for |u| < 1, u = r/(c·s), without branches.
                let inv = 1.0 / (TUKEY_C * s);
                let kept = self.r.iter().zip(&self.keep);
                for (w, (r, k)) in self.w.iter_mut().zip(kept) {
                    let u = r * inv;
                    let t = (1.0 - u * u).max(0.0);
                    *w = k * t * t;
                }
            } else {
                self.w.copy_from_slice(&self.keep);
            }
            let Some(next) = self.wls() else {
                // Too few samples kept weight: return to the last solvable weights.
                std::mem::swap(&mut self.w, &mut self.previous_w);
                break;
            };
            self.previous_w.copy_from_slice(&self.w);
            let change = (next - current).norm();
            current = next;
            if round > 0 && change <= SPECULAR_TOLERANCE * current.norm() {
                break;
            }
        }
        current
    }
}

/// Lanes of the packed accumulators: independent partial sums let the compiler use vector
/// registers and hide the latency of floating-point addition.
const LANES: usize = 2;

/// A symmetric 3×3 matrix stored as its six distinct entries (xx, xy, xz, yy, yz, zz), for
/// accumulating normal equations without the redundant half.
#[derive(Debug, Clone, Copy, Default)]
struct Sym3([f64; 6]);

impl Sym3 {
    /// l·lᵀ.
    fn outer(l: &Vector3<f64>) -> Self {
        Sym3([
            l.x * l.x,
            l.x * l.y,
            l.x * l.z,
            l.y * l.y,
            l.y * l.z,
            l.z * l.z,
        ])
    }

    fn add(&mut self, o: &Sym3) {
        for (a, b) in self.0.iter_mut().zip(&o.0) {
            *a += b;
        }
    }

    fn add_scaled(&mut self, o: &Sym3, w: f64) {
        for (a, b) in self.0.iter_mut().zip(&o.0) {
            *a += w * b;
        }
    }

    fn matrix(&self) -> Matrix3<f64> {
        let [xx, xy, xz, yy, yz, zz] = self.0;
        Matrix3::new(xx, xy, xz, xy, yy, yz, xz, yz, zz)
    }
}

/// The half vector h = (l + v)/|l + v| of light direction `l` and the orthographic view
/// v = (0, 0, 1) (v itself for a light straight behind the surface).
pub(crate) fn half_vector(l: &Vector3<f64>) -> Vector3<f64> {
    let view = Vector3::z();
    (l + view).try_normalize(1e-12).unwrap_or(view)
}

/// Upper quantile of the χ² distribution with `dof` degrees of freedom at standard-normal
/// deviate `z` (e.g. 3.09 for a 0.1% tail), by the Wilson–Hilferty cube-root approximation
/// (Wilson & Hilferty 1931), accurate to a few per cent for dof ≥ 1 at these tails.
pub fn chi2_upper_quantile(dof: f64, z: f64) -> f64 {
    let a = 2.0 / (9.0 * dof);
    dof * (1.0 - a + z * a.sqrt()).powi(3)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::lights::Lights;
    use rand::{RngExt, SeedableRng};

    fn setup() -> (Vec<Vector3<f64>>, Vec<f32>) {
        let lights = Lights::fibonacci(40, 60.0).unwrap();
        (lights.directions().to_vec(), vec![1.0; 40])
    }

    fn angle(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
        (a.dot(b) / (a.norm() * b.norm()))
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees()
    }

    /// Each estimator recovers g exactly from clean Lambertian samples with attached shadows.
    #[test]
    fn exact_on_lambertian_samples() {
        let (dirs, gains) = setup();
        let g = Vector3::new(0.2, -0.3, 0.6);
        let vals: Vec<f32> = dirs.iter().map(|l| g.dot(l).max(0.0) as f32).collect();
        let sat = vec![false; dirs.len()];
        let mut f = PixelFitter::new(&dirs, &gains, 0.05, 0.0, true, 100.0);
        for est in [
            Estimator::Irls(Loss::Huber),
            Estimator::Irls(Loss::Tukey),
            Estimator::Irls(Loss::L1),
            Estimator::Specular {
                cos_cone: 30f64.to_radians().cos(),
                min_cos_lit: 0.1,
            },
        ] {
            let p = f.fit(&vals, &sat, est);
            assert_eq!(p.status, PixelStatus::Solved, "{est:?}");
            assert!((p.g - g).norm() < 1e-5 * g.norm(), "{est:?}: {:?}", p.g);
        }
    }

    /// Sparse gross outliers (a fifth of the lit samples, 2–4× too bright or black) bias
    /// least squares by degrees; the redescending and L1 estimators stay within 0.5°.
    #[test]
    fn robust_to_sparse_outliers() {
        let (dirs, gains) = setup();
        let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(3);
        let sat = vec![false; dirs.len()];
        let mut f = PixelFitter::new(&dirs, &gains, 0.05, 0.0, true, 100.0);
        let mut worst_plain: f64 = 0.0;
        let mut worst = [0.0f64; 3];
        for _ in 0..50 {
            let n = Vector3::new(
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.5..0.5),
                1.0,
            )
            .normalize();
            let g = n * 0.7;
            let vals: Vec<f32> = dirs
                .iter()
                .map(|l| {
                    let v = g.dot(l).max(0.0);
                    let u: f64 = rng.random_range(0.0..1.0);
                    let v = if v > 0.0 && u < 0.1 {
                        v * rng.random_range(2.0..4.0)
                    } else if v > 0.0 && u < 0.2 {
                        0.0
                    } else {
                        v + rng.random_range(-0.002..0.002)
                    };
                    v as f32
                })
                .collect();
            let plain = f.fit(
                &vals,
                &sat,
                Estimator::Trimmed {
                    low: 0.0,
                    high: 0.0,
                },
            );
            worst_plain = worst_plain.max(angle(&plain.g, &g));
            for (i, loss) in [Loss::Huber, Loss::Tukey, Loss::L1].into_iter().enumerate() {
                let p = f.fit(&vals, &sat, Estimator::Irls(loss));
                worst[i] = worst[i].max(angle(&p.g, &g));
            }
        }
        assert!(
            worst_plain > 3.0,
            "outliers should hurt least squares: {worst_plain}"
        );
        assert!(worst[1] < 0.5, "tukey {:?}", worst);
        assert!(worst[2] < 0.5, "l1 {:?}", worst);
        // Huber bounds the influence but does not remove it.
        assert!(worst[0] < worst_plain / 2.0, "huber {:?}", worst);
    }

    /// A Blinn–Phong lobe on top of the Lambertian term: the half-vector rejection removes it.
    #[test]
    fn specular_lobe_rejected() {
        let (dirs, gains) = setup();
        let sat = vec![false; dirs.len()];
        let n = Vector3::new(0.3, 0.2, 1.0).normalize();
        let view = Vector3::z();
        let vals: Vec<f32> = dirs
            .iter()
            .map(|l| {
                let c = n.dot(l).max(0.0);
                let h = (l + view).normalize();
                (0.5 * c + 0.8 * n.dot(&h).max(0.0).powi(60) * c) as f32
            })
            .collect();
        let mut f = PixelFitter::new(&dirs, &gains, 0.05, 0.0, true, 100.0);
        let plain = f.fit(
            &vals,
            &sat,
            Estimator::Trimmed {
                low: 0.0,
                high: 0.0,
            },
        );
        let spec = f.fit(
            &vals,
            &sat,
            Estimator::Specular {
                cos_cone: 30f64.to_radians().cos(),
                min_cos_lit: 0.1,
            },
        );
        assert!(angle(&plain.g, &n) > 2.0, "{}", angle(&plain.g, &n));
        // What is left is the lobe's tail beyond the cone (0.05° measured).
        assert!(angle(&spec.g, &n) < 0.1, "{}", angle(&spec.g, &n));
        assert!((spec.g.norm() - 0.5).abs() < 1e-3);
    }

    #[test]
    fn rank_trimming_drops_extremes() {
        let (dirs, gains) = setup();
        let sat = vec![false; dirs.len()];
        let g = Vector3::new(0.0, 0.0, 0.5);
        let mut vals: Vec<f32> = dirs.iter().map(|l| g.dot(l).max(0.0) as f32).collect();
        // The brightest sample becomes a highlight; trimming 10% from the top removes it.
        let top = (0..vals.len())
            .max_by(|&a, &b| vals[a].total_cmp(&vals[b]))
            .unwrap();
        vals[top] *= 5.0;
        let mut f = PixelFitter::new(&dirs, &gains, 0.05, 0.0, true, 100.0);
        let p = f.fit(
            &vals,
            &sat,
            Estimator::Trimmed {
                low: 0.2,
                high: 0.1,
            },
        );
        assert!((p.g - g).norm() < 1e-5, "{:?}", p.g);
        assert_eq!(p.samples, 40 - 8 - 4);
    }

    #[test]
    fn chi2_quantile_matches_tables() {
        // χ²_{0.999}: dof 1 → 10.83, 10 → 29.59, 93 → 140.89 (tables).
        let z = 3.0902;
        assert!((chi2_upper_quantile(10.0, z) - 29.59).abs() < 0.3);
        assert!((chi2_upper_quantile(93.0, z) - 140.89).abs() < 1.0);
        assert!((chi2_upper_quantile(1.0, z) - 10.83).abs() < 0.6);
    }
}
