//! A non-Lambertian model only where the data need it: the pixels that `auto`'s fit test says
//! Lambert's law does not explain are refitted with an isotropic reflectance of a diffuse term
//! plus a dictionary of specular lobes, using the samples that the specular estimator discards,
//! and the refit is kept where it explains them better than Lambert's law with outliers.
//!
//! **Model.** For a pixel of normal n, orthographic view v = (0, 0, 1), light l_k and half
//! vector h_k = (l_k + v)/|l_k + v|, the sample (divided by the light's intensity) is the
//! reflectance times the foreshortening,
//!
//! ```text
//! I_k = max(0, n·l_k) (ρ + Σ_j c_j exp(−(1 − n·h_k)/w_j)),   ρ ≥ 0, c_j ≥ 0,
//! ```
//!
//! a reflectance that depends on the half-vector angle alone (isotropic, as the lobes of
//! Blinn–Phong, Torrance–Sparrow and Ward nearly do; exp(−(1 − cos θ_h)/w) ≈ cos^{1/w} θ_h).
//! The non-negative weights c_j of a fixed dictionary of widths stand in for the unknown lobe,
//! as the bi-polynomial reflectance of Shi, Tan, Matsushita and Ikeuchi ("Bi-polynomial
//! modeling of low-frequency reflectances", TPAMI 2014) and the bivariate one of Alldrin,
//! Zickler and Kriegman ("Photometric stereo with non-parametric and spatially-varying
//! reflectance", CVPR 2008) stand in for an unknown BRDF. The widths [`WIDTHS`] run from 0.3
//! (a broad sheen, about cos³ θ_h) to 1/270 (about cos²⁷⁰ θ_h), a factor 3 apart; each
//! exponential is the cube of the next wider one, so one `exp` a sample serves them all. The
//! dictionary was set before any measurement, to span the renderer's lobes (Blinn–Phong
//! n = 5–200, Torrance–Sparrow m = 0.1–0.5). A form without the n·l factor (the lobe alone, as
//! a microfacet lobe's D/(4 n·v) is) was tried first: DiLiGenT cat 4.56° against 4.43°, and on
//! rendered Blinn–Phong and Torrance–Sparrow scenes it made `auto` worse at k_s ≥ 0.2.
//!
//! **Fit.** Variable projection: for a given n the weights (ρ, c) are the non-negative least
//! squares solution (Lawson and Hanson, *Solving Least Squares Problems*, 1974, ch. 23), and n
//! moves by damped Gauss–Newton steps in its tangent plane on the projected Jacobian (Kaufman,
//! "A variable projection method for solving separable nonlinear least squares problems",
//! BIT 1975). It starts from the robust estimate's normal and runs [`ROUNDS`] rounds, each but
//! the first Tukey-reweighted (scale 1.4826 × the median absolute residual, never below the
//! image noise), so
//! cast shadows and interreflections that the model does not describe lose their weight. The
//! samples are the threshold set of the shadow rule: no sample the Lambertian fit calls
//! shadowed or saturated is used.
//!
//! **Which pixels keep it.** Three tests, each a decline to the robust estimate:
//! 1. *Lambert's law with outliers explains the samples as well.* Both models are scored by
//!    Tukey's ρ (a bounded negative log-likelihood) at the lobe fit's robust scale, Lambert's
//!    law by Tukey IRLS on the same samples; the lobes are kept when they lower the score by
//!    more than the Bayesian information criterion charges for their extra parameters,
//!    ½ (k − 3) ln n. A rough diffuse surface (Oren–Nayar) is declined here.
//! 2. *The light set cannot resolve the lobe.* When the fit's dominant lobe is narrower than
//!    the spacing of the half vectors ([`resolvable_lobes`]), its shape, not the surface,
//!    decides where the normal goes: a sharp Blinn–Phong n = 200 lobe under 32 lights went from
//!    0.27° to 0.54° before this test, and is now left as the robust fit had it.
//! 3. *The lobes do not explain the pixel either.* The relative residual (weighted RMS residual
//!    over ρ) is an outlier among the refitted pixels: above their median plus
//!    [`crate::ps::solve::SolveOptions::fit_test_z`] (3.09, the fit test's deviate) times
//!    1.4826 × their median absolute deviation. An interreflection in a fold, a cast shadow
//!    above the threshold: there the robust estimate, which discards samples instead of
//!    modelling them, is kept.
//!
//! A pixel with fewer than [`MIN_SAMPLES_PER_PARAMETER`] usable samples a parameter, no diffuse
//! term or a normal facing away from the camera keeps it too.
//!
//! **Measured** (docs/photometric-stereo.md): DiLiGenT cat 5.33° → 4.43°, bear 4.23° → 3.94°,
//! reading 11.79° → 11.03° (mean angular error, default command); on rendered scenes under 32
//! and 96 lights the error falls by up to a factor 9 (Blinn–Phong n = 10) and rises on none.
//! It costs 1.1–1.5 s of the solve on a DiLiGenT object (2 cores), 1.5–1.8 s of the whole run.
//!
//! **Where it breaks.** Anisotropic, retro-reflective or strongly Fresnel-dependent surfaces
//! (the lobe depends on more than θ_h); near lights and perspective views (v and h change
//! across the image); fewer than 16 usable samples a pixel (with 12 lights the lobes are not
//! fitted). The diffuse term is Lambertian: a rough (Oren–Nayar) surface keeps its robust
//! estimate and its error.

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::error::{Error, Result};
use crate::grid::Mask;
use crate::ps::robust::{Estimator, Loss, MAD_TO_SIGMA, TUKEY_C, half_vector};
use crate::ps::solve::{PixelStatus, Solution, SolveOptions};
use crate::stats::median_by;
use nalgebra::{SMatrix, SVector, Vector3};
use rayon::prelude::*;
use serde::Serialize;
use std::time::Instant;

/// Lobe widths w_j of the dictionary (in 1 − cos θ_h), widest first; each is the previous
/// one's third, so exp(−(1 − x)/w_{j+1}) is the cube of exp(−(1 − x)/w_j).
pub const WIDTHS: [f64; 5] = [0.3, 0.1, 0.1 / 3.0, 0.1 / 9.0, 0.1 / 27.0];

/// Unknowns of the linear part: ρ and one weight a lobe.
const TERMS: usize = 1 + WIDTHS.len();

/// Parameters of the whole fit: the two of the normal and the linear ones.
const PARAMETERS: usize = 2 + TERMS;

/// A refit needs at least this many used samples for each of its [`PARAMETERS`]: as many
/// residual degrees of freedom as parameters, so that its relative residual measures the
/// model's fit and not the parameters' freedom.
pub const MIN_SAMPLES_PER_PARAMETER: usize = 2;

/// Tukey-reweighting rounds (the first unweighted).
pub const ROUNDS: usize = 3;

/// Gauss–Newton steps at most in a round.
const MAX_STEPS: usize = 20;

/// A round stops when a step moves the normal less than this (radians; 0.06°, a small
/// fraction of the errors that real captures leave: ending at 10⁻⁴ changed no DiLiGenT mean
/// by more than 0.005° and took a third more steps).
const STEP_TOLERANCE: f64 = 1e-3;

/// The upper median, reordering `values`; `None` when empty.
fn median(values: &mut [f64]) -> Option<f64> {
    median_by(values, f64::total_cmp)
}

type Mat = SMatrix<f64, TERMS, TERMS>;
type Vec6 = SVector<f64, TERMS>;

/// What the refit with specular lobes did, over the pixels of a solve (summed over the bands
/// of a streamed run).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct LobeSummary {
    /// Solved pixels that failed the Lambertian fit test (`auto`'s robust pixels).
    pub examined: usize,
    /// Of those, pixels that Lambert's law with outliers explains as well as the lobes, given
    /// their extra parameters (Bayesian information criterion): they keep the robust estimate.
    pub explained_by_outliers: usize,
    /// Pixels whose dominant lobe is narrower than the light set resolves
    /// ([`resolvable_lobes`]): they keep the robust estimate.
    pub unresolved: usize,
    /// Pixels the lobes explain better, whose relative residual was then judged.
    pub refitted: usize,
    /// Refitted pixels whose normal and albedo now come from the lobe model.
    pub applied: usize,
    /// Refitted pixels whose relative residual was an outlier (kept the robust estimate).
    pub declined: usize,
    /// The relative-residual limit (the last band's in a streamed run).
    pub limit: f64,
    /// Median relative residual of the refitted pixels (the last band's in a streamed run).
    pub median_relative_residual: f64,
    /// Time taken, seconds (not written with the summary: `report.json` holds no timing outside
    /// its `timings_s`, so that a run's report is reproducible).
    #[serde(skip_serializing)]
    pub seconds: f64,
}

impl LobeSummary {
    /// Adds the counts of another part of the image (a band of rows).
    pub fn add(&mut self, other: &LobeSummary) {
        self.examined += other.examined;
        self.explained_by_outliers += other.explained_by_outliers;
        self.unresolved += other.unresolved;
        self.refitted += other.refitted;
        self.applied += other.applied;
        self.declined += other.declined;
        self.limit = other.limit;
        self.median_relative_residual = other.median_relative_residual;
        self.seconds += other.seconds;
    }
}

/// One pixel's refit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LobeFit {
    /// Unit normal.
    pub normal: Vector3<f64>,
    /// Diffuse albedo ρ.
    pub albedo: f64,
    /// Lobe weights c_j, in the order of [`WIDTHS`].
    pub lobes: [f64; WIDTHS.len()],
    /// Weighted RMS residual.
    pub residual: f64,
    /// Samples with positive weight in the last round.
    pub used: usize,
    /// Whether the lobes explain the samples better than Lambert's law with outliers by more
    /// than their extra parameters cost.
    pub preferred: bool,
}

impl LobeFit {
    /// The index in [`WIDTHS`] of the lobe of largest weight; `None` without lobes.
    pub fn dominant_lobe(&self) -> Option<usize> {
        (0..WIDTHS.len())
            .filter(|&j| self.lobes[j] > 0.0)
            .max_by(|&i, &j| self.lobes[i].total_cmp(&self.lobes[j]))
    }

    /// Weighted RMS residual over the diffuse albedo (∞ without a diffuse term).
    pub fn relative_residual(&self) -> f64 {
        if self.albedo > 0.0 {
            self.residual / self.albedo
        } else {
            f64::INFINITY
        }
    }

    /// The model's value for light direction `l` (unit, towards the light).
    pub fn predict(&self, l: &Vector3<f64>) -> f64 {
        let nl = self.normal.dot(l);
        if nl <= 0.0 {
            return 0.0;
        }
        let mut b = [0.0; TERMS];
        basis(self.normal.dot(&half_vector(l)), nl, &mut b);
        self.albedo * b[0]
            + self
                .lobes
                .iter()
                .zip(&b[1..])
                .map(|(c, e)| c * e)
                .sum::<f64>()
    }
}

/// The basis at n·h = `x`, n·l = `nl` (> 0): the diffuse n·l, then each lobe times n·l.
fn basis(x: f64, nl: f64, b: &mut [f64; TERMS]) {
    b[0] = nl;
    let mut e = (-(1.0 - x.min(1.0)) / WIDTHS[0]).exp();
    for v in b.iter_mut().skip(1) {
        *v = e * nl;
        e = e * e * e;
    }
}

/// Σ aₖbₖ in four interleaved partial sums, added in a fixed order: independent chains that
/// the compiler vectorises, with a result that does not depend on the machine.
#[inline]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    debug_assert_eq!(a.len(), b.len());
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0; 4];
    let (mut ca, mut cb) = (a.chunks_exact(4), b.chunks_exact(4));
    for (x, y) in (&mut ca).zip(&mut cb) {
        for lane in 0..4 {
            acc[lane] += x[lane] * y[lane];
        }
    }
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// `out` = `w` × `v`, element by element.
#[inline]
fn weighted(w: &[f64], v: &[f64], out: &mut Vec<f64>) {
    out.clear();
    out.extend(w.iter().zip(v).map(|(w, v)| w * v));
}

/// The samples of one pixel in the form the fit uses, one array a quantity (so that the passes
/// over the samples vectorise).
#[derive(Default)]
pub(crate) struct Samples {
    /// Light directions, by component.
    l: [Vec<f64>; 3],
    /// Half vectors, by component.
    h: [Vec<f64>; 3],
    y: Vec<f64>,
    /// Noise σ of each sample (after gains).
    sigma: Vec<f64>,
    /// Current robust weights.
    w: Vec<f64>,
    /// Scratch: n·l, and the first lobe's exponent and then its value, at the normal being
    /// evaluated; the weights times the residuals there.
    nl: Vec<f64>,
    e: Vec<f64>,
    wr: Vec<f64>,
    /// Scratch: the model's derivative along each tangent, the projected Jacobian's two columns
    /// and those times the weights.
    d: [Vec<f64>; 2],
    j: [Vec<f64>; 2],
    wj: [Vec<f64>; 2],
    /// Scratch of [`fit_samples`]'s medians.
    abs: Vec<f64>,
    /// Scratch of [`lambert_robust_cost`]: the weights, and the light directions' components
    /// times them.
    lambert: [Vec<f64>; 4],
    /// The evaluation at the current normal.
    cur: Evaluation,
    /// The evaluation at the last trial normal ([`Samples::project`]); it becomes the current
    /// one when accepted ([`Samples::accept`]), so a rejected trial costs no re-evaluation.
    trial: Evaluation,
}

/// The model evaluated at one normal.
#[derive(Default)]
struct Evaluation {
    /// Each basis function at every sample.
    basis: [Vec<f64>; TERMS],
    /// The same times the robust weights.
    wb: [Vec<f64>; TERMS],
    /// Residuals at the non-negative least-squares weights.
    r: Vec<f64>,
    /// The weighted Gram matrix of the basis.
    gram: Mat,
    /// The passive set of the linear solve.
    passive: [bool; TERMS],
}

impl Samples {
    fn clear(&mut self) {
        self.cur.passive = [false; TERMS];
        for v in self.l.iter_mut().chain(&mut self.h) {
            v.clear();
        }
        self.y.clear();
        self.sigma.clear();
        self.w.clear();
    }

    fn push(&mut self, l: Vector3<f64>, h: Vector3<f64>, y: f64, sigma: f64) {
        for c in 0..3 {
            self.l[c].push(l[c]);
            self.h[c].push(h[c]);
        }
        self.y.push(y);
        self.sigma.push(sigma);
        self.w.push(1.0);
    }

    fn len(&self) -> usize {
        self.y.len()
    }

    /// Evaluates the basis at `n` for every sample into the trial evaluation, and returns the
    /// weighted Gram matrix and right-hand side of the linear problem.
    fn normal_equations(&mut self, n: &Vector3<f64>) -> (Mat, Vec6) {
        let len = self.len();
        let [lx, ly, lz] = &self.l;
        let [hx, hy, hz] = &self.h;
        self.nl.clear();
        self.nl
            .extend((0..len).map(|k| n.x * lx[k] + n.y * ly[k] + n.z * lz[k]));
        self.e.clear();
        self.e.extend((0..len).map(|k| {
            let x = n.x * hx[k] + n.y * hy[k] + n.z * hz[k];
            -(1.0 - x.min(1.0)) / WIDTHS[0]
        }));
        for v in &mut self.e {
            *v = v.exp();
        }
        let ev = &mut self.trial;
        for b in &mut ev.basis {
            b.resize(len, 0.0);
        }
        for k in 0..len {
            // Each lobe is the cube of the next wider one, times n·l; nothing below the
            // horizon.
            let nl = self.nl[k].max(0.0);
            let mut e = if nl > 0.0 { self.e[k] } else { 0.0 };
            ev.basis[0][k] = nl;
            for b in &mut ev.basis[1..] {
                b[k] = e * nl;
                e = e * e * e;
            }
        }
        for (wb, b) in ev.wb.iter_mut().zip(&ev.basis) {
            weighted(&self.w, b, wb);
        }
        let mut a = Mat::zeros();
        let mut rhs = Vec6::zeros();
        for i in 0..TERMS {
            rhs[i] = dot(&ev.wb[i], &self.y);
            for j in i..TERMS {
                let v = dot(&ev.wb[i], &ev.basis[j]);
                a[(i, j)] = v;
                a[(j, i)] = v;
            }
        }
        (a, rhs)
    }

    /// Evaluates the model at `n` into the trial evaluation (the linear solve warm-started
    /// from the current one's passive set): the linear weights and the weighted sum of
    /// squared residuals.
    fn project(&mut self, n: &Vector3<f64>) -> (Vec6, f64) {
        let (a, rhs) = self.normal_equations(n);
        let (c, passive) = nnls(&a, &rhs, self.cur.passive);
        let ev = &mut self.trial;
        ev.gram = a;
        ev.passive = passive;
        ev.r.clear();
        ev.r.extend_from_slice(&self.y);
        for (b, &ci) in ev.basis.iter().zip(c.iter()) {
            if ci != 0.0 {
                for (r, b) in ev.r.iter_mut().zip(b) {
                    *r -= b * ci;
                }
            }
        }
        weighted(&self.w, &ev.r, &mut self.wr);
        let cost = dot(&self.wr, &ev.r);
        (c, cost)
    }

    /// Makes the trial evaluation the current one.
    fn accept(&mut self) {
        std::mem::swap(&mut self.cur, &mut self.trial);
    }
}

/// Non-negative least squares min |Bc − y|² s.t. c ≥ 0 from its normal equations
/// `a` = BᵀB, `b` = Bᵀy (Lawson and Hanson's active-set algorithm), started from the passive
/// set `guess` when its solution is feasible (the current, last accepted, evaluation's, which a
/// small move of the normal rarely changes). Returns the solution and its passive set.
fn nnls(a: &Mat, b: &Vec6, guess: [bool; TERMS]) -> (Vec6, [bool; TERMS]) {
    let scale = a.diagonal().max().max(f64::MIN_POSITIVE);
    let tol = 1e-12 * scale * b.amax().max(f64::MIN_POSITIVE);
    let mut passive = [false; TERMS];
    let mut x = Vec6::zeros();
    if guess.iter().any(|&p| p)
        && let Some(z) = solve_passive(a, b, &guess)
        && (0..TERMS).all(|i| !guess[i] || z[i] > 0.0)
    {
        passive = guess;
        x = z;
    }
    for _ in 0..3 * TERMS {
        let grad = b - a * x;
        let next = (0..TERMS)
            .filter(|&j| !passive[j] && grad[j] > tol && a[(j, j)] > 1e-14 * scale)
            .max_by(|&i, &j| grad[i].total_cmp(&grad[j]));
        let Some(j) = next else { break };
        passive[j] = true;
        for _ in 0..3 * TERMS {
            let Some(z) = solve_passive(a, b, &passive) else {
                return (x, passive);
            };
            if (0..TERMS).all(|i| !passive[i] || z[i] > 0.0) {
                x = z;
                break;
            }
            let mut alpha = 1.0f64;
            for i in 0..TERMS {
                if passive[i] && z[i] <= 0.0 {
                    alpha = alpha.min(x[i] / (x[i] - z[i]));
                }
            }
            x += (z - x) * alpha;
            for i in 0..TERMS {
                if passive[i] && x[i] <= 1e-15 * x.amax() {
                    passive[i] = false;
                    x[i] = 0.0;
                }
            }
        }
    }
    (x, passive)
}

/// The Cholesky factor of the normal equations restricted to the passive set (identity
/// elsewhere).
fn factor_passive(
    a: &Mat,
    passive: &[bool; TERMS],
) -> Option<nalgebra::Cholesky<f64, nalgebra::Const<TERMS>>> {
    let mut m = *a;
    for i in 0..TERMS {
        if !passive[i] {
            for j in 0..TERMS {
                m[(i, j)] = 0.0;
                m[(j, i)] = 0.0;
            }
            m[(i, i)] = 1.0;
        }
    }
    m.cholesky()
}

/// `b` with the entries outside the passive set zeroed.
fn restrict(b: &Vec6, passive: &[bool; TERMS]) -> Vec6 {
    Vec6::from_fn(|i, _| if passive[i] { b[i] } else { 0.0 })
}

/// The solution of the normal equations over the passive set (zero elsewhere).
fn solve_passive(a: &Mat, b: &Vec6, passive: &[bool; TERMS]) -> Option<Vec6> {
    factor_passive(a, passive).map(|c| c.solve(&restrict(b, passive)))
}

/// The lobes of [`WIDTHS`] that a light set can resolve: those whose full width at half
/// maximum, 2 acos(1 − w ln 2) in θ_h, is at least the spacing of the half vectors (the median
/// angle from each half vector to its nearest neighbour): at least one sample a width, as a
/// sampling theorem asks. A narrower lobe is seen by one sample or none; fitted, its shape
/// rather than the surface decides where the normal goes.
pub fn resolvable_lobes(halves: &[Vector3<f64>]) -> [bool; WIDTHS.len()] {
    let mut nearest: Vec<f64> = halves
        .iter()
        .enumerate()
        .map(|(i, a)| {
            halves
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, b)| a.dot(b).clamp(-1.0, 1.0).acos())
                .fold(f64::INFINITY, f64::min)
        })
        .filter(|d| d.is_finite())
        .collect();
    let spacing = median(&mut nearest).unwrap_or(f64::INFINITY);
    WIDTHS.map(|w| 2.0 * (1.0 - w * std::f64::consts::LN_2).acos() >= spacing)
}

/// Two unit vectors spanning the plane orthogonal to unit `n`.
fn tangents(n: &Vector3<f64>) -> [Vector3<f64>; 2] {
    let a = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = n.cross(&a).normalize();
    [e1, n.cross(&e1)]
}

/// Damped Gauss–Newton on the normal with the linear weights projected out, from `n`, under
/// the samples' current weights. Returns the normal, the weights and the cost.
fn descend(s: &mut Samples, mut n: Vector3<f64>) -> (Vector3<f64>, Vec6, f64) {
    let (mut c, mut cost) = s.project(&n);
    s.accept();
    let mut damping: f64 = 1e-3;
    for _ in 0..MAX_STEPS {
        let t = tangents(&n);
        let len = s.len();
        // The model's derivative along each tangent, for fixed weights:
        // d/dn of n·l (ρ + Σ c_j e_j) = l (ρ + Σ c_j e_j) + n·l Σ c_j e_j/w_j h, with the
        // basis already carrying the n·l factor.
        let b = &s.cur.basis;
        for d in &mut s.d {
            d.resize(len, 0.0);
        }
        for (k, &b0) in b[0].iter().enumerate() {
            if b0 <= 0.0 {
                s.d[0][k] = 0.0;
                s.d[1][k] = 0.0;
                continue;
            }
            let mut lobe = 0.0;
            let mut sum = 0.0;
            for j in 0..WIDTHS.len() {
                lobe += c[j + 1] * b[j + 1][k] / WIDTHS[j];
                sum += c[j + 1] * b[j + 1][k];
            }
            let along_l = c[0] + sum / b0;
            let grad: [f64; 3] = std::array::from_fn(|a| s.l[a][k] * along_l + s.h[a][k] * lobe);
            for (q, tq) in t.iter().enumerate() {
                s.d[q][k] = grad[0] * tq.x + grad[1] * tq.y + grad[2] * tq.z;
            }
        }
        // Project the derivatives off the span of the active basis (Kaufman's Jacobian).
        let bd: [Vec6; 2] =
            std::array::from_fn(|q| Vec6::from_fn(|i, _| dot(&s.cur.wb[i], &s.d[q])));
        let active: [bool; TERMS] = std::array::from_fn(|i| c[i] > 0.0);
        let coef = match factor_passive(&s.cur.gram, &active) {
            Some(f) => [
                f.solve(&restrict(&bd[0], &active)),
                f.solve(&restrict(&bd[1], &active)),
            ],
            None => [Vec6::zeros(); 2],
        };
        for (q, coef) in coef.iter().enumerate() {
            s.j[q].clear();
            s.j[q].extend_from_slice(&s.d[q]);
            for (bi, &ci) in b.iter().zip(coef.iter()) {
                if ci != 0.0 {
                    for (j, b) in s.j[q].iter_mut().zip(bi) {
                        *j -= b * ci;
                    }
                }
            }
            weighted(&s.w, &s.j[q], &mut s.wj[q]);
        }
        let jtr = nalgebra::Vector2::from_fn(|p, _| dot(&s.wj[p], &s.cur.r));
        let jtj = nalgebra::Matrix2::from_fn(|p, q| dot(&s.wj[p], &s.j[q]));
        let mut moved = false;
        let mut step_norm: f64 = 0.0;
        for _ in 0..8 {
            let mut m = jtj;
            m[(0, 0)] += damping * (jtj[(0, 0)] + f64::MIN_POSITIVE);
            m[(1, 1)] += damping * (jtj[(1, 1)] + f64::MIN_POSITIVE);
            let Some(delta): Option<nalgebra::Vector2<f64>> = m.try_inverse().map(|inv| inv * jtr)
            else {
                break;
            };
            step_norm = delta.norm();
            if !step_norm.is_finite() {
                break;
            }
            let candidate = (n + t[0] * delta[0] + t[1] * delta[1]).normalize();
            if !candidate.iter().all(|v| v.is_finite()) {
                break;
            }
            let (c2, cost2) = s.project(&candidate);
            if cost2 <= cost {
                s.accept();
                n = candidate;
                c = c2;
                cost = cost2;
                damping = (damping / 3.0).max(1e-9);
                moved = true;
                break;
            }
            damping *= 4.0;
        }
        if !moved {
            // The current evaluation is still the kept normal's.
            break;
        }
        if step_norm < STEP_TOLERANCE {
            break;
        }
    }
    (n, c, cost)
}

/// Fits the lobe model to the samples, starting from normal `start`: [`ROUNDS`] rounds of
/// Tukey reweighting around [`descend`]. `None` when fewer than
/// [`MIN_SAMPLES_PER_PARAMETER`] × [`PARAMETERS`] samples keep a weight, or the fit is not
/// finite.
pub(crate) fn fit_samples(s: &mut Samples, start: Vector3<f64>) -> Option<LobeFit> {
    let need = MIN_SAMPLES_PER_PARAMETER * PARAMETERS;
    if s.len() < need || !start.iter().all(|v| v.is_finite()) || start.norm() == 0.0 {
        return None;
    }
    // The scratch for medians, taken out of the samples while they are borrowed.
    let mut abs = std::mem::take(&mut s.abs);
    abs.clear();
    abs.extend_from_slice(&s.sigma);
    let noise = median(&mut abs)?;
    let mut n = start.normalize();
    let mut c = Vec6::zeros();
    let mut cost = 0.0;
    for round in 0..ROUNDS {
        if round > 0 {
            abs.clear();
            abs.extend(s.cur.r.iter().map(|r| r.abs()));
            let scale = (MAD_TO_SIGMA * median(&mut abs)?).max(noise);
            for (w, r) in s.w.iter_mut().zip(&s.cur.r) {
                *w = Loss::Tukey.weight(r / scale);
            }
        }
        (n, c, cost) = descend(s, n);
    }
    let used = s.w.iter().filter(|&&w| w > 0.0).count();
    let weight: f64 = s.w.iter().sum();
    if used < need || weight <= 0.0 {
        s.abs = abs;
        return None;
    }
    abs.clear();
    abs.extend(s.cur.r.iter().map(|r| r.abs()));
    let scale = (MAD_TO_SIGMA * median(&mut abs)?).max(noise);
    s.abs = abs;
    let lobe_cost: f64 = s.cur.r.iter().map(|r| tukey_rho(r / scale)).sum();
    let lambert_cost = lambert_robust_cost(s, start, scale);
    let terms = c.iter().filter(|&&v| v > 0.0).count();
    let penalty = 0.5 * (2 + terms).saturating_sub(3) as f64 * (s.len() as f64).ln();
    let fit = LobeFit {
        normal: n,
        albedo: c[0],
        lobes: std::array::from_fn(|j| c[j + 1]),
        residual: (cost / weight).sqrt(),
        used,
        preferred: lambert_cost - lobe_cost > penalty,
    };
    (fit.normal.iter().all(|v| v.is_finite()) && fit.residual.is_finite()).then_some(fit)
}

/// Tukey's ρ at u = r/scale: u²/2 near 0, c²/6 beyond c (a bounded negative log-likelihood).
fn tukey_rho(u: f64) -> f64 {
    let c2 = TUKEY_C * TUKEY_C;
    let t = (u * u / c2).min(1.0);
    c2 / 6.0 * (1.0 - (1.0 - t).powi(3))
}

/// Σ ρ(r/scale) of Lambert's law with outliers on the samples: g by Tukey IRLS at a fixed
/// scale from the start (a unit normal, scaled by least squares).
fn lambert_robust_cost(s: &mut Samples, start: Vector3<f64>, scale: f64) -> f64 {
    let n0 = start.normalize();
    let [lx, ly, lz] = &s.l;
    let len = s.len();
    let along = |g: &Vector3<f64>, k: usize| g.x * lx[k] + g.y * ly[k] + g.z * lz[k];
    let (mut num, mut den) = (0.0, 0.0);
    for k in 0..len {
        let a = along(&n0, k);
        num += a * s.y[k];
        den += a * a;
    }
    let mut g = n0 * if den > 0.0 { num / den } else { 0.0 };
    let [w, wl @ ..] = &mut s.lambert;
    for _ in 0..10 {
        w.clear();
        w.extend((0..len).map(|k| Loss::Tukey.weight((s.y[k] - along(&g, k)) / scale)));
        for (out, l) in wl.iter_mut().zip(&s.l) {
            weighted(w, l, out);
        }
        let a = nalgebra::Matrix3::from_fn(|i, j| dot(&wl[i.min(j)], &s.l[i.max(j)]));
        let b = Vector3::from_fn(|i, _| dot(&wl[i], &s.y));
        match a.cholesky() {
            Some(ch) => g = ch.solve(&b),
            None => break,
        }
    }
    (0..len)
        .map(|k| tukey_rho((s.y[k] - along(&g, k)) / scale))
        .sum()
}

/// What the refit made of one pixel.
enum Outcome {
    /// Lambert's law with outliers explains the samples as well, given the lobes' extra
    /// parameters.
    Explained,
    /// The dominant lobe is narrower than the light set resolves.
    Unresolved,
    /// Too few samples, or no finite fit with a diffuse term facing the camera.
    NotFitted,
    /// The lobe model's fit.
    Fitted(LobeFit),
}

/// Pixels sampled over the mask to estimate the capture-wide relative-residual limit
/// ([`estimate_limit`]); about a tenth of a DiLiGenT object, a fifth of a second of fitting.
pub const LIMIT_SAMPLE: usize = 4000;

/// Fewest lobe fits from which a limit is estimated; with fewer the limit is not estimated and
/// nothing is declined for its relative residual.
pub const MIN_LIMIT_FITS: usize = 50;

/// The per-pixel part of the refit: gathers a pixel's samples and fits the lobe model.
struct Refitter<'a> {
    stack: &'a ImageStack,
    channel: usize,
    options: &'a SolveOptions,
    dirs: Vec<Vector3<f64>>,
    halves: Vec<Vector3<f64>>,
    resolvable: [bool; WIDTHS.len()],
    gains: &'a [f32],
    sigma: &'a [f32],
}

/// A worker's scratch.
struct Scratch<'f> {
    fitter: crate::ps::robust::PixelFitter<'f>,
    values: Vec<f32>,
    saturated: Vec<bool>,
    samples: Samples,
}

impl<'a> Refitter<'a> {
    fn new(
        stack: &'a ImageStack,
        channel: usize,
        lights: &Lights,
        options: &'a SolveOptions,
        gains: &'a [f32],
        sigma: &'a [f32],
    ) -> Self {
        let dirs = lights.directions();
        let halves: Vec<Vector3<f64>> = dirs.iter().map(half_vector).collect();
        Refitter {
            stack,
            channel,
            options,
            resolvable: resolvable_lobes(&halves),
            dirs,
            halves,
            gains,
            sigma,
        }
    }

    fn scratch(&self) -> Scratch<'_> {
        let count = self.stack.count();
        Scratch {
            fitter: crate::ps::solve::fitter(&self.dirs, self.gains, self.options),
            values: vec![0f32; count],
            saturated: vec![false; count],
            samples: Samples::default(),
        }
    }

    /// Loads pixel `p`'s samples into the scratch; `false` outside the stack's window.
    fn gather(&self, p: usize, s: &mut Scratch) -> bool {
        let Some(local) = self.stack.local(p) else {
            return false;
        };
        for k in 0..self.stack.count() {
            s.values[k] = self.stack.plane(k, self.channel)[local];
            s.saturated[k] = self.stack.is_saturated(k, p);
        }
        true
    }

    /// Refits the gathered pixel from normal `start` (g of the robust fit).
    fn refit(&self, start: Vector3<f64>, s: &mut Scratch) -> Outcome {
        let rule = Estimator::Plain {
            reject: true,
            intensity_weight: false,
        };
        s.fitter.fit(&s.values, &s.saturated, rule);
        s.samples.clear();
        for (k, &w) in s.fitter.weights().iter().enumerate() {
            if w > 0.0 {
                let g = f64::from(self.gains[k]);
                s.samples.push(
                    self.dirs[k],
                    self.halves[k],
                    f64::from(s.values[k]) * g,
                    f64::from(self.sigma[k]) * g,
                );
            }
        }
        match fit_samples(&mut s.samples, start) {
            None => Outcome::NotFitted,
            Some(f) if f.albedo <= 0.0 || f.normal.z <= 0.0 => Outcome::NotFitted,
            Some(f) if !f.preferred => Outcome::Explained,
            Some(f) if !f.dominant_lobe().is_none_or(|j| self.resolvable[j]) => Outcome::Unresolved,
            Some(f) => Outcome::Fitted(f),
        }
    }
}

/// The relative-residual limit of the module documentation's third test, from the lobe fits'
/// relative residuals: their median plus `z` × 1.4826 × their median absolute deviation, and
/// the median; `None` with fewer than [`MIN_LIMIT_FITS`].
fn limit_of(mut relative: Vec<f64>, z: f64) -> Option<(f64, f64)> {
    if relative.len() < MIN_LIMIT_FITS {
        return None;
    }
    let centre = median(&mut relative)?;
    let mut deviations: Vec<f64> = relative.iter().map(|r| (r - centre).abs()).collect();
    let spread = MAD_TO_SIGMA * median(&mut deviations)?;
    Some((centre + z * spread, centre))
}

/// Estimates the capture-wide relative-residual limit of channel `channel` (the module
/// documentation's third test) on up to [`LIMIT_SAMPLE`] pixels spread evenly over the mask:
/// each is fitted as `auto` fits it under the per-image noise `sigma` and `gains`, and refitted
/// with the lobes where the fit test escalates it. Part of [`crate::ps::solve::ImageModel`],
/// so that a capture solved in parts (bands, tiles) judges every part by one limit. `None`
/// when fewer than [`MIN_LIMIT_FITS`] sampled pixels are refitted.
pub(crate) fn estimate_limit(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
    sigma: &[f32],
    gains: &[f32],
) -> Option<f64> {
    let inside: Vec<usize> = (0..mask.data().len())
        .filter(|&p| mask.data()[p] && stack.local(p).is_some())
        .collect();
    let step = inside.len().div_ceil(LIMIT_SAMPLE).max(1);
    let refitter = Refitter::new(stack, channel, lights, options, gains, sigma);
    let relative: Vec<f64> = inside
        .par_iter()
        .step_by(step)
        .with_min_len(64)
        .map_init(
            || refitter.scratch(),
            |s, &p| {
                if !refitter.gather(p, s) {
                    return None;
                }
                let fit = crate::ps::solve::fit_with(
                    &mut s.fitter,
                    &s.values,
                    &s.saturated,
                    sigma,
                    options,
                );
                if fit.status != PixelStatus::Solved || !fit.robust {
                    return None;
                }
                match refitter.refit(fit.g, s) {
                    Outcome::Fitted(f) => Some(f.relative_residual()),
                    _ => None,
                }
            },
        )
        .flatten()
        .collect();
    limit_of(relative, options.fit_test_z).map(|(limit, _)| limit)
}

/// Refits the pixels of `solution` that `auto`'s fit test escalated (its `robust` map) with
/// the lobe model, and keeps the refit where the module documentation's three tests allow.
/// `solution` is the solve of the same stack, channel, lights and mask under `options`;
/// `limit` is the capture-wide relative-residual limit ([`crate::ps::solve::ImageModel`]),
/// `None` to take it from this solve's own refitted pixels.
///
/// # Errors
/// As [`crate::ps::solve::solve`] for mismatched inputs; [`Error::DimensionMismatch`] when
/// `solution` is not of the mask's size; [`Error::InvalidParameter`] when the solution's gains
/// do not match the image count.
pub fn refit_with_lobes(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
    limit: Option<f64>,
    solution: &mut Solution,
) -> Result<LobeSummary> {
    let t = Instant::now();
    crate::ps::solve::check_inputs(stack, channel, lights, mask, options)?;
    mask.check_same_size(&solution.g, "solution vs mask")?;
    mask.check_same_size(&solution.robust, "solution's robust map vs mask")?;
    mask.check_same_size(&solution.status, "solution's status vs mask")?;
    mask.check_same_size(&solution.residual, "solution's residual vs mask")?;
    mask.check_same_size(&solution.samples, "solution's sample counts vs mask")?;
    let count = stack.count();
    if solution.gains.gains.len() != count {
        return Err(Error::param(
            "solution",
            format!("{} gains for {count} images", solution.gains.gains.len()),
        ));
    }
    if let Some(l) = limit
        && !(l.is_finite() && l > 0.0)
    {
        return Err(Error::param(
            "lobe_limit",
            format!("{l} is not a finite relative residual > 0"),
        ));
    }
    let sigma: Vec<f32> = if solution.noise.len() == count {
        solution.noise.clone()
    } else {
        crate::ps::solve::test_sigmas(stack, channel, mask, options)
    };
    let gains = solution.gains.gains.clone();
    let refitter = Refitter::new(stack, channel, lights, options, &gains, &sigma);
    let pixels: Vec<usize> = (0..mask.data().len())
        .filter(|&p| {
            mask.data()[p]
                && solution.robust.data()[p]
                && solution.status.data()[p] == PixelStatus::Solved
        })
        .collect();
    let outcomes: Vec<Outcome> = pixels
        .par_iter()
        .with_min_len(256)
        .map_init(
            || refitter.scratch(),
            |s, &p| {
                if !refitter.gather(p, s) {
                    return Outcome::NotFitted;
                }
                refitter.refit(solution.g.data()[p].map(f64::from), s)
            },
        )
        .collect();
    let count_of = |pred: fn(&Outcome) -> bool| outcomes.iter().filter(|o| pred(o)).count();
    let relative: Vec<f64> = outcomes
        .iter()
        .filter_map(|o| match o {
            Outcome::Fitted(f) => Some(f.relative_residual()),
            _ => None,
        })
        .collect();
    let mut summary = LobeSummary {
        examined: pixels.len(),
        explained_by_outliers: count_of(|o| matches!(o, Outcome::Explained)),
        unresolved: count_of(|o| matches!(o, Outcome::Unresolved)),
        refitted: relative.len(),
        ..LobeSummary::default()
    };
    let own = limit_of(relative, options.fit_test_z);
    summary.median_relative_residual = own.map_or(f64::NAN, |(_, centre)| centre);
    let limit = limit.or(own.map(|(l, _)| l)).unwrap_or(f64::INFINITY);
    summary.limit = limit;
    for (&p, outcome) in pixels.iter().zip(&outcomes) {
        let Outcome::Fitted(fit) = outcome else {
            continue;
        };
        if fit.relative_residual() <= limit {
            solution.g.data_mut()[p] = (fit.normal * fit.albedo).map(|v| v as f32);
            solution.residual.data_mut()[p] = fit.residual as f32;
            solution.samples.data_mut()[p] = fit.used.min(u16::MAX as usize) as u16;
            summary.applied += 1;
        } else {
            summary.declined += 1;
        }
    }
    summary.seconds = t.elapsed().as_secs_f64();
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Non-negative least squares against the exhaustive solution over every passive set.
    #[test]
    fn nnls_matches_exhaustive_search() {
        let mut rng_state = 12345u64;
        let mut next = || {
            rng_state = rng_state.wrapping_mul(6364136223846793005).wrapping_add(1);
            ((rng_state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        };
        for _ in 0..200 {
            let rows = 14;
            let bm: Vec<[f64; TERMS]> =
                (0..rows).map(|_| std::array::from_fn(|_| next())).collect();
            let y: Vec<f64> = (0..rows).map(|_| next()).collect();
            let mut a = Mat::zeros();
            let mut b = Vec6::zeros();
            for (row, yk) in bm.iter().zip(&y) {
                for i in 0..TERMS {
                    b[i] += row[i] * yk;
                    for j in 0..TERMS {
                        a[(i, j)] += row[i] * row[j];
                    }
                }
            }
            let cost = |x: &Vec6| -> f64 {
                bm.iter()
                    .zip(&y)
                    .map(|(row, yk)| {
                        let p: f64 = (0..TERMS).map(|i| row[i] * x[i]).sum();
                        (p - yk).powi(2)
                    })
                    .sum()
            };
            let (x, _) = nnls(&a, &b, [false; TERMS]);
            // A warm start from any passive set reaches the same minimum.
            let (warm, _) = nnls(&a, &b, std::array::from_fn(|i| i % 2 == 0));
            assert!((cost(&warm) - cost(&x)).abs() <= 1e-9 * (1.0 + cost(&x)));
            assert!(x.iter().all(|&v| v >= 0.0));
            let mut best = f64::INFINITY;
            for set in 0u32..(1 << TERMS) {
                let passive: [bool; TERMS] = std::array::from_fn(|i| set & (1 << i) != 0);
                if let Some(z) = solve_passive(&a, &b, &passive)
                    && z.iter().all(|&v| v >= -1e-12)
                {
                    best = best.min(cost(&z));
                }
            }
            assert!(
                cost(&x) <= best + 1e-9 * (1.0 + best),
                "{} vs {best}",
                cost(&x)
            );
        }
    }

    /// `basis` cubes each lobe's exponential to get the next: the widths must be a factor 3
    /// apart.
    #[test]
    fn widths_are_a_factor_three_apart() {
        for pair in WIDTHS.windows(2) {
            assert!((pair[0] / pair[1] - 3.0).abs() < 1e-12, "{pair:?}");
        }
        let mut b = [0.0; TERMS];
        basis(0.97, 0.5, &mut b);
        for (j, w) in WIDTHS.iter().enumerate() {
            let want = (-(1.0 - 0.97) / w).exp() * 0.5;
            assert!((b[j + 1] - want).abs() < 1e-12 * want.max(1e-300), "{j}");
        }
    }

    /// The evaluation a fit ends with is the one at its normal: evaluating the model there
    /// again gives the same weights, cost and residuals (a rejected trial step must not leave
    /// its evaluation behind).
    #[test]
    fn the_kept_evaluation_belongs_to_the_final_normal() {
        let lights = Lights::fibonacci(48, 15.0).unwrap();
        let truth = LobeFit {
            normal: Vector3::new(-0.2, 0.1, 0.95).normalize(),
            albedo: 0.5,
            lobes: [0.1, 0.0, 0.3, 0.0, 0.0],
            residual: 0.0,
            used: 0,
            preferred: true,
        };
        let mut s = Samples::default();
        for (k, l) in lights.directions().into_iter().enumerate() {
            // Deterministic noise of about 1%, and two outliers for the Tukey rounds.
            let wobble = 0.01 * ((k as f64 * 2.39996).sin());
            let outlier = if k % 17 == 3 { 0.3 } else { 0.0 };
            let y = truth.predict(&l) * (1.0 + wobble) + outlier;
            if y > 0.01 {
                s.push(l, half_vector(&l), y, 1e-3);
            }
        }
        let start = (truth.normal + Vector3::new(0.1, -0.05, 0.0)).normalize();
        let fit = fit_samples(&mut s, start).unwrap();
        let kept = s.cur.r.clone();
        let (c, _) = s.project(&fit.normal);
        assert!(
            (c[0] - fit.albedo).abs() < 1e-9,
            "{} vs {}",
            c[0],
            fit.albedo
        );
        for (a, b) in c.iter().skip(1).zip(&fit.lobes) {
            assert!((a - b).abs() < 1e-9, "{c:?} vs {:?}", fit.lobes);
        }
        for (a, b) in s.trial.r.iter().zip(&kept) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
    }

    /// Noise-free samples of the model itself: the normal, albedo and lobe weights come back
    /// from a start 15° off.
    #[test]
    fn recovers_the_model_from_a_distant_start() {
        let lights = Lights::fibonacci(64, 15.0).unwrap();
        let truth = LobeFit {
            normal: Vector3::new(0.3, -0.2, 0.9).normalize(),
            albedo: 0.6,
            lobes: [0.0, 0.05, 0.0, 0.4, 0.0],
            residual: 0.0,
            used: 0,
            preferred: true,
        };
        let mut s = Samples::default();
        for l in lights.directions() {
            let y = truth.predict(&l);
            if y > 0.01 {
                s.push(l, half_vector(&l), y, 1e-4);
            }
        }
        let axis = truth.normal.cross(&Vector3::x()).normalize();
        let start = nalgebra::Rotation3::from_axis_angle(
            &nalgebra::Unit::new_normalize(axis),
            15f64.to_radians(),
        ) * truth.normal;
        let fit = fit_samples(&mut s, start).unwrap();
        let err = fit
            .normal
            .dot(&truth.normal)
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees();
        assert!(err < 1e-4, "{err}°");
        assert!((fit.albedo - truth.albedo).abs() < 1e-6);
        for (c, t) in fit.lobes.iter().zip(&truth.lobes) {
            assert!((c - t).abs() < 1e-5, "{:?}", fit.lobes);
        }
        assert!(fit.residual < 1e-8);
    }
}
