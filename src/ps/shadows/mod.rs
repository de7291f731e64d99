//! Cast shadows as regions: spatially coherent shadow/lit labels per image, after
//! Chandraker, Agarwal & Kriegman, "ShadowCuts: Photometric stereo with shadows", CVPR 2007.
//!
//! The per-pixel estimators of [`crate::ps::solve`] decide each sample alone: below a fraction
//! of the pixel's brightest sample it is a shadow, above it a lit sample (or, for the robust
//! ones, whatever its residual says). But a cast shadow is a region of an image bounded by a
//! curve that neighbouring pixels share: a pixel whose own samples cannot tell (few samples, a
//! shadow lifted above the threshold by ambient light or interreflection, noise at the
//! boundary) should borrow the decision of its neighbours. This pass labels every sample of
//! every image lit (1) or shadow (0) by minimising, for each image k, an energy over the pixel
//! grid; then refits each pixel without the samples labelled shadow, and repeats.
//!
//! **Energy.** For image k, with labels x_p of the masked pixels p and 4-neighbour pairs N:
//!
//! E_k(x) = Σ_p D_p(x_p) + λ Σ_{(p,q)∈N} [x_p ≠ x_q]
//!
//! The unary terms are negative log-likelihoods of the sample v = I_k(p) (intensity-divided,
//! times the image's gain) under each label, given the pixel's current g and m = l_k·g:
//! - **lit**: v = m + e, e of scale s with Student-t tails (ν = 3):
//!   D(1) = ((ν+1)/2)·ln(1 + u²/ν) + ln(s·C_ν), u = (v − m)/(s√c). Real surfaces depart from
//!   Lambert's law by more than a Gaussian allows (interreflections, a darkening towards grazing
//!   angles): with Gaussian tails, DiLiGenT `reading` lost 0.6° and `cat` gained less. The
//!   variance factor c makes u honest: for a sample the current fit used, c = 1 − h, the
//!   deleted residual of regression diagnostics (Cook & Weisberg 1982, *Residuals and
//!   Influence in Regression*), with leverage h = l_kᵀ(Σ_used l lᵀ)⁻¹l_k, so a pixel's own
//!   shadowed sample cannot hide by dragging g towards itself; for one it did not use,
//!   c = 1 + h (prediction variance). A sample of leverage ≥ [`MAX_LEVERAGE`] (a pixel fitted
//!   from about three samples) says nothing about its own label: its unary is zero and its
//!   label comes from the neighbours — the point of the pass. A pixel the solve left unsolved
//!   is predicted from the mean g of its solved 4-neighbours (c = 2), or has zero unaries.
//! - **shadow**: a cast shadow blocks some or all of the light (what is left is ambient light
//!   and interreflection), so v is uniform on [0, m]: D(0) = ln m for v ≤ m, with the lit
//!   term's tail above m (a sample brighter than predicted is not a shadow; highlights are left
//!   to the robust estimators).
//! - **prior**: ln((1 − π_k)/π_k) in favour of lit, π_k the fraction of image k's samples
//!   facing its light (m > 0) labelled shadow in the previous round (the per-pixel rule's
//!   labels at first), within [[`MIN_PRIOR`], 1 − [`MIN_PRIOR`]].
//!
//! A sample with m ≤ 0 is fixed as shadow (attached: Lambert's law gives max(0, l·g), which
//! does not depend on g there); a missing or saturated one has zero unaries (the estimators
//! never use it). The per-image scale is s(m) = √(σ_k² + κ_k²m²): σ_k the image noise
//! ([`crate::ps::noise`]), κ_k the relative model error, set so that the used samples'
//! residuals standardised by s have the median of a standard normal's |z| (0 when noise alone
//! explains them). So a lone sample is labelled shadow when it is darker than predicted by
//! more than a few s, the number set by ln(m/s) and the prior: derived from the data, not tuned.
//!
//! **Pair term.** Potts with weight λ = [`DEFAULT_SMOOTHNESS`] nats between 4-neighbours: a
//! shadow boundary is a curve, so a label change costs λ per unit of its length. A lone sample
//! is outvoted by its four neighbours when its own preference is below 4λ. λ was chosen on
//! rendered scenes (the table in `docs/photometric-stereo.md`: 2 gains a little more than 1 at
//! twice the cost), not on any one input; the Potts term ignores image edges.
//!
//! **Minimisation.** The energy is binary and submodular, so its exact minimum is a minimum
//! s–t cut (`cut.rs`: persistency fixes the samples whose preference outweighs their
//! neighbours, Dinic's max-flow solves the small components left — the ShadowCuts choice of
//! exact graph cuts; no maintained Rust crate does it, and the residual problems are small).
//! Images are independent given g and are labelled in parallel.
//!
//! **Refit.** Each pixel whose labels changed is refitted by the solve's own estimator
//! ([`crate::ps::solve::Method`]: its shadow rule, fit test and robust fallback) with its
//! shadow-labelled samples removed; it keeps its previous fit when that leaves it unsolved.
//! The labels only ever remove samples the rule kept: a sample the rule dropped stays dropped
//! whatever its label (letting the labels add samples too — a refit without the rule — lost
//! on reading with both `auto` and `threshold`), and the estimator's own defences (the specular
//! cone, IRLS) still apply (least squares over the lit-labelled samples lost them: DiLiGenT cat
//! went from 5.30° to 6.2° with `auto`). Labelling and refit alternate for
//! [`ShadowLabelOptions::rounds`] rounds.
//!
//! **Failure modes.** The labels are only as good as g: where the starting estimate is far off
//! (most samples of a pixel shadowed or non-Lambertian), the residuals mislead and smoothing
//! spreads the error to the neighbours — on DiLiGenT `reading`, whose folds are full of
//! interreflections, the pass costs 0.4° of mean error. A lit region narrower than a pixel or
//! two (a thin rim between shadows) is smoothed away when its own preference is weak. The
//! uniform shadow density and the Potts prior are assumptions. In a streamed run each band is
//! labelled on its own, so neighbours across a band boundary do not vote. The shared-normal
//! colour solve is not relabelled.

mod cut;

use crate::capture::lights::Lights;
use crate::capture::stack::ImageStack;
use crate::error::{Error, Result};
use crate::grid::Mask;
use crate::ps::solve::{PixelSolution, PixelStatus, Solution, SolveOptions};
use cut::{CutScratch, PairGraph, min_cut};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::Serialize;
use std::time::Instant;

/// Default Potts weight λ between 4-neighbours, in nats of the unary terms: chosen on rendered
/// scenes with cast shadows (`docs/photometric-stereo.md`).
pub const DEFAULT_SMOOTHNESS: f64 = 1.0;
/// Default number of label-and-refit rounds.
pub const DEFAULT_ROUNDS: usize = 2;
/// Most rounds accepted.
pub const MAX_ROUNDS: usize = 20;
/// A sample of leverage at or above this (a fit from about three samples reproduces them
/// whatever they are) says nothing about its own label.
pub const MAX_LEVERAGE: f64 = 0.95;
/// Degrees of freedom ν of the Student-t tails of a lit sample's residual: heavy enough that
/// a real surface's departures from Lambert's law are not taken for shadows (ν = 1 and 6 did
/// no better on the rendered scenes and on cat; Gaussian tails did worse on both). The unary
/// term uses (ν + 1)/2 = 2.
const TAIL_DOF: f64 = 3.0;
/// The normaliser C_ν = Γ(ν/2)√(νπ)/Γ((ν+1)/2) of the Student-t density for ν = 3: π√3/2.
const TAIL_NORM: f64 = 2.720_699_046_351_326_4;
/// Smallest prior probability of either label.
pub const MIN_PRIOR: f64 = 0.01;
/// At most this many residuals are ranked per image for its scale (a regular subsample).
const MAX_SCALE_SAMPLES: usize = 5_000;
/// Nodes per parallel work item.
const CHUNK: usize = 1024;
/// Unary preference, in nats, of a sample its own data cannot decide, for the per-pixel rule's
/// label: far below any real preference, it only breaks ties.
const TIE_BREAK: f64 = 1e-6;
/// Median of |z| for a standard normal z.
const HALF_NORMAL_MEDIAN: f64 = 0.674_489_750_196_081_7;
/// Largest relative scale κ searched.
const MAX_KAPPA: f64 = 1.0;

/// Parameters of the labelling pass.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ShadowLabelOptions {
    /// Potts weight λ ≥ 0 between 4-neighbours, in nats (0: every sample decided alone).
    pub smoothness: f64,
    /// Label-and-refit rounds, 1 to [`MAX_ROUNDS`].
    pub rounds: usize,
}

impl Default for ShadowLabelOptions {
    fn default() -> Self {
        ShadowLabelOptions {
            smoothness: DEFAULT_SMOOTHNESS,
            rounds: DEFAULT_ROUNDS,
        }
    }
}

impl ShadowLabelOptions {
    /// Checks parameter ranges.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] naming the parameter out of range.
    pub fn validate(&self) -> Result<()> {
        if !(self.smoothness.is_finite() && self.smoothness >= 0.0) {
            return Err(Error::param(
                "shadow-smoothness",
                format!("{} must be finite and ≥ 0", self.smoothness),
            ));
        }
        if !(1..=MAX_ROUNDS).contains(&self.rounds) {
            return Err(Error::param(
                "shadow-rounds",
                format!("{} is outside 1..={MAX_ROUNDS}", self.rounds),
            ));
        }
        Ok(())
    }
}

/// What the labelling pass changed, over the samples of the masked pixels.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct ShadowSummary {
    /// Finite samples labelled (masked pixels × images).
    pub samples: usize,
    /// Samples the per-pixel shadow rule kept (the threshold set).
    pub kept_by_rule: usize,
    /// Samples labelled shadow at the end.
    pub shadow: usize,
    /// Samples the rule kept that the labels took out of the fit.
    pub removed: usize,
    /// Samples the rule dropped that are labelled lit (they stay out of the fit).
    pub lit_below_rule: usize,
    /// Samples of the last round whose label is not the one their own unary term prefers:
    /// decided by their neighbours.
    pub from_neighbours: usize,
    /// Pixels refitted without their shadow-labelled samples.
    pub refitted: usize,
    /// Rounds run.
    pub rounds: usize,
    /// Wall time of the pass, seconds.
    pub seconds: f64,
}

impl ShadowSummary {
    /// Adds the counts of another part of the image (a band, a channel) and its time.
    pub fn add(&mut self, other: &ShadowSummary) {
        self.samples += other.samples;
        self.kept_by_rule += other.kept_by_rule;
        self.shadow += other.shadow;
        self.removed += other.removed;
        self.lit_below_rule += other.lit_below_rule;
        self.from_neighbours += other.from_neighbours;
        self.refitted += other.refitted;
        self.rounds = self.rounds.max(other.rounds);
        self.seconds += other.seconds;
    }
}

/// Labels the samples of channel `channel` of `stack` lit or shadow by minimising the Potts
/// energy of the module documentation per image, and refits `solution` (the solve of the same
/// stack, channel, lights and mask under `options`) without the samples labelled shadow.
///
/// # Errors
/// As [`crate::ps::solve::solve`] for mismatched inputs; [`Error::DimensionMismatch`] when
/// `solution` is not of the mask's size; [`Error::InvalidParameter`] for invalid options or a
/// solution whose gains do not match the image count.
pub fn label_shadows(
    stack: &ImageStack,
    channel: usize,
    lights: &Lights,
    mask: &Mask,
    options: &SolveOptions,
    labels: &ShadowLabelOptions,
    solution: &mut Solution,
) -> Result<ShadowSummary> {
    let t = Instant::now();
    labels.validate()?;
    crate::ps::solve::check_inputs(stack, channel, lights, mask, options)?;
    mask.check_same_size(&solution.g, "solution vs mask")?;
    let k = stack.count();
    if solution.gains.gains.len() != k {
        return Err(Error::param(
            "solution",
            format!("{} gains for {k} images", solution.gains.gains.len()),
        ));
    }
    let sigma: Vec<f32> = if solution.noise.len() == k && solution.noise.iter().all(|s| *s > 0.0) {
        solution.noise.clone()
    } else {
        crate::ps::solve::test_sigmas(stack, channel, mask, options)
    };
    let mut pass = Pass::new(stack, channel, lights, mask, options, solution, sigma);
    let mut summary = pass.run(labels);
    pass.write(solution, &mut summary);
    summary.seconds = t.elapsed().as_secs_f64();
    Ok(summary)
}

/// One image's model of a lit sample's departure from l·g, and the prior of its labels.
#[derive(Debug, Clone, Copy)]
struct ImageNoise {
    /// Additive noise σ (times the image's gain).
    sigma: f64,
    /// Relative model error: the scale at prediction m is √(σ² + κ²m²).
    kappa: f64,
    /// ln((1 − π)/π), π the fraction of the image's facing samples labelled shadow.
    log_prior: f64,
}

impl ImageNoise {
    /// The residual scale at prediction `m`.
    fn scale(&self, m: f64) -> f64 {
        (self.sigma * self.sigma + self.kappa * self.kappa * m * m).sqrt()
    }
}

/// The relative scale κ ≥ 0 for which the residuals `pairs` (|r|, m) standardised by
/// √(σ² + κ²m²) have the median of a standard normal's |z|; 0 when σ alone explains them.
fn relative_scale(pairs: &[(f64, f64)], sigma: f64) -> f64 {
    let mut u = Vec::with_capacity(pairs.len());
    let mut median_at = |kappa: f64| {
        u.clear();
        u.extend(
            pairs
                .iter()
                .map(|&(e, m)| e / (sigma * sigma + kappa * kappa * m * m).sqrt()),
        );
        crate::stats::median_by(&mut u, f64::total_cmp).unwrap_or(0.0)
    };
    if pairs.is_empty() || median_at(0.0) <= HALF_NORMAL_MEDIAN {
        return 0.0;
    }
    let (mut lo, mut hi) = (0.0, MAX_KAPPA);
    if median_at(hi) > HALF_NORMAL_MEDIAN {
        return hi;
    }
    // The median falls as κ grows: bisect to 0.1% of MAX_KAPPA.
    for _ in 0..10 {
        let mid = 0.5 * (lo + hi);
        if median_at(mid) > HALF_NORMAL_MEDIAN {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    hi
}

/// What predicts a node's samples, compactly (it is read once per image): g, and for an own
/// fit the inverse Gram matrix of the samples that fit used (upper triangle, for leverages);
/// for a neighbours' mean g, NaN there.
#[derive(Clone, Copy)]
struct Prediction {
    g: [f32; 3],
    ainv: [f32; 6],
}

impl Prediction {
    /// l·g.
    #[inline]
    fn at(&self, l: &[f32; 3]) -> f32 {
        self.g[0] * l[0] + self.g[1] * l[1] + self.g[2] * l[2]
    }

    /// Whether this is the node's own fit.
    #[inline]
    fn own(&self) -> bool {
        !self.ainv[0].is_nan()
    }

    /// The leverage lᵀA⁻¹l of a sample with light `l` in the own fit.
    #[inline]
    fn leverage(&self, l: &[f32; 3]) -> f32 {
        let a = &self.ainv;
        a[0] * l[0] * l[0]
            + a[3] * l[1] * l[1]
            + a[5] * l[2] * l[2]
            + 2.0 * (a[1] * l[0] * l[1] + a[2] * l[0] * l[2] + a[4] * l[1] * l[2])
    }
}

/// A node's refit: the solution, the inverse Gram matrix of the samples it used, and which
/// samples those were.
type Refit = (PixelSolution, Matrix3<f64>, Vec<u8>);

/// The state of one labelling pass over a band.
struct Pass<'a> {
    stack: &'a ImageStack,
    channel: usize,
    options: &'a SolveOptions,
    dirs: Vec<Vector3<f64>>,
    dirs32: Vec<[f32; 3]>,
    gains: Vec<f32>,
    /// Per-image noise of the samples before gains (the fit test's, for the refit).
    sigma: Vec<f32>,
    /// Full-image index and plane index of each node (masked pixel).
    pixel: Vec<usize>,
    local: Vec<usize>,
    graph: PairGraph,
    /// Per node: current g (NaN when unsolved) and the inverse Gram matrix of the samples its
    /// fit used.
    g: Vec<Vector3<f64>>,
    ainv: Vec<Option<Matrix3<f64>>>,
    /// Per node, its refit (when it was refitted and solved).
    refit: Vec<Option<PixelSolution>>,
    /// Image-major (`[k * n + i]`) sample flags: kept by the per-pixel rule, used by the
    /// node's current fit, hidden from it, and the current labels (1 lit).
    kept: Vec<u8>,
    used: Vec<u8>,
    hidden: Vec<u8>,
    lit: Vec<u8>,
}

impl<'a> Pass<'a> {
    fn new(
        stack: &'a ImageStack,
        channel: usize,
        lights: &Lights,
        mask: &Mask,
        options: &'a SolveOptions,
        solution: &Solution,
        sigma: Vec<f32>,
    ) -> Self {
        let (w, h) = (mask.width(), mask.height());
        let k = stack.count();
        let mut id = vec![u32::MAX; w * h];
        let mut pixel = Vec::new();
        for (p, &m) in mask.data().iter().enumerate() {
            if m {
                id[p] = pixel.len() as u32;
                pixel.push(p);
            }
        }
        let n = pixel.len();
        let mut edges = Vec::with_capacity(2 * n);
        for &p in &pixel {
            let (x, y) = (p % w, p / w);
            if x + 1 < w && id[p + 1] != u32::MAX {
                edges.push((id[p], id[p + 1]));
            }
            if y + 1 < h && id[p + w] != u32::MAX {
                edges.push((id[p], id[p + w]));
            }
        }
        // The mask lies in the stack's window (checked by `check_inputs`).
        let local = pixel.iter().map(|&p| stack.local(p).unwrap_or(0)).collect();
        let g = pixel
            .iter()
            .map(|&p| {
                if solution.status.data()[p] == PixelStatus::Solved {
                    solution.g.data()[p].map(f64::from)
                } else {
                    Vector3::repeat(f64::NAN)
                }
            })
            .collect();
        let mut pass = Pass {
            stack,
            channel,
            options,
            dirs: lights.directions(),
            dirs32: lights
                .directions()
                .iter()
                .map(|d| [d.x as f32, d.y as f32, d.z as f32])
                .collect(),
            gains: solution.gains.gains.clone(),
            sigma,
            pixel,
            local,
            graph: PairGraph::new(n, &edges),
            g,
            ainv: Vec::new(),
            refit: vec![None; n],
            kept: vec![0; k * n],
            used: Vec::new(),
            hidden: vec![0; k * n],
            lit: Vec::new(),
        };
        pass.rule_set();
        pass
    }

    /// Image `k`'s plane of the channel and its saturation bits when the options reject
    /// saturated samples.
    fn image(&self, k: usize) -> (&[f32], Option<&[u64]>) {
        let bits = if self.options.reject_saturated {
            self.stack.saturation_bits(k)
        } else {
            None
        };
        (self.stack.plane(k, self.channel), bits)
    }

    /// The samples the per-pixel rule keeps, as the solve's own fitter decides them (shadow
    /// threshold and saturation; every finite one for plain least squares), and the inverse
    /// Gram matrix of that set: what the solve's fit used, as far as the rule says (a robust
    /// fit used a subset of it).
    fn rule_set(&mut self) {
        let (n, k) = (self.pixel.len(), self.stack.count());
        if n == 0 {
            return;
        }
        let reject = self.options.method != crate::ps::solve::Method::LeastSquares;
        let rule = crate::ps::robust::Estimator::Plain {
            reject,
            intensity_weight: false,
        };
        let this = &*self;
        let per_node: Vec<(Vec<u8>, Option<Matrix3<f64>>)> = (0..n)
            .into_par_iter()
            .with_min_len(CHUNK)
            .map_init(
                || {
                    (
                        crate::ps::solve::fitter(&this.dirs, &this.gains, this.options),
                        vec![0f32; k],
                        vec![false; k],
                    )
                },
                |(f, values, saturated), i| {
                    this.gather(i, None, values, saturated);
                    f.fit(values, saturated, rule);
                    let kept: Vec<u8> = f.weights().iter().map(|&w| u8::from(w > 0.0)).collect();
                    let ainv = this.gram(&kept).try_inverse();
                    (kept, ainv)
                },
            )
            .collect();
        let mut kept = vec![0u8; k * n];
        let mut ainv = Vec::with_capacity(n);
        for (i, (node, a)) in per_node.into_iter().enumerate() {
            for (kk, x) in node.into_iter().enumerate() {
                kept[kk * n + i] = x;
            }
            ainv.push(a);
        }
        self.ainv = ainv;
        self.used = kept.clone();
        self.lit = kept.clone();
        self.kept = kept;
    }

    /// Node `i`'s samples (as stored, before gains) and saturation flags, the samples marked in
    /// `hidden` (image-major, of all nodes) replaced by NaN.
    fn gather(&self, i: usize, hidden: Option<&[u8]>, values: &mut [f32], saturated: &mut [bool]) {
        let n = self.pixel.len();
        for (kk, (v, s)) in values.iter_mut().zip(saturated.iter_mut()).enumerate() {
            let hide = hidden.is_some_and(|h| h[kk * n + i] == 1);
            *v = if hide {
                f32::NAN
            } else {
                self.stack.plane(kk, self.channel)[self.local[i]]
            };
            *s = self.stack.is_saturated(kk, self.pixel[i]);
        }
    }

    /// Σ l·lᵀ over the samples flagged in `used` (one flag per image).
    fn gram(&self, used: &[u8]) -> Matrix3<f64> {
        let mut a = Matrix3::zeros();
        for (l, &u) in self.dirs.iter().zip(used) {
            if u == 1 {
                a += l * l.transpose();
            }
        }
        a
    }

    /// Runs the rounds; returns the counts of the last one.
    fn run(&mut self, options: &ShadowLabelOptions) -> ShadowSummary {
        let n = self.pixel.len();
        let mut summary = ShadowSummary::default();
        if n == 0 {
            return summary;
        }
        for _ in 0..options.rounds {
            let predicted = self.predictions();
            let noise = self.noise_models(&predicted);
            let k = self.stack.count();
            let mut next = vec![0u8; k * n];
            let this = &*self;
            let from_neighbours: usize = next
                .par_chunks_mut(n)
                .enumerate()
                .map_init(
                    || (CutScratch::default(), Vec::new()),
                    |(scratch, delta), (kk, out)| {
                        this.unaries(kk, &predicted, &noise[kk], delta);
                        min_cut(&this.graph, delta, options.smoothness, out, scratch);
                        delta
                            .iter()
                            .zip(out.iter())
                            .filter(|(d, l)| (**d > 0.0 && **l == 0) || (**d < 0.0 && **l == 1))
                            .count()
                    },
                )
                .sum();
            self.lit = next;
            summary.from_neighbours = from_neighbours;
            self.refit_changed();
            summary.rounds += 1;
        }
        summary
    }

    /// Each node's prediction: its own fit, the mean g of its solved neighbours, or none.
    fn predictions(&self) -> Vec<Option<Prediction>> {
        let f = |v: Vector3<f64>| [v.x as f32, v.y as f32, v.z as f32];
        (0..self.pixel.len())
            .into_par_iter()
            .with_min_len(CHUNK)
            .map(|i| {
                if self.g[i].x.is_finite() {
                    let a = self.ainv[i]?;
                    return Some(Prediction {
                        g: f(self.g[i]),
                        ainv: [
                            a[(0, 0)],
                            a[(0, 1)],
                            a[(0, 2)],
                            a[(1, 1)],
                            a[(1, 2)],
                            a[(2, 2)],
                        ]
                        .map(|x| x as f32),
                    });
                }
                let mut sum = Vector3::zeros();
                let mut count = 0;
                for &j in self.graph.neighbours(i) {
                    let gj = self.g[j as usize];
                    if gj.x.is_finite() {
                        sum += gj;
                        count += 1;
                    }
                }
                (count > 0).then(|| Prediction {
                    g: f(sum / f64::from(count)),
                    ainv: [f32::NAN; 6],
                })
            })
            .collect()
    }

    /// The variance factor c of sample (k, i)'s residual under prediction `p`: 1 − h for a
    /// sample its fit used, 1 + h for one it did not, 2 for a neighbours' prediction; `None`
    /// when the leverage is too high to tell.
    #[inline]
    fn variance_factor(&self, k: usize, i: usize, p: &Prediction) -> Option<f32> {
        if !p.own() {
            return Some(2.0);
        }
        let h = p.leverage(&self.dirs32[k]);
        if self.used[k * self.pixel.len() + i] == 1 {
            (h < MAX_LEVERAGE as f32).then_some(1.0 - h)
        } else {
            Some(1.0 + h)
        }
    }

    /// Each image's lit-sample noise model and label prior ([`ImageNoise`]), from a regular
    /// subsample (at most [`MAX_SCALE_SAMPLES`]) of its samples under the current labels.
    fn noise_models(&self, predicted: &[Option<Prediction>]) -> Vec<ImageNoise> {
        let n = self.pixel.len();
        let stride = n.div_ceil(MAX_SCALE_SAMPLES).max(1);
        (0..self.stack.count())
            .into_par_iter()
            .map(|k| {
                let l = self.dirs32[k];
                let (plane, _) = self.image(k);
                let gain = f64::from(self.gains[k]);
                let sigma = f64::from(self.sigma[k]) * gain;
                // |r|/√c and m of the used samples of own fits.
                let mut pairs = Vec::new();
                let (mut facing, mut shadowed) = (0usize, 0usize);
                for i in (0..n).step_by(stride) {
                    let v = f64::from(plane[self.local[i]]) * gain;
                    let Some(p) = &predicted[i] else { continue };
                    let m = f64::from(p.at(&l));
                    if !(m > 0.0 && v.is_finite()) {
                        continue;
                    }
                    facing += 1;
                    if self.lit[k * n + i] == 0 {
                        shadowed += 1;
                        continue;
                    }
                    if !p.own() || self.used[k * n + i] == 0 {
                        continue;
                    }
                    if let Some(c) = self.variance_factor(k, i, p) {
                        pairs.push(((v - m).abs() / f64::from(c).sqrt(), m));
                    }
                }
                let prior =
                    (shadowed as f64 / facing.max(1) as f64).clamp(MIN_PRIOR, 1.0 - MIN_PRIOR);
                ImageNoise {
                    sigma,
                    kappa: relative_scale(&pairs, sigma),
                    log_prior: ((1.0 - prior) / prior).ln(),
                }
            })
            .collect()
    }

    /// The unary preferences D(0) − D(1) of image `k`'s nodes for the lit label.
    fn unaries(
        &self,
        k: usize,
        predicted: &[Option<Prediction>],
        noise: &ImageNoise,
        delta: &mut Vec<f64>,
    ) {
        let n = self.pixel.len();
        let l = self.dirs32[k];
        let (plane, bits) = self.image(k);
        let gain = self.gains[k];
        let rule = &self.kept[k * n..(k + 1) * n];
        delta.clear();
        delta.extend((0..n).map(|i| {
            let v = plane[self.local[i]] * gain;
            let p = self.pixel[i];
            let d = if !v.is_finite() || bits.is_some_and(|b| b[p / 64] >> (p % 64) & 1 == 1) {
                0.0
            } else if let Some(pred) = &predicted[i] {
                let m = pred.at(&l);
                if m <= 0.0 {
                    f64::NEG_INFINITY
                } else {
                    match self.variance_factor(k, i, pred) {
                        None => 0.0,
                        Some(c) => {
                            let (m, c, v) = (f64::from(m), f64::from(c), f64::from(v));
                            let s = noise.scale(m) * c.sqrt();
                            if s.is_finite() && s > 0.0 {
                                // Above m the two labels share the lit tail: only the
                                // normalisers differ. ln(m/(s·C₃)) − 2·ln(1 + u²/3) in one
                                // logarithm.
                                let u = (v - m).min(0.0) / s;
                                let t = 1.0 + u * u / TAIL_DOF;
                                (m / (s * TAIL_NORM * t * t)).ln() + noise.log_prior
                            } else {
                                0.0
                            }
                        }
                    }
                }
            } else {
                0.0
            };
            // A sample its own data cannot decide leans, by a hair, the way the per-pixel rule
            // decided it: the neighbours outvote the lean, and a region that nothing decides
            // keeps the rule's labels.
            if d == 0.0 {
                if rule[i] == 1 { TIE_BREAK } else { -TIE_BREAK }
            } else {
                d
            }
        }));
    }

    /// Refits, by the solve's estimator without the samples the rule kept and the labels call
    /// shadow, every node whose hidden samples changed since its last fit; a node whose refit
    /// is not solved keeps its previous fit.
    fn refit_changed(&mut self) {
        let (n, k) = (self.pixel.len(), self.stack.count());
        let hidden: Vec<u8> = self
            .kept
            .par_iter()
            .zip(&self.lit)
            .map(|(&kept, &lit)| kept & (1 - lit))
            .collect();
        let options = SolveOptions {
            shadow_labels: None,
            ..*self.options
        };
        let this = &*self;
        let hidden_ref = &hidden;
        let fits: Vec<Option<Refit>> = (0..n)
            .into_par_iter()
            .with_min_len(CHUNK)
            .map_init(
                || {
                    (
                        crate::ps::solve::fitter(&this.dirs, &this.gains, &options),
                        vec![0f32; k],
                        vec![false; k],
                    )
                },
                |(f, values, saturated), i| {
                    if !(0..k).any(|kk| hidden_ref[kk * n + i] != this.hidden[kk * n + i]) {
                        return None;
                    }
                    this.gather(i, Some(hidden_ref), values, saturated);
                    let p = crate::ps::solve::fit_with(f, values, saturated, &this.sigma, &options);
                    if p.status != PixelStatus::Solved {
                        return None;
                    }
                    let used: Vec<u8> = f.weights().iter().map(|&w| u8::from(w > 0.0)).collect();
                    Some((p, this.gram(&used).try_inverse()?, used))
                },
            )
            .collect();
        for (i, fit) in fits.into_iter().enumerate() {
            let Some((p, ainv, used)) = fit else { continue };
            self.g[i] = p.g;
            self.ainv[i] = Some(ainv);
            self.refit[i] = Some(p);
            for (kk, u) in used.into_iter().enumerate() {
                self.used[kk * n + i] = u;
                self.hidden[kk * n + i] = hidden[kk * n + i];
            }
        }
    }

    /// Writes the refitted pixels into `solution` and the label counts into `summary`.
    fn write(&self, solution: &mut Solution, summary: &mut ShadowSummary) {
        let n = self.pixel.len();
        for kk in 0..self.stack.count() {
            let (plane, _) = self.image(kk);
            for i in 0..n {
                if !plane[self.local[i]].is_finite() {
                    continue;
                }
                let j = kk * n + i;
                let (kept, lit) = (self.kept[j] == 1, self.lit[j] == 1);
                summary.samples += 1;
                summary.kept_by_rule += usize::from(kept);
                summary.shadow += usize::from(!lit);
                summary.removed += usize::from(kept && !lit);
                summary.lit_below_rule += usize::from(!kept && lit);
            }
        }
        for (i, r) in self.refit.iter().enumerate() {
            let Some(r) = r else { continue };
            solution.record(self.pixel[i], r);
            summary.refitted += 1;
        }
    }
}

#[cfg(test)]
mod tests;
