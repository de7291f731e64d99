//! The line search of the shape-from-shading solvers' Gauss–Newton steps ([`super::horn`] and
//! the perspective refinement): the length along a step by quadratic interpolation (Nocedal &
//! Wright, "Numerical optimization", 2nd ed., 2006, §3.5).
//!
//! E(α) along the step is modelled by the parabola through E(0), its slope E′(0) and the last
//! length tried. While E has not fallen below E(0), the next length tried is the parabola's
//! minimum, kept between a tenth and a half of the last (halving when E is not a number). Once a
//! length lowers E, the parabola's minimum is tried too when it lies well short of that length:
//! a Gauss–Newton matrix leaves out the residuals' own curvature, so a full step often
//! overshoots, and taking the first length that lowers E then costs many more steps (the
//! perspective refinement on peaks at 256², light 30° off the axis: 24 steps, each lowering E by
//! about 0.15%, against 8).

/// Lengths tried before the step is given up (E(0) is then a minimum along it, to rounding).
const TRIES: usize = 12;
/// Once a length lowers E, the parabola's minimum is tried when shorter than this fraction of it.
const SHORTER: f64 = 0.8;

/// The length α along a step that lowers `energy(α)` below `e0` = E(0), and E there; `None` when
/// no length tried does. `slope` is E′(0) (negative along a descent step). With `shorten`, a
/// length that lowers E is followed by the parabola's minimum when that is well short of it;
/// without, the first length that lowers E is kept (for an energy with kinks, whose parabola
/// through a lowered value is a poor guide).
pub(crate) fn search(
    e0: f64,
    slope: f64,
    shorten: bool,
    mut energy: impl FnMut(f64) -> f64,
) -> Option<(f64, f64)> {
    let mut alpha = 1.0;
    for _ in 0..TRIES {
        let e = energy(alpha);
        let curvature = (e - e0 - slope * alpha) / (alpha * alpha);
        let best = if curvature > 0.0 && slope < 0.0 {
            -slope / (2.0 * curvature)
        } else {
            alpha
        };
        if e.is_finite() && e < e0 {
            if shorten && best > 0.1 * alpha && best < SHORTER * alpha {
                let e_best = energy(best);
                if e_best < e {
                    return Some((best, e_best));
                }
            }
            return Some((alpha, e));
        }
        alpha = if e.is_finite() {
            best.clamp(0.1 * alpha, 0.5 * alpha)
        } else {
            0.5 * alpha
        };
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a parabola the search lands on its minimum: at once when a full step undershoots or
    /// reaches it, by the interpolated length when the full step overshoots; without
    /// shortening, a full step that lowers E is kept.
    #[test]
    fn finds_the_minimum_of_a_parabola() {
        for minimum in [0.25, 0.5, 0.7, 1.0, 1.5] {
            // E(α) = (α − m)², E(0) = m², E′(0) = −2m.
            let e = |a: f64| (a - minimum) * (a - minimum);
            let (alpha, at) = search(e(0.0), -2.0 * minimum, true, e).unwrap();
            let expected = if minimum < SHORTER { minimum } else { 1.0 };
            assert!((alpha - expected).abs() < 1e-12, "{minimum}: {alpha}");
            assert!(at < e(0.0));
            let (alpha, _) = search(e(0.0), -2.0 * minimum, false, e).unwrap();
            let kept = if minimum > 0.5 { 1.0 } else { minimum };
            assert!((alpha - kept).abs() < 1e-12, "{minimum}, kept: {alpha}");
        }
    }

    /// A full step far past the minimum is cut back by interpolation, not by halving alone; a
    /// step along which E only grows, or is not a number, is given up.
    #[test]
    fn backtracks_and_gives_up() {
        let e = |a: f64| (a - 0.01) * (a - 0.01);
        for shorten in [true, false] {
            let (alpha, _) = search(e(0.0), -0.02, shorten, e).unwrap();
            assert!((alpha - 0.01).abs() < 1e-12, "{alpha}");
            assert!(search(1.0, 0.5, shorten, |a| 1.0 + a).is_none());
            assert!(search(1.0, -1.0, shorten, |_| f64::NAN).is_none());
        }
    }
}
