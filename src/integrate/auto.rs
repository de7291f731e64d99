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
//! 3. call a loop **outlying** when |c| > τσ̂, with τ the two-sided Gaussian quantile at which all
//!    m loops together expect [`FALSE_ALARMS`] false alarms (Bonferroni:
//!    P(|N(0,1)| > τ) = [`FALSE_ALARMS`]/m; τ ≈ 5.2 for 4·10⁴ loops), so that noise alone almost
//!    never produces one;
//! 4. the surface has **depth jumps** when the outlying loops carry more than half of the
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
//! leave its depth worse than the smooth one (DiLiGenT goblet: 9.65 mm against 7.84; the demo
//! scene's hemisphere; `docs/integration.md`); exact synthetic normals have no noise to compare
//! with, and their discretisation error at high curvature reads as jumps.

use super::{Censoring, Integrator, window_edge_differences};
use crate::grid::{Mask, ScalarMap};
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
                "depth jumps: {} of {} pixel loops whose gradients do not close beyond {:.1}σ carry {:.0}% of the non-integrability, but the discontinuity-preserving integrator would need about {} MiB and integration may use {} MiB, so the smooth integrator was used: it smooths over the jumps",
                self.outlying_loops,
                self.loops,
                self.tau,
                100.0 * self.outlying_share,
                h.needed.div_ceil(1 << 20),
                h.allowed >> 20
            )
        } else if self.jumps() {
            format!(
                "depth jumps: {} of {} pixel loops whose gradients do not close beyond {:.1}σ carry {:.0}% of the non-integrability, so the discontinuity-preserving integrator was used",
                self.outlying_loops,
                self.loops,
                self.tau,
                100.0 * self.outlying_share
            )
        } else {
            format!(
                "no depth jumps: {} of {} pixel loops not closing beyond {:.1}σ carry {:.0}% of the non-integrability, so the smooth integrator was kept",
                self.outlying_loops,
                self.loops,
                self.tau,
                100.0 * self.outlying_share
            )
        }
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
    // Circulation around the 2×2 loop with top-left pixel i, in units of its noise: the
    // smallest a² of its four pixels is the weight (the noisiest gradient dominates).
    let mut loops = Vec::new();
    for y in 0..h.saturating_sub(1) {
        for x in 0..w.saturating_sub(1) {
            let i = y * w + x;
            let c = right[i] + down[i + 1] - right[i + w] - down[i];
            if !c.is_finite() {
                continue;
            }
            let k = (win.y0 + y) * image_w + win.x0 + x;
            let a2 = [k, k + 1, k + image_w, k + image_w + 1]
                .iter()
                .map(|&k| a[k] * a[k])
                .fold(f64::INFINITY, f64::min);
            let e = (a2.sqrt() * c).abs();
            if e.is_finite() {
                loops.push(e);
            }
        }
    }
    let count = loops.len();
    let mut sorted = loops.clone();
    let noise = if count == 0 {
        0.0
    } else {
        let mid = count / 2;
        1.4826 * *sorted.select_nth_unstable_by(mid, f64::total_cmp).1
    };
    let tau = two_sided_quantile(FALSE_ALARMS / count.max(1) as f64);
    let limit = tau * noise;
    let (mut outlying, mut energy_out, mut energy) = (0usize, 0.0f64, 0.0f64);
    for e in &loops {
        energy += e * e;
        if *e > limit {
            outlying += 1;
            energy_out += e * e;
        }
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

    #[test]
    fn quantiles_match_the_gaussian_tail() {
        // Known two-sided quantiles: 5% → 1.959964, 1e-4 → 3.890592, 1e-7 → 5.326724.
        for (p, tau) in [(0.05, 1.959_964), (1e-4, 3.890_592), (1e-7, 5.326_724)] {
            let got = two_sided_quantile(p);
            assert!((got - tau).abs() < 1e-4, "p {p}: {got} vs {tau}");
        }
    }
}
