//! Error measures against ground truth: angular error of normals, depth RMSE, albedo error.

use crate::error::{Error, Result};
use crate::grid::{Mask, NormalMap, ScalarMap};
use crate::stats::finite_sorted;
use serde::Serialize;

/// Statistics of the angle between estimated and true normals, arccos(n·n_gt), in degrees.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AngularErrorStats {
    /// Mean over the compared pixels (DiLiGenT's figure of merit).
    pub mean_deg: f64,
    /// Median.
    pub median_deg: f64,
    /// Root mean square.
    pub rms_deg: f64,
    /// 95th percentile.
    pub p95_deg: f64,
    /// Fraction of compared pixels under 5°.
    pub below_5deg: f64,
    /// Fraction under 10°.
    pub below_10deg: f64,
    /// Fraction under 20°.
    pub below_20deg: f64,
    /// Pixels compared (in the mask, both normals defined).
    pub pixels: usize,
    /// Pixels in the mask with a defined true normal but no estimate.
    pub missing: usize,
}

/// Per-pixel angular error in degrees; NaN outside `mask` or where either normal is undefined.
///
/// # Errors
/// [`Error::DimensionMismatch`] when sizes differ.
pub fn angular_error_map(est: &NormalMap, gt: &NormalMap, mask: &Mask) -> Result<ScalarMap> {
    est.check_same_size(gt, "estimated vs true normals")?;
    est.check_same_size(mask, "normals vs mask")?;
    let mut out = est.map(|_| f32::NAN);
    for (i, o) in out.data_mut().iter_mut().enumerate() {
        let (a, b) = (est.data()[i], gt.data()[i]);
        if !mask.data()[i] || !a.iter().chain(b.iter()).all(|v| v.is_finite()) {
            continue;
        }
        let (a, b) = (a.cast::<f64>(), b.cast::<f64>());
        let (na, nb) = (a.norm(), b.norm());
        if na == 0.0 || nb == 0.0 {
            continue;
        }
        let c = (a.dot(&b) / (na * nb)).clamp(-1.0, 1.0);
        *o = c.acos().to_degrees() as f32;
    }
    Ok(out)
}

/// Angular error statistics of `est` against `gt` over `mask`.
///
/// # Errors
/// [`Error::DimensionMismatch`] when sizes differ; [`Error::Mask`] when no pixel can be compared.
pub fn angular_errors(est: &NormalMap, gt: &NormalMap, mask: &Mask) -> Result<AngularErrorStats> {
    let e = finite_sorted(&angular_error_map(est, gt, mask)?);
    let missing = (0..mask.len())
        .filter(|&i| {
            mask.data()[i]
                && gt.data()[i].iter().all(|v| v.is_finite())
                && !est.data()[i].iter().all(|v| v.is_finite())
        })
        .count();
    if e.is_empty() {
        return Err(Error::Mask {
            path: "<evaluation>".into(),
            reason: "no pixel has both an estimated and a true normal inside the mask".into(),
        });
    }
    let n = e.len() as f64;
    let frac = |t: f64| e.iter().filter(|v| **v < t).count() as f64 / n;
    Ok(AngularErrorStats {
        mean_deg: e.iter().sum::<f64>() / n,
        median_deg: percentile(&e, 0.5),
        rms_deg: (e.iter().map(|v| v * v).sum::<f64>() / n).sqrt(),
        p95_deg: percentile(&e, 0.95),
        below_5deg: frac(5.0),
        below_10deg: frac(10.0),
        below_20deg: frac(20.0),
        pixels: e.len(),
        missing,
    })
}

/// Percentile `f` ∈ [0, 1] of sorted values (nearest rank).
fn percentile(sorted: &[f64], f: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * f).round() as usize]
}

/// Depth error after removing the mean offset (orthographic depth is known up to a constant).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DepthErrorStats {
    /// RMSE of (z − mean z) − (z_gt − mean z_gt), in the maps' units.
    pub rmse: f64,
    /// Mean absolute error after the same offset removal.
    pub mean_abs: f64,
    /// max − min of the true depth over the compared pixels.
    pub gt_range: f64,
    /// `rmse / gt_range`.
    pub rmse_over_range: f64,
    /// Pixels compared.
    pub pixels: usize,
}

/// The (estimated, true) depth pairs inside `mask` where both are finite and the estimate
/// passes `keep`.
fn depth_pairs(
    est: &ScalarMap,
    gt: &ScalarMap,
    mask: &Mask,
    keep: impl Fn(f32) -> bool,
) -> Result<Vec<(f64, f64)>> {
    est.check_same_size(gt, "estimated vs true depth")?;
    est.check_same_size(mask, "depth vs mask")?;
    let pairs: Vec<(f64, f64)> = (0..est.len())
        .filter(|&i| {
            let (e, g) = (est.data()[i], gt.data()[i]);
            mask.data()[i] && e.is_finite() && g.is_finite() && keep(e)
        })
        .map(|i| (f64::from(est.data()[i]), f64::from(gt.data()[i])))
        .collect();
    if pairs.is_empty() {
        return Err(Error::Mask {
            path: "<evaluation>".into(),
            reason: "no pixel has both an estimated and a true depth inside the mask".into(),
        });
    }
    Ok(pairs)
}

/// Depth error of `est` against `gt` over `mask` after removing the mean offset.
///
/// # Errors
/// [`Error::DimensionMismatch`] when sizes differ; [`Error::Mask`] when no pixel can be compared.
pub fn depth_errors(est: &ScalarMap, gt: &ScalarMap, mask: &Mask) -> Result<DepthErrorStats> {
    let pairs = depth_pairs(est, gt, mask, |_| true)?;
    let n = pairs.len() as f64;
    let (me, mg) = pairs
        .iter()
        .fold((0.0, 0.0), |(a, b), (e, g)| (a + e / n, b + g / n));
    let (mut ss, mut sa) = (0.0, 0.0);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (e, g) in &pairs {
        let d = (e - me) - (g - mg);
        ss += d * d;
        sa += d.abs();
        lo = lo.min(*g);
        hi = hi.max(*g);
    }
    let rmse = (ss / n).sqrt();
    Ok(DepthErrorStats {
        rmse,
        mean_abs: sa / n,
        gt_range: hi - lo,
        rmse_over_range: if hi > lo { rmse / (hi - lo) } else { f64::NAN },
        pixels: pairs.len(),
    })
}

/// Depth RMSE with the mean offset removed separately on each part labelled in `parts` (for
/// example [`crate::synth::scene::HeightField::object`]), over `mask`. Normals do not tell the height
/// of a depth discontinuity, so an object seen over another is only known up to its own
/// offset. This measures the shape of each part and not where the parts sit.
///
/// # Errors
/// [`Error::DimensionMismatch`] when sizes differ; [`Error::Mask`] when no pixel can be compared.
pub fn depth_rmse_per_part(
    est: &ScalarMap,
    gt: &ScalarMap,
    mask: &Mask,
    parts: &crate::grid::Grid<u32>,
) -> Result<f64> {
    est.check_same_size(parts, "depth vs parts")?;
    // Checks the other sizes and that something can be compared.
    depth_pairs(est, gt, mask, |_| true)?;
    // Per part: count, Σd, Σd² of d = est − gt; the offset-free sum of squares is
    // Σd² − (Σd)²/n.
    let mut sums: std::collections::HashMap<u32, (f64, f64, f64)> = Default::default();
    for i in 0..est.len() {
        let (e, g) = (est.data()[i], gt.data()[i]);
        if mask.data()[i] && e.is_finite() && g.is_finite() {
            let d = f64::from(e) - f64::from(g);
            let s = sums.entry(parts.data()[i]).or_default();
            s.0 += 1.0;
            s.1 += d;
            s.2 += d * d;
        }
    }
    let (n, ss) = sums.values().fold((0.0, 0.0), |(n, ss), (c, s, s2)| {
        (n + c, ss + (s2 - s * s / c).max(0.0))
    });
    Ok((ss / n).sqrt())
}

/// Depth error after a global scale fit, for depth known up to scale (perspective integration):
/// the estimate is multiplied by median(z_gt / z) over the compared pixels, then compared (the
/// metric of the bilateral-normal-integration benchmark on DiLiGenT).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ScaledDepthErrorStats {
    /// The fitted scale median(z_gt / z).
    pub scale: f64,
    /// Mean absolute difference after scaling (the benchmark's figure), in the truth's units.
    pub mean_abs: f64,
    /// RMSE after scaling.
    pub rmse: f64,
    /// Pixels compared.
    pub pixels: usize,
}

/// Depth error of `est` against `gt` over `mask` after the median scale fit.
///
/// # Errors
/// [`Error::DimensionMismatch`] when sizes differ; [`Error::Mask`] when no pixel can be compared.
pub fn scaled_depth_errors(
    est: &ScalarMap,
    gt: &ScalarMap,
    mask: &Mask,
) -> Result<ScaledDepthErrorStats> {
    let pairs = depth_pairs(est, gt, mask, |e| e != 0.0)?;
    let mut ratios: Vec<f64> = pairs.iter().map(|(e, g)| g / e).collect();
    ratios.sort_by(f64::total_cmp);
    let n = ratios.len();
    // numpy's median: the mean of the two middle values for an even count.
    let scale = if n % 2 == 1 {
        ratios[n / 2]
    } else {
        0.5 * (ratios[n / 2 - 1] + ratios[n / 2])
    };
    let (mut sa, mut ss) = (0.0, 0.0);
    for (e, g) in &pairs {
        let d = e * scale - g;
        sa += d.abs();
        ss += d * d;
    }
    Ok(ScaledDepthErrorStats {
        scale,
        mean_abs: sa / n as f64,
        rmse: (ss / n as f64).sqrt(),
        pixels: n,
    })
}

/// Mean and maximum relative albedo error |ρ − ρ_gt| / ρ_gt over `mask`.
///
/// # Errors
/// [`Error::DimensionMismatch`] when sizes differ; [`Error::Mask`] when no pixel can be compared.
pub fn albedo_relative_error(est: &ScalarMap, gt: &ScalarMap, mask: &Mask) -> Result<(f64, f64)> {
    est.check_same_size(gt, "estimated vs true albedo")?;
    est.check_same_size(mask, "albedo vs mask")?;
    let errs: Vec<f64> = (0..est.len())
        .filter(|&i| {
            mask.data()[i]
                && est.data()[i].is_finite()
                && gt.data()[i].is_finite()
                && gt.data()[i] > 0.0
        })
        .map(|i| f64::from((est.data()[i] - gt.data()[i]).abs() / gt.data()[i]))
        .collect();
    if errs.is_empty() {
        return Err(Error::Mask {
            path: "<evaluation>".into(),
            reason: "no pixel has both an estimated and a true albedo inside the mask".into(),
        });
    }
    let mean = errs.iter().sum::<f64>() / errs.len() as f64;
    let max = errs.iter().copied().fold(0.0, f64::max);
    Ok((mean, max))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Grid;
    use nalgebra::Vector3;

    #[test]
    fn angular_error_of_a_known_rotation() {
        let a = Grid::new(4, 4, Vector3::new(0.0f32, 0.0, 1.0));
        let t = 10f32.to_radians();
        let b = Grid::new(4, 4, Vector3::new(t.sin(), 0.0, t.cos()));
        let mask = Grid::new(4, 4, true);
        let s = angular_errors(&a, &b, &mask).unwrap();
        assert!((s.mean_deg - 10.0).abs() < 1e-4);
        assert_eq!(s.pixels, 16);
        assert_eq!(s.below_10deg, 0.0);
        assert_eq!(s.below_20deg, 1.0);
    }

    #[test]
    fn depth_error_ignores_offset() {
        let gt = Grid::from_fn(5, 5, |x, y| (x + y) as f32);
        let est = gt.map(|v| v + 100.0);
        let mask = Grid::new(5, 5, true);
        let s = depth_errors(&est, &gt, &mask).unwrap();
        assert!(s.rmse < 1e-6);
        assert_eq!(s.gt_range, 8.0);
    }
}
