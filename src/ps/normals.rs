//! From g = ρN to albedo and normals, surface gradients, and the integrability check.
//!
//! For a depth map z(x, y) seen orthographically (x right, y up, z towards the camera), the
//! normal is N ∝ (−∂z/∂x, −∂z/∂y, 1), so the gradients are p = ∂z/∂x = −n_x/n_z and
//! q = ∂z/∂y = −n_y/n_z. A field (p, q) is the gradient of a surface only if it is curl-free:
//! ∂p/∂y − ∂q/∂x = 0. The curl of the measured field therefore shows where normals are wrong
//! (or where the surface is discontinuous).

use crate::grid::{Grid, Mask, NormalMap, ScalarMap};
use crate::ps::solve::{PixelStatus, Solution};
use nalgebra::Vector3;
use serde::Serialize;

/// Smallest n_z used when converting normals to gradients: caps |p|, |q| at about 1/MIN_NZ,
/// keeping grazing rim pixels from dominating integration.
pub const MIN_NZ: f32 = 0.02;

/// Whether `n` can be a surface normal: finite, and not the zero vector, so that the zero
/// vectors and NaN that normal maps use for "no normal" are not. Any length is taken:
/// integration reads the direction ([`crate::integrate::unit_normals`]).
///
/// ```
/// use nalgebra::Vector3;
/// use photostereo::integrate::usable_normal;
/// assert!(usable_normal(&Vector3::new(0.0, 0.6, 0.8)));
/// assert!(usable_normal(&Vector3::new(0.0, 0.06, 0.08)));
/// assert!(!usable_normal(&Vector3::zeros()));
/// assert!(!usable_normal(&Vector3::new(f32::NAN, 0.0, 1.0)));
/// ```
pub fn usable_normal(n: &Vector3<f32>) -> bool {
    n.iter().all(|v| v.is_finite()) && n.amax() > 0.0
}

/// How far the squared length of a normal may be from 1 for it to be taken as a unit vector:
/// above the rounding of a normalisation in `f32` (a few 10⁻⁷), below that of a normal map
/// stored in half floats (about 10⁻³), which is therefore normalised again.
const UNIT_SQUARED_TOLERANCE: f32 = 1e-5;

/// Whether `n` is a [`usable_normal`] that is not of unit length (beyond
/// [`UNIT_SQUARED_TOLERANCE`]).
pub(crate) fn off_unit(n: &Vector3<f32>) -> bool {
    usable_normal(n) && (n.norm_squared() - 1.0).abs() > UNIT_SQUARED_TOLERANCE
}

/// `n` scaled to unit length when it is [`off_unit`] (by its largest component first, so that
/// neither a huge nor a tiny vector overflows or underflows its squared length), else as it is
/// (bit for bit).
pub(crate) fn unit_length(n: &Vector3<f32>) -> Vector3<f32> {
    if off_unit(n) {
        let v = n / n.amax();
        v / v.norm()
    } else {
        *n
    }
}

/// Albedo and unit normals from a grey solve: ρ = |g|, N = g/ρ; NaN where not solved.
pub fn albedo_and_normals(solution: &Solution) -> (ScalarMap, NormalMap) {
    let albedo = solution.g.map(|g| g.norm());
    let normals = solution.g.map(|g| {
        let r = g.norm();
        if r.is_finite() && r > 0.0 {
            g / r
        } else {
            Vector3::repeat(f32::NAN)
        }
    });
    (albedo, normals)
}

/// Normals and per-channel albedo from per-channel solves of the same pixels: the normal is the
/// direction of g_R + g_G + g_B (channels with more signal count more), and the albedo of
/// channel c is |g_c|. A pixel is solved when every channel is, filled when every channel has an
/// estimate and one was filled.
pub fn combine_channels(solutions: &[Solution]) -> (Vec<ScalarMap>, NormalMap, Grid<PixelStatus>) {
    let Some(first) = solutions.first() else {
        return (
            Vec::new(),
            Grid::new(0, 0, Vector3::zeros()),
            Grid::new(0, 0, PixelStatus::Outside),
        );
    };
    let (w, h) = (first.g.width(), first.g.height());
    let albedo = solutions.iter().map(|s| s.g.map(|g| g.norm())).collect();
    let status = Grid::from_fn(w, h, |x, y| {
        solutions
            .iter()
            .map(|s| *s.status.at(x, y))
            .min_by_key(|s| match s {
                // The worst channel: no estimate, then filled, then solved.
                s if !s.has_normal() => 0,
                PixelStatus::Filled => 1,
                _ => 2,
            })
            .unwrap_or(PixelStatus::Solved)
    });
    let normals = Grid::from_fn(w, h, |x, y| {
        let sum: Vector3<f32> = solutions.iter().map(|s| *s.g.at(x, y)).sum();
        let r = sum.norm();
        if status.at(x, y).has_normal() && r > 0.0 {
            sum / r
        } else {
            Vector3::repeat(f32::NAN)
        }
    });
    (albedo, normals, status)
}

/// Surface gradients p = −n_x/n_z, q = −n_y/n_z (with n_z clamped to ≥ [`MIN_NZ`]); NaN
/// outside `mask` or where there is no normal (NaN, or the zero vector that normal maps store
/// for none: [`usable_normal`]).
pub fn gradients(normals: &NormalMap, mask: &Mask) -> (ScalarMap, ScalarMap) {
    gradient_maps(normals, mask, |_, n| {
        let nz = n.z.max(MIN_NZ);
        (-n.x / nz, -n.y / nz)
    })
}

/// Two maps of `f(pixel index, normal)` over the masked pixels with a normal (finite and not
/// zero; NaN elsewhere), computed in parallel over rows.
pub(crate) fn gradient_maps(
    normals: &NormalMap,
    mask: &Mask,
    f: impl Fn(usize, &Vector3<f32>) -> (f32, f32) + Sync,
) -> (ScalarMap, ScalarMap) {
    use rayon::prelude::*;
    let w = normals.width().max(1);
    let mut p = Grid::new(normals.width(), normals.height(), f32::NAN);
    let mut q = p.clone();
    p.data_mut()
        .par_chunks_mut(w)
        .zip(q.data_mut().par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (p, q))| {
            let row = y * w;
            for (x, (p, q)) in p.iter_mut().zip(q).enumerate() {
                let n = &normals.data()[row + x];
                if mask.data()[row + x] && usable_normal(n) {
                    (*p, *q) = f(row + x, n);
                }
            }
        });
    (p, q)
}

/// The integrability check of a gradient field.
#[derive(Debug, Clone)]
pub struct Integrability {
    /// Curl ∂p/∂y − ∂q/∂x per pixel (per pixel unit); NaN where it cannot be computed.
    pub curl: ScalarMap,
    /// Summary over the pixels where the curl is defined.
    pub summary: IntegrabilitySummary,
}

/// Summary statistics of |curl|.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct IntegrabilitySummary {
    /// Mean |curl| over the mask.
    pub mean_abs_curl: f64,
    /// Median |curl|.
    pub median_abs_curl: f64,
    /// 95th percentile of |curl|.
    pub p95_abs_curl: f64,
    /// Pixels where the curl is defined.
    pub pixels: usize,
}

/// Derivative along one axis of `f` at index `i`, from neighbours `prev`/`next` (when defined):
/// central difference inside, one-sided at the edge of the defined region.
fn diff(f: &[f32], i: usize, prev: Option<usize>, next: Option<usize>) -> f32 {
    let ok = |j: Option<usize>| j.filter(|&j| f[j].is_finite());
    match (ok(prev), ok(next)) {
        (Some(a), Some(b)) => (f[b] - f[a]) / 2.0,
        (None, Some(b)) => f[b] - f[i],
        (Some(a), None) => f[i] - f[a],
        (None, None) => f32::NAN,
    }
}

/// Curl ∂p/∂y − ∂q/∂x of the field (p, q) with y up (so ∂/∂y = −∂/∂row), by central
/// differences inside the defined region and one-sided ones at its edge.
pub fn integrability(p: &ScalarMap, q: &ScalarMap) -> Integrability {
    let (w, h) = (p.width(), p.height());
    let (pd, qd) = (p.data(), q.data());
    let curl = Grid::from_fn(w, h, |x, y| {
        let i = y * w + x;
        if !pd[i].is_finite() || !qd[i].is_finite() {
            return f32::NAN;
        }
        let up = (y > 0).then(|| i - w);
        let down = (y + 1 < h).then(|| i + w);
        let left = (x > 0).then(|| i - 1);
        let right = (x + 1 < w).then(|| i + 1);
        // ∂p/∂y = −∂p/∂row; "prev" along +y is the row below.
        let dp_dy = diff(pd, i, down, up);
        let dq_dx = diff(qd, i, left, right);
        dp_dy - dq_dx
    });
    let mut abs: Vec<f64> = curl
        .data()
        .iter()
        .filter(|c| c.is_finite())
        .map(|c| f64::from(c.abs()))
        .collect();
    let summary = if abs.is_empty() {
        IntegrabilitySummary::default()
    } else {
        // Order statistics by selection (linear time) rather than a full sort.
        let n = abs.len();
        let mean_abs_curl = abs.iter().sum::<f64>() / n as f64;
        let mut pct = |f: f64| {
            let k = ((n - 1) as f64 * f).round() as usize;
            *abs.select_nth_unstable_by(k, f64::total_cmp).1
        };
        IntegrabilitySummary {
            mean_abs_curl,
            median_abs_curl: pct(0.5),
            p95_abs_curl: pct(0.95),
            pixels: n,
        }
    };
    Integrability { curl, summary }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gradients_of_a_plane_and_zero_curl() {
        // z = 0.3 x − 0.2 y → N ∝ (−0.3, 0.2, 1).
        let n = Vector3::new(-0.3f32, 0.2, 1.0).normalize();
        let normals = Grid::new(8, 6, n);
        let mask = Grid::new(8, 6, true);
        let (p, q) = gradients(&normals, &mask);
        assert!((p.at(3, 3) - 0.3).abs() < 1e-6);
        assert!((q.at(3, 3) + 0.2).abs() < 1e-6);
        let i = integrability(&p, &q);
        assert!(i.summary.mean_abs_curl < 1e-6);
        assert_eq!(i.summary.pixels, 48);
    }

    #[test]
    fn curl_of_a_rotational_field_is_its_closed_form() {
        // p = −y, q = x (y up): ∂p/∂y − ∂q/∂x = −2 everywhere.
        let (w, h) = (9, 7);
        let yc = |row: usize| (h as f32 - 1.0) / 2.0 - row as f32;
        let p = Grid::from_fn(w, h, |_, r| -yc(r));
        let q = Grid::from_fn(w, h, |c, _| c as f32);
        let i = integrability(&p, &q);
        for c in i.curl.data() {
            assert!((c + 2.0).abs() < 1e-5, "{c}");
        }
    }
}
