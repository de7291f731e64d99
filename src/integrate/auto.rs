//! `auto`: choose, from the normals themselves, between the smooth integrator (masked least
//! squares) and the discontinuity-preserving one (bilateral), and say why.
//!
//! A continuous surface's gradients are integrable up to noise: around every 2×2 loop of pixels
//! the four depth differences the gradients give (the module's shared discretisation) sum to
//! zero, up to noise. A depth jump inside the mask (a self-occlusion) is not in the normals, and
//! where its height changes along it the loops that straddle it do not close: their circulation
//! is far above the noise, and those few loops carry most of the field's non-integrability.
//! So, before integrating:
//! 1. weight each loop's circulation c by its noise: a gradient's noise grows like 1/a (a = n_z,
//!    or m with a camera), so the loop is scaled by the smallest a of its four pixels, and
//!    grazing normals, whose gradients are unreliable anyway, weigh little;
//! 2. estimate the noise robustly, σ̂ = 1.4826 · median |c|;
//! 3. bound what the discretisation alone can make a loop's circulation, ε: a smooth surface's
//!    gradients do not close exactly under any quadrature rule, and where the gradients vary
//!    fast (near an occluding rim, at high curvature) that error, not noise, is the
//!    circulation ([`discretisation_bound`]);
//! 4. call a loop **outlying** when |c| − ε > τσ̂, with τ the two-sided Gaussian quantile at which
//!    all m loops together expect [`FALSE_ALARMS`] false alarms (Bonferroni:
//!    P(|N(0,1)| > τ) = [`FALSE_ALARMS`]/m; τ ≈ 5.2 for 4·10⁴ loops), so that neither noise nor
//!    the discretisation alone almost ever produces one;
//! 5. the surface has **depth jumps** when the outlying loops carry more than half of the
//!    circulation's energy Σc² ([`JUMP_SHARE`]): the non-integrability is then concentrated, not
//!    noise.
//!
//! (A first version tested the masked least-squares residual instead; least squares spreads a
//! jump's missing height over a wide neighbourhood, which raises the noise estimate itself, and a
//! rendered tilted disc floating above the ground went undetected.)
//!
//! With jumps the bilateral integrator runs (its cost is paid only then); without, masked least
//! squares runs, and a smooth object pays one pass over its gradients for the test. The
//! decision and its numbers are returned ([`AutoDecision`]) and reported.
//!
//! Where it breaks: a jump whose height is constant along a closed curve (a disc floating
//! parallel to the ground) closes every loop — the normals carry no trace of it, and no
//! integrator recovers its height; a jump that the bilateral integrator only partly cuts can
//! leave its depth worse than the smooth one (the demo scene's hemisphere; DiLiGenT goblet,
//! 8.72 mm against 7.84 even with its cut closed; `docs/integration.md`); on exact (noise-free) normals a crease, where the
//! gradients themselves jump (the rendered pyramid's edges), is taken for a depth jump, since
//! the bound of step 3 assumes gradients smooth along each line.
//!
//! Without step 3 the test took the discretisation error of exact or nearly noise-free normals
//! for jumps wherever the gradients vary fast: a rendered sphere, vase, relief, peaks or bust
//! with exact normals chose the bilateral integrator, with 17–23% of their loops outlying, as
//! did the photometric-stereo normals of a noise-free rendered sphere — at 5000² that whole run
//! took 112 s (96 s of it integrating) and peaked at 11.9 GB; with masked least squares it takes
//! 27 s and 6.2 GB.

use super::{Censoring, Integrator, window_edge_differences};
use crate::grid::{Mask, ScalarMap};
use rayon::prelude::*;
use serde::Serialize;

/// Expected number of loops that noise alone makes outlying (the Bonferroni level of the test,
/// over all loops together).
pub const FALSE_ALARMS: f64 = 0.01;
/// The surface has depth jumps when the outlying loops carry more than this share of the
/// circulation's energy (a majority).
pub const JUMP_SHARE: f64 = 0.5;

/// What `auto` found and chose.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AutoDecision {
    /// The integrator whose depth is returned.
    pub chosen: Integrator,
    /// Loops (2×2 pixel squares in the domain) tested.
    pub loops: usize,
    /// Robust noise σ̂ of the weighted circulation (height or log-depth units).
    pub noise: f64,
    /// τ: a loop is outlying beyond τσ̂.
    pub tau: f64,
    /// Outlying loops.
    pub outlying_loops: usize,
    /// Share of the circulation's energy on the outlying loops.
    pub outlying_share: f64,
    /// Set when the surface has depth jumps but bilateral integration would need more memory
    /// than integration was allowed: masked least squares ran instead.
    pub held_back: Option<HeldBack>,
}

/// Bilateral integration held back by the memory cap
/// ([`super::IntegrationOptions::max_memory`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct HeldBack {
    /// Bytes bilateral integration would need.
    pub needed: u64,
    /// Bytes integration was allowed.
    pub allowed: u64,
}

impl AutoDecision {
    /// Whether the test found depth jumps (bilateral integration ran, unless it was
    /// [`held back`](Self::held_back)).
    pub fn jumps(&self) -> bool {
        self.chosen == Integrator::Bilateral || self.held_back.is_some()
    }

    /// One sentence: what was chosen and why.
    pub fn reason(&self) -> String {
        if let Some(h) = self.held_back {
            format!(
                "depth jumps: {} of {} pixel loops whose gradients do not close by more than their discretisation error and {:.1}σ carry {:.0}% of the non-integrability, but the discontinuity-preserving integrator would need about {} MiB and integration may use {} MiB, so the smooth integrator was used: it smooths over the jumps",
                self.outlying_loops,
                self.loops,
                self.tau,
                100.0 * self.outlying_share,
                h.needed.div_ceil(1 << 20),
                h.allowed >> 20
            )
        } else if self.jumps() {
            format!(
                "depth jumps: {} of {} pixel loops whose gradients do not close by more than their discretisation error and {:.1}σ carry {:.0}% of the non-integrability, so the discontinuity-preserving integrator was used",
                self.outlying_loops,
                self.loops,
                self.tau,
                100.0 * self.outlying_share
            )
        } else {
            format!(
                "no depth jumps: {} of {} pixel loops not closing by more than their discretisation error and {:.1}σ carry {:.0}% of the non-integrability, so the smooth integrator was kept",
                self.outlying_loops,
                self.loops,
                self.tau,
                100.0 * self.outlying_share
            )
        }
    }
}

/// `a` when `a` and `b` have one sign and |a| ≤ |b|, `b` when |b| < |a|, else 0: the smaller of
/// two slopes that agree (the minmod limiter of shock-capturing schemes, Roe 1986), so that a
/// jump between them estimates nothing.
fn minmod(a: f64, b: f64) -> f64 {
    if a * b <= 0.0 {
        0.0
    } else if a.abs() <= b.abs() {
        a
    } else {
        b
    }
}

/// The line of gradient samples an edge lies on: the samples `g` and the `domain` flags (of the
/// whole image), the stride between neighbours along the line (1 along a row, the image width
/// along a column), and the number of samples on the line (the image width or height).
struct Line<'a> {
    g: &'a [f32],
    domain: &'a [bool],
    stride: usize,
    len: usize,
}

impl Line<'_> {
    /// The second difference of g at the sample `steps` steps from sample `k` (at position `pos`
    /// along the line), when it and both its neighbours are in the domain.
    fn second_difference(&self, k: usize, pos: usize, steps: isize) -> Option<f64> {
        let at = pos as isize + steps;
        if at < 1 || at + 1 >= self.len as isize {
            return None;
        }
        let centre = (k as isize + steps * self.stride as isize) as usize;
        let (before, after) = (centre - self.stride, centre + self.stride);
        [before, centre, after]
            .iter()
            .all(|&i| self.domain[i])
            .then(|| {
                let g = |i: usize| f64::from(self.g[i]);
                g(before) - 2.0 * g(centre) + g(after)
            })
    }
}

/// A bound on the error of the depth difference `d` the shared discretisation gives the edge
/// from sample `k` (at position `pos` along `line`) to the next (`sign` −1 for the columns, whose
/// difference is −∫q).
///
/// The trapezoid rule's error on an edge is g''(ξ)/12 for some ξ on it (Euler–Maclaurin);
/// estimated by the second differences Δ²g at the edge's ends, it bounds the error of the
/// fourth-order rule used inside the domain, whose leading term (11/720)g⁗ is several times
/// smaller wherever g varies over more than a pixel — the classical embedded error estimate of a
/// higher-order rule by a lower one. Inside the domain the two ends' second differences are
/// combined by [`minmod`]: on a smooth line they agree, and across a step in g — where a depth
/// jump changes the gradient — they have opposite signs and give 0, so a jump never excuses its
/// own circulation. Next to the domain's edge, where one end's second difference is missing, the
/// other end's is taken, plus the difference between the rule used there (the trapezoid, or the
/// rim profile) and the trapezoid. Each is an estimate to leading order, not a strict bound:
/// where g'' changes sign on an edge the limiter gives 0 and the fourth-order rule's own term,
/// (11/720)g⁗, is left; at the domain's edge the one-sided second difference is off by about
/// g'''/12 (the unit test allows exactly those terms). Extrapolating the one-sided difference
/// linearly was tried: it cost a real occlusion (DiLiGenT bear's photometric-stereo normals
/// fell from a 51% to a 46% share, below the majority).
fn discretisation_bound(line: &Line, k: usize, pos: usize, d: f64, sign: f64) -> f64 {
    let g = |i: usize| f64::from(line.g[i]);
    let trapezoid = sign * 0.5 * (g(k) + g(k + line.stride));
    let rule = (d - trapezoid).abs();
    let at = |steps| line.second_difference(k, pos, steps);
    match (at(0), at(1)) {
        (Some(first), Some(second)) => minmod(first, second).abs() / 12.0,
        (None, Some(end)) | (Some(end), None) => end.abs() / 12.0 + rule,
        (None, None) => rule,
    }
}

/// Two-sided Gaussian quantile τ with P(|N(0,1)| > τ) = `p`, by bisection on the complementary
/// error function (accurate to 1e-6 in τ).
pub(crate) fn two_sided_quantile(p: f64) -> f64 {
    let (mut lo, mut hi) = (0.0f64, 40.0f64);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if libm::erfc(mid / std::f64::consts::SQRT_2) > p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// The test of the module documentation on the gradients (p, q) over `domain`, with `a` the
/// per-pixel normal factor ([`super::normal_factor`]): the decision, with
/// [`Integrator::Bilateral`] chosen when the circulation shows depth jumps and
/// [`Integrator::MaskedLs`] otherwise.
pub(crate) fn decide(p: &ScalarMap, q: &ScalarMap, a: &[f64], domain: &Mask) -> AutoDecision {
    let image_w = p.width();
    // Every loop lies in the domain's bounding box: the differences are taken there.
    let (win, right, down) = match window_edge_differences(p, q, domain, &Censoring::None) {
        Some((win, _, right, down)) => (win, right, down),
        None => (crate::grid::Window::full(0, 0), Vec::new(), Vec::new()),
    };
    let (w, h) = (win.width(), win.height());
    let (pd, qd, inside) = (p.data(), q.data(), domain.data());
    let image_h = p.height();
    // The lines the loops' edges lie on: rows of p, columns of q.
    let rows = Line {
        g: pd,
        domain: inside,
        stride: 1,
        len: image_w,
    };
    let columns = Line {
        g: qd,
        domain: inside,
        stride: image_w,
        len: image_h,
    };
    // The loop with top-left pixel (x, y) of the box: its circulation in units of its noise,
    // the smallest a of its four pixels being the weight (the noisiest gradient dominates), and
    // that weight. None where an edge leaves the domain.
    let circulation = |x: usize, y: usize| -> Option<(f64, f64)> {
        let i = y * w + x;
        let c = right[i] + down[i + 1] - right[i + w] - down[i];
        if !c.is_finite() {
            return None;
        }
        let k = (win.y0 + y) * image_w + win.x0 + x;
        let a2 = [k, k + 1, k + image_w, k + image_w + 1]
            .iter()
            .map(|&k| a[k] * a[k])
            .fold(f64::INFINITY, f64::min);
        let weight = a2.sqrt();
        let e = (weight * c).abs();
        e.is_finite().then_some((e, weight))
    };
    // The same loop's discretisation bound in units of its noise (`weight`). Finite wherever
    // the circulation is: every sample it reads is a domain pixel's, whose gradients are finite.
    let bound = |x: usize, y: usize, weight: f64| -> f64 {
        let i = y * w + x;
        let (ix, iy) = (win.x0 + x, win.y0 + y);
        let k = iy * image_w + ix;
        weight
            * (discretisation_bound(&rows, k, ix, right[i], 1.0)
                + discretisation_bound(&columns, k + 1, iy, down[i + 1], -1.0)
                + discretisation_bound(&rows, k + image_w, ix, right[i + w], 1.0)
                + discretisation_bound(&columns, k, iy, down[i], -1.0))
    };
    let (rows, cols) = (h.saturating_sub(1), w.saturating_sub(1));
    // The weighted circulations for the noise estimate, one slot a loop position of the box
    // written in place (no loop there: +∞, which sorts after every circulation).
    let mut loops = vec![f64::INFINITY; rows * cols];
    if cols > 0 {
        loops.par_chunks_mut(cols).enumerate().for_each(|(y, row)| {
            for (x, slot) in row.iter_mut().enumerate() {
                if let Some((e, _)) = circulation(x, y) {
                    *slot = e;
                }
            }
        });
    }
    let count = loops.iter().filter(|e| e.is_finite()).count();
    let noise = if count == 0 {
        0.0
    } else {
        let mid = count / 2;
        1.4826 * *loops.select_nth_unstable_by(mid, f64::total_cmp).1
    };
    drop(loops);
    let tau = two_sided_quantile(FALSE_ALARMS / count.max(1) as f64);
    let limit = tau * noise;
    // Outlying loops and the energies, summed per row and then over rows in order, so that the
    // sums do not depend on the number of threads.
    let per_row: Vec<(usize, f64, f64)> = (0..rows)
        .into_par_iter()
        .map(|y| {
            let (mut outlying, mut energy_out, mut energy) = (0usize, 0.0f64, 0.0f64);
            for x in 0..cols {
                let Some((e, weight)) = circulation(x, y) else {
                    continue;
                };
                energy += e * e;
                // The bound is not negative: only a loop beyond the limit needs it.
                if e > limit && e - bound(x, y, weight) > limit {
                    outlying += 1;
                    energy_out += e * e;
                }
            }
            (outlying, energy_out, energy)
        })
        .collect();
    let (mut outlying, mut energy_out, mut energy) = (0usize, 0.0f64, 0.0f64);
    for (o, eo, e) in per_row {
        outlying += o;
        energy_out += eo;
        energy += e;
    }
    let share = if energy > 0.0 {
        energy_out / energy
    } else {
        0.0
    };
    AutoDecision {
        chosen: if outlying > 0 && share > JUMP_SHARE {
            Integrator::Bilateral
        } else {
            Integrator::MaskedLs
        },
        loops: count,
        noise,
        tau,
        outlying_loops: outlying,
        outlying_share: share,
        held_back: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;

    /// The depth differences the shared discretisation gives a line of derivative samples `g`
    /// (t = 0, 1, …), and their discretisation bounds, per edge k (from sample k to k + 1): the
    /// line laid along the middle row (`column` false) or the middle column of a three-pixel-wide
    /// image, with one pixel outside the domain at each end. Down a column the samples are q = −g
    /// (y is up), so both give the same differences.
    fn line_differences(g: &[f32], column: bool) -> (Vec<f64>, Vec<f64>) {
        let n = g.len();
        let (w, h) = if column { (3, n + 2) } else { (n + 2, 3) };
        // Position along the line, 1..=n inside the domain.
        let at = |x: usize, y: usize| {
            if column {
                (x == 1).then_some(y)
            } else {
                (y == 1).then_some(x)
            }
        };
        let inside = |x, y| at(x, y).is_some_and(|t| (1..=n).contains(&t));
        let sample = |x, y| {
            if inside(x, y) {
                g[at(x, y).unwrap_or(0) - 1]
            } else {
                f32::NAN
            }
        };
        let zero = Grid::from_fn(w, h, |x, y| if inside(x, y) { 0.0 } else { f32::NAN });
        let along = Grid::from_fn(
            w,
            h,
            |x, y| {
                if column { -sample(x, y) } else { sample(x, y) }
            },
        );
        let (p, q) = if column {
            (&zero, &along)
        } else {
            (&along, &zero)
        };
        let domain = Grid::from_fn(w, h, inside);
        let (right, down) =
            super::super::edge_differences(p, q, &domain, &super::super::Censoring::None);
        let line = Line {
            g: along.data(),
            domain: domain.data(),
            stride: if column { w } else { 1 },
            len: if column { h } else { w },
        };
        (0..n - 1)
            .map(|k| {
                let (i, d, sign) = if column {
                    let i = (k + 1) * w + 1;
                    (i, down[i], -1.0)
                } else {
                    (w + k + 1, right[w + k + 1], 1.0)
                };
                (d, discretisation_bound(&line, i, k + 1, d, sign))
            })
            .unzip()
    }

    /// The forward difference of `order` of `g` from sample `at`.
    fn forward_difference(g: &[f32], at: usize, order: usize) -> f64 {
        let mut v: Vec<f64> = g[at..=at + order].iter().map(|&x| f64::from(x)).collect();
        for _ in 0..order {
            v = v.windows(2).map(|w| w[1] - w[0]).collect();
        }
        v[0]
    }

    /// A depth profile z(t) along a line and its derivative g(t).
    type Profile = (&'static str, fn(f64) -> f64, fn(f64) -> f64);

    /// On a rim-like line, g = 1/√(t + 1/2) (depth 2√(t + 1/2), a contour half a pixel before
    /// the first sample, where the rim profile applies), a cosine, and a line that steepens
    /// towards both ends, laid along a row and down a column (the same bounds, bit for bit):
    /// - the bound holds the error of the rule used on every edge, up to the next term of each
    ///   estimate;
    /// - inside, where g'' keeps its sign and size over the edge's stencil, the bound is the
    ///   trapezoid rule's error within a factor of 2 (what it estimates);
    /// - a step in g, as a depth jump makes it, excuses nothing on the edges whose inner samples
    ///   straddle it.
    #[test]
    fn the_discretisation_bound_holds_the_rule_error_and_not_a_step() {
        let n = 40;
        let profiles: [Profile; 3] = [
            (
                "rim",
                |t| 2.0 * (t + 0.5).sqrt(),
                |t| 1.0 / (t + 0.5).sqrt(),
            ),
            ("cosine", |t| (0.4 * t).sin() / 0.4, |t| (0.4 * t).cos()),
            (
                "two rims",
                |t| -(400.0 - (t - 19.5).powi(2)).sqrt(),
                |t| (t - 19.5) / (400.0 - (t - 19.5).powi(2)).sqrt(),
            ),
        ];
        let mut compared = 0;
        for (name, z, dz) in profiles {
            let g: Vec<f32> = (0..n).map(|t| dz(t as f64) as f32).collect();
            let (d, bounds) = line_differences(&g, false);
            let (d_column, bounds_column) = line_differences(&g, true);
            assert_eq!(d, d_column, "{name}: differences along a column");
            assert_eq!(bounds, bounds_column, "{name}: bounds along a column");
            let v = |i: usize| f64::from(g[i]);
            for (k, (&d, &bound)) in d.iter().zip(&bounds).enumerate() {
                let truth = z(k as f64 + 1.0) - z(k as f64);
                let error = (truth - d).abs();
                // What each estimate leaves: inside, where g'' may change sign on the edge and
                // the limiter give 0, the fourth-order rule's own leading term (11/720)|g⁗|, the
                // largest fourth difference about the edge; at the ends, the one-sided second
                // difference's miss, about |g'''|/12. f32 samples add the rule's rounding, a few
                // units of 6e-8 of g.
                let allowance = if (1..n - 2).contains(&k) {
                    (k.saturating_sub(2)..=k.min(n - 5))
                        .map(|at| forward_difference(&g, at, 4).abs())
                        .fold(0.0, f64::max)
                        * 11.0
                        / 720.0
                } else {
                    forward_difference(&g, k.min(n - 4), 3).abs() / 12.0
                };
                let rounding = 1e-6 * v(k).abs().max(v(k + 1).abs());
                assert!(
                    error <= bound + allowance + rounding,
                    "{name} edge {k}: error {error:e} above the bound {bound:e} + {allowance:e}"
                );
                if (1..n - 2).contains(&k) {
                    let (s0, s1) = (
                        forward_difference(&g, k - 1, 2),
                        forward_difference(&g, k, 2),
                    );
                    if s0 * s1 > 0.0 && s0.abs().min(s1.abs()) >= 0.5 * s0.abs().max(s1.abs()) {
                        let trapezoid = (truth - 0.5 * (v(k) + v(k + 1))).abs();
                        assert!(
                            (0.5..=2.0).contains(&(bound / trapezoid)),
                            "{name} edge {k}: bound {bound:e}, trapezoid error {trapezoid:e}"
                        );
                        compared += 1;
                    }
                }
            }
        }
        assert!(
            compared >= 60,
            "{compared} edges compared with the trapezoid error"
        );
        let step: Vec<f32> = (0..n).map(|t| if t < 20 { 0.5 } else { 2.5 }).collect();
        for column in [false, true] {
            let (_, bounds) = line_differences(&step, column);
            // The edges 18 → 19, 19 → 20 (the step) and 20 → 21.
            assert_eq!(bounds[18..=20], [0.0; 3], "column {column}");
        }
    }

    #[test]
    fn quantiles_match_the_gaussian_tail() {
        // Known two-sided quantiles: 5% → 1.959964, 1e-4 → 3.890592, 1e-7 → 5.326724.
        for (p, tau) in [(0.05, 1.959_964), (1e-4, 3.890_592), (1e-7, 5.326_724)] {
            let got = two_sided_quantile(p);
            assert!((got - tau).abs() < 1e-4, "p {p}: {got} vs {tau}");
        }
    }
}
