//! A start surface for [`super::shape_from_shading_from`] as a depth sensor, stereo or a
//! coarse reconstruction gives it: at another resolution than the image, and with holes.
//!
//! [`prepare_start`] brings such a height map to the image's grid:
//! - **Only the object's samples.** The start covers the image's field of view with square
//!   pixels, at s image pixels a start pixel (s = W/w ≈ H/h, the two within one start pixel of
//!   each other). A start sample is used only where its centre falls inside the mask: a
//!   sensor's depth map also holds the background, and blending it into the object's rim
//!   would put a cliff where the object's outline is.
//! - **Holes are filled on the start's grid**: the samples the interpolation below reads (those
//!   within one sample of one that holds a mask pixel) and that have no usable height (a
//!   sensor's dropouts: non-finite values; the background around the rim) are filled by
//!   biharmonic interpolation (the least-squares minimum of the squared 5-point Laplacians, the
//!   usable heights fixed; as scikit-image's `inpaint_biharmonic`, after S. B. Damelin and
//!   N. S. Hoang, "On surface completion and image inpainting by biharmonic functions:
//!   numerical aspects", IJMMS 2018), solved by sparse Cholesky. The fill continues the
//!   surface's slopes into the hole: exact for planes and quadrics such as x² + y² (where a
//!   membrane, Laplace's equation, flattens a cap into a cone), and for finer detail a smooth
//!   patch that the shading then has to shape. Filling before interpolating keeps the surface
//!   smooth around a hole: interpolating from the remaining samples alone (weights
//!   renormalised) put a kink around every dropout and doubled the start's normal error on
//!   rendered shapes with one sample in ten missing.
//! - **Resampling.** The centre of image pixel x lies at start coordinate x' = (x + ½)/s − ½
//!   along each axis; the height there is the bilinear interpolation of the four samples
//!   around it, multiplied by s, because heights are measured in each grid's pixels.
//!   Coordinates beyond the outer samples' centres are clamped to them. At s = 1 every image
//!   pixel is its own sample, unchanged.
//!
//! Fails where: a part of the mask has no start height at all (nothing to fill it from): it is
//! refused, naming a pixel of it. Large holes are filled, not refused; [`StartSurface::filled`]
//! says how many pixels had no height of their own, and a refinement from a start that is
//! mostly filled is only as good as a refinement from a smooth guess.

use crate::error::{Error, Result};
use crate::grid::{Mask, ScalarMap};
use crate::integrate::sparse::{
    CholeskyWork, NONE, Unknowns, nested_dissection, symbolic_cholesky,
};
use faer::Par;

/// A start surface on the image's grid ([`prepare_start`]).
#[derive(Debug, Clone)]
pub struct StartSurface {
    /// Heights towards the camera in the image's pixels, finite over the mask and NaN outside
    /// it: the `start` of [`super::shape_from_shading_from`].
    pub heights: ScalarMap,
    /// Image pixels a start pixel (1 when the start was at the image's size; 4 for a start at
    /// a quarter of the resolution).
    pub scale: f64,
    /// Start samples inside the mask without a finite height (a sensor's dropouts), filled by
    /// biharmonic interpolation; in the start's pixels (each covers about `scale`² image pixels).
    pub filled: usize,
}

/// Brings `start` (heights towards the camera in its own pixels, any offset; non-finite where
/// unknown) to the grid of `mask` (the image's): resampled to the image's resolution and
/// scaled to its pixels, holes filled (module documentation).
///
/// # Errors
/// [`Error::InvalidParameter`] (`start`) when it is empty, when its size is not the image's
/// scaled by one factor (another field of view or aspect), or when a connected part of the
/// mask has no start height at all.
pub fn prepare_start(start: &ScalarMap, mask: &Mask) -> Result<StartSurface> {
    let (w, h) = (mask.width(), mask.height());
    let (sw, sh) = (start.width(), start.height());
    if sw == 0 || sh == 0 {
        return Err(Error::param("start", "is empty"));
    }
    let (sx, sy) = (w as f64 / sw as f64, h as f64 / sh as f64);
    // One start pixel over its shorter side: sizes rounded from one factor agree to that.
    if (sx / sy - 1.0).abs() > 1.0 / sw.min(sh) as f64 {
        return Err(Error::param(
            "start",
            format!(
                "size {sw}×{sh} is not the image's {w}×{h} at another resolution ({sx:.3}× \
                 across, {sy:.3}× down): the start must cover the image's field of view with \
                 square pixels"
            ),
        ));
    }
    let scale = 0.5 * (sx + sy);
    // The start sample whose square holds image pixel (x, y)'s centre, and the image pixel
    // that holds start sample (i, j)'s centre.
    let cell = |x: usize, y: usize| {
        (
            (((x as f64 + 0.5) / sx) as usize).min(sw - 1),
            (((y as f64 + 0.5) / sy) as usize).min(sh - 1),
        )
    };
    let pixel = |i: usize, j: usize| {
        (
            (((i as f64 + 0.5) * sx) as usize).min(w - 1),
            (((j as f64 + 0.5) * sy) as usize).min(h - 1),
        )
    };
    // Usable samples: finite, with their centre inside the mask (the object's).
    let mut known = Mask::new(sw, sh, false);
    let parts = Unknowns::new(mask);
    let mut index = vec![NONE; w * h];
    for (k, &p) in parts.pixel.iter().enumerate() {
        index[p as usize] = k as u32;
    }
    let mut sampled = vec![false; parts.parts];
    for j in 0..sh {
        for i in 0..sw {
            let (x, y) = pixel(i, j);
            let k = index[y * w + x];
            if k != NONE && start.data()[j * sw + i].is_finite() {
                known.data_mut()[j * sw + i] = true;
                sampled[parts.part[k as usize] as usize] = true;
            }
        }
    }
    if let Some(k) = (0..parts.len()).find(|&k| !sampled[parts.part[k] as usize]) {
        let p = parts.pixel[k] as usize;
        let size = parts.part.iter().filter(|&&q| q == parts.part[k]).count();
        return Err(Error::param(
            "start",
            format!(
                "the part of the mask around pixel ({}, {}) ({size} pixels) has no start height \
                 inside it (a start pixel covers {scale:.2}×{scale:.2} image pixels): nothing to \
                 fill it from",
                p % w,
                p / w
            ),
        ));
    }
    // The samples the interpolation reads: those within one of a sample that holds a mask
    // pixel's centre. The ones without a usable height are filled.
    let mut needed = Mask::new(sw, sh, false);
    for y in 0..h {
        for x in 0..w {
            if mask.data()[y * w + x] {
                let (i, j) = cell(x, y);
                for jj in j.saturating_sub(1)..(j + 2).min(sh) {
                    for ii in i.saturating_sub(1)..(i + 2).min(sw) {
                        needed.data_mut()[jj * sw + ii] = true;
                    }
                }
            }
        }
    }
    let mut samples = ScalarMap::new(sw, sh, f32::NAN);
    let mut missing = Mask::new(sw, sh, false);
    let mut filled = 0;
    for q in 0..sw * sh {
        if known.data()[q] {
            samples.data_mut()[q] = start.data()[q];
        } else if needed.data()[q] {
            missing.data_mut()[q] = true;
            let (x, y) = pixel(q % sw, q / sw);
            if mask.data()[y * w + x] {
                filled += 1;
            }
        }
    }
    if missing.count() > 0 {
        fill(&mut samples, &missing)?;
    }
    let axis = |p: usize, s: f64, n: usize| -> (usize, usize, f64) {
        let t = ((p as f64 + 0.5) / s - 0.5).clamp(0.0, (n - 1) as f64);
        let i0 = (t.floor() as usize).min(n - 1);
        let i1 = (i0 + 1).min(n - 1);
        (i0, i1, t - i0 as f64)
    };
    let mut heights = ScalarMap::new(w, h, f32::NAN);
    for y in 0..h {
        let (j0, j1, fy) = axis(y, sy, sh);
        for x in 0..w {
            let p = y * w + x;
            if !mask.data()[p] {
                continue;
            }
            let (i0, i1, fx) = axis(x, sx, sw);
            let mut sum = 0.0;
            for (i, j, c) in [
                (i0, j0, (1.0 - fx) * (1.0 - fy)),
                (i1, j0, fx * (1.0 - fy)),
                (i0, j1, (1.0 - fx) * fy),
                (i1, j1, fx * fy),
            ] {
                if c > 0.0 {
                    sum += c * f64::from(samples.data()[j * sw + i]);
                }
            }
            heights.data_mut()[p] = (scale * sum) as f32;
        }
    }
    Ok(StartSurface {
        heights,
        scale,
        filled,
    })
}

/// The membrane's weight beside the biharmonic energy in [`fill`]: enough to make the system
/// definite where a filled sample enters no Laplacian (a corner of the region), too small to
/// move a fill the biharmonic energy determines (its relative effect is of this order).
const MEMBRANE: f64 = 1e-6;

/// Fills the `missing` samples of `heights` by biharmonic interpolation: the least-squares minimum of Σ (Δz)² over the 5-point Laplacians
/// whose samples all have a height or are missing, the heights fixed, plus [`MEMBRANE`] ×
/// Σ (z_i − z_j)² over the missing samples' edges. [`prepare_start`] has checked that every
/// part of the missing samples touches one with a height; the error is a guard.
fn fill(heights: &mut ScalarMap, missing: &Mask) -> Result<()> {
    let (w, h) = (missing.width(), missing.height());
    let u = Unknowns::new(missing);
    let n = u.len();
    let mut index = vec![NONE; w * h];
    for (k, &p) in u.pixel.iter().enumerate() {
        index[p as usize] = k as u32;
    }
    let has_height = |q: usize| heights.data()[q].is_finite();
    let available = |q: usize| has_height(q) || missing.data()[q];
    let around = |p: usize| {
        let (x, y) = (p % w, p / w);
        [
            (x > 0).then(|| p - 1),
            (x + 1 < w).then(|| p + 1),
            (y > 0).then(|| p - w),
            (y + 1 < h).then(|| p + w),
        ]
    };
    // The normal equations' columns (lower triangle: rows ≥ the column), summed into maps.
    let mut columns: Vec<std::collections::BTreeMap<usize, f64>> = vec![Default::default(); n];
    let mut rhs = vec![0.0f64; n];
    let mut anchored = vec![false; u.parts];
    let mut add = |terms: &[(usize, f64)], weight: f64| {
        // One squared equation weight·(Σ c_q z_q)² = 0 over the samples `terms`.
        let fixed: f64 = terms
            .iter()
            .filter(|&&(q, _)| index[q] == NONE)
            .map(|&(q, c)| c * f64::from(heights.data()[q]))
            .sum();
        let free: Vec<(usize, f64)> = terms
            .iter()
            .filter(|&&(q, _)| index[q] != NONE)
            .map(|&(q, c)| (index[q] as usize, c))
            .collect();
        let touches_known = free.len() < terms.len();
        for &(i, ci) in &free {
            rhs[i] -= weight * ci * fixed;
            if touches_known {
                anchored[u.part[i] as usize] = true;
            }
            for &(j, cj) in &free {
                if j >= i {
                    *columns[i].entry(j).or_insert(0.0) += weight * ci * cj;
                }
            }
        }
    };
    for p in 0..w * h {
        if !available(p) {
            continue;
        }
        let nb = around(p);
        if nb.iter().all(|q| q.is_some_and(available)) {
            let mut terms = vec![(p, 4.0)];
            terms.extend(nb.iter().flatten().map(|&q| (q, -1.0)));
            if terms.iter().any(|&(q, _)| index[q] != NONE) {
                add(&terms, 1.0);
            }
        }
        // Each edge once: to the right and downwards.
        for q in [nb[1], nb[3]].into_iter().flatten() {
            if available(q) && (index[p] != NONE || index[q] != NONE) {
                add(&[(p, 1.0), (q, -1.0)], MEMBRANE);
            }
        }
    }
    if let Some(k) = (0..n).find(|&k| !anchored[u.part[k] as usize]) {
        let p = u.pixel[k] as usize;
        return Err(Error::param(
            "start",
            format!(
                "sample ({}, {}) has no height and no sample with one around it",
                p % w,
                p / w
            ),
        ));
    }
    let mut col_ptr = Vec::with_capacity(n + 1);
    let mut row_idx = Vec::new();
    let mut values = Vec::new();
    col_ptr.push(0);
    for column in &columns {
        for (&i, &v) in column {
            row_idx.push(i);
            values.push(v);
        }
        col_ptr.push(row_idx.len());
    }
    // The Laplacians couple samples up to two apart along an axis.
    let symbolic = symbolic_cholesky(&col_ptr, &row_idx, nested_dissection(&u, 2))?;
    CholeskyWork::new(&symbolic, Par::Seq)?
        .solve(&symbolic, &col_ptr, &row_idx, &values, &mut rhs)?;
    for (k, &p) in u.pixel.iter().enumerate() {
        heights.data_mut()[p as usize] = rhs[k] as f32;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plane in the start's own pixels: z' = a x' + b y' + c.
    fn plane_start(sw: usize, sh: usize, (a, b, c): (f64, f64, f64)) -> ScalarMap {
        let mut s = ScalarMap::new(sw, sh, 0.0);
        for j in 0..sh {
            for i in 0..sw {
                s.data_mut()[j * sw + i] = (a * i as f64 + b * j as f64 + c) as f32;
            }
        }
        s
    }

    /// The same plane on the image's grid at `scale` image pixels a start pixel, in image
    /// pixels: z = s (a x' + b y' + c) at x' = (x + ½)/s − ½.
    fn plane_on_image(x: usize, y: usize, scale: f64, (a, b, c): (f64, f64, f64)) -> f64 {
        let at = |p: usize| (p as f64 + 0.5) / scale - 0.5;
        scale * (a * at(x) + b * at(y) + c)
    }

    #[test]
    fn a_start_at_the_image_size_is_kept_as_it_is() {
        let mask = Mask::new(20, 16, true);
        let start = plane_start(20, 16, (0.3, -0.7, 5.0));
        let s = prepare_start(&start, &mask).unwrap();
        assert_eq!((s.scale, s.filled), (1.0, 0));
        assert_eq!(s.heights.data(), start.data());
    }

    #[test]
    fn a_coarse_plane_is_upsampled_to_the_same_plane_in_image_pixels() {
        let coef = (0.4, -0.25, 3.0);
        let mask = Mask::new(64, 48, true);
        let s = prepare_start(&plane_start(16, 12, coef), &mask).unwrap();
        assert_eq!((s.scale, s.filled), (4.0, 0));
        // Between the outer samples' centres the interpolation is exact; beyond them (two
        // pixels at each edge) it is clamped to the outer sample.
        let mut worst: f64 = 0.0;
        for y in 2..46 {
            for x in 2..62 {
                let v = f64::from(s.heights.data()[y * 64 + x]);
                worst = worst.max((v - plane_on_image(x, y, 4.0, coef)).abs());
            }
        }
        assert!(worst < 1e-4, "{worst}");
    }

    #[test]
    fn a_hole_in_a_plane_is_filled_with_the_plane() {
        // A hole inside a plane and one at the mask's edge: the fill is the plane, up to the
        // rounding of the f32 heights around the holes, which the fill's extrapolation to the
        // edge amplifies (to 2·10⁻⁵ of the plane's range of 27 pixels here).
        let coef = (0.5, 0.2, -1.0);
        let mask = Mask::new(40, 40, true);
        let mut start = plane_start(40, 40, coef);
        for y in 0..40 {
            for x in 0..40 {
                if (x as f64 - 20.0).hypot(y as f64 - 18.0) < 7.0 || (x < 6 && (5..15).contains(&y))
                {
                    start.data_mut()[y * 40 + x] = f32::NAN;
                }
            }
        }
        let holes = start.data().iter().filter(|v| v.is_nan()).count();
        let s = prepare_start(&start, &mask).unwrap();
        assert_eq!(s.filled, holes);
        assert!(holes > 100);
        let worst = (0..40 * 40)
            .map(|p| {
                let truth = plane_on_image(p % 40, p / 40, 1.0, coef);
                (f64::from(s.heights.data()[p]) - truth).abs()
            })
            .fold(0.0, f64::max);
        assert!(worst < 1e-4 * 27.3, "{worst}");
    }

    #[test]
    fn a_paraboloid_hole_is_filled_with_the_paraboloid() {
        // z = x² + y² is biharmonic (Δz = 4, Δ²z = 0), so the fill of a disc hole of radius R
        // reproduces it, where a membrane (Laplace's equation) would give the constant R².
        let (n, c, r) = (61usize, 30.0, 12.0);
        let mask = Mask::new(n, n, true);
        let truth = |x: usize, y: usize| (x as f64 - c).powi(2) + (y as f64 - c).powi(2);
        let mut start = ScalarMap::new(n, n, 0.0);
        for y in 0..n {
            for x in 0..n {
                let d2 = truth(x, y);
                start.data_mut()[y * n + x] = if d2 < r * r { f32::NAN } else { d2 as f32 };
            }
        }
        let s = prepare_start(&start, &mask).unwrap();
        assert!(s.filled > 400, "{}", s.filled);
        let worst = (0..n * n)
            .map(|p| (f64::from(s.heights.data()[p]) - truth(p % n, p / n)).abs())
            .fold(0.0, f64::max);
        // Of a depth of R² = 144 across the hole.
        assert!(worst < 0.01, "{worst}");
    }

    #[test]
    fn background_samples_are_not_blended_into_the_object() {
        // A disc at height 10 (in start pixels) on a background at 0, the start at half the
        // image's resolution: every pixel of the image's disc comes out at 20 image pixels,
        // the rim included.
        let mut mask = Mask::new(64, 64, false);
        for y in 0..64 {
            for x in 0..64 {
                mask.data_mut()[y * 64 + x] = (x as f64 - 31.5).hypot(y as f64 - 31.5) < 20.0;
            }
        }
        let mut start = ScalarMap::new(32, 32, 0.0);
        for j in 0..32 {
            for i in 0..32 {
                let (x, y) = (2 * i + 1, 2 * j + 1);
                if mask.data()[y * 64 + x] {
                    start.data_mut()[j * 32 + i] = 10.0;
                }
            }
        }
        let s = prepare_start(&start, &mask).unwrap();
        assert_eq!(s.scale, 2.0);
        for p in 0..64 * 64 {
            if mask.data()[p] {
                assert!((s.heights.data()[p] - 20.0).abs() < 1e-5, "{p}");
            } else {
                assert!(s.heights.data()[p].is_nan());
            }
        }
    }

    #[test]
    fn refuses_another_field_of_view_and_a_part_without_heights() {
        let mask = Mask::new(64, 48, true);
        let err = prepare_start(&ScalarMap::new(16, 16, 0.0), &mask).unwrap_err();
        assert!(
            matches!(&err, Error::InvalidParameter { name: "start", reason } if reason.contains("16×16") && reason.contains("64×48")),
            "{err}"
        );
        assert!(prepare_start(&ScalarMap::new(0, 0, 0.0), &mask).is_err());
        // Two parts; the right one has no height.
        let mut mask = Mask::new(20, 10, true);
        for y in 0..10 {
            mask.data_mut()[y * 20 + 10] = false;
        }
        let mut start = ScalarMap::new(20, 10, 1.0);
        for y in 0..10 {
            for x in 11..20 {
                start.data_mut()[y * 20 + x] = f32::NAN;
            }
        }
        let err = prepare_start(&start, &mask).unwrap_err();
        assert!(
            matches!(&err, Error::InvalidParameter { name: "start", reason } if reason.contains("(11, 0)") && reason.contains("90 pixels")),
            "{err}"
        );
    }
}
