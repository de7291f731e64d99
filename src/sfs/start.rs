//! A start surface for [`super::shape_from_shading_from`] as a depth sensor, stereo or a
//! coarse reconstruction gives it: at another resolution than the image, and with holes.
//!
//! [`prepare_start`] brings such a height map to the image's grid:
//! - **The same view.** The start covers the image's field of view with square pixels, at s
//!   image pixels a start pixel: some factor s rounds the one grid's width and height to the
//!   other's (a 320×180 sensor map for a 1280×720 image; a 1001×750 map for a 250×188 image),
//!   else it is refused. A start finer than the image (s < 1) is first averaged over the
//!   samples whose centre each image pixel holds (point samples would alias its noise), and
//!   then treated as a start at the image's resolution.
//! - **Only the object's samples.** A start sample is used only where its centre falls inside
//!   the mask: a sensor's depth map also holds the background, and blending it into the
//!   object's rim would put a cliff where the object's outline is.
//! - **Holes are filled on the start's grid**: the samples the interpolation below reads (with
//!   a weight above zero, for some pixel of the mask) that have no usable height (a sensor's
//!   dropouts: non-finite values; the background around the rim) are filled by biharmonic
//!   interpolation (the least-squares minimum of the squared 5-point Laplacians, the usable
//!   heights fixed; as scikit-image's `inpaint_biharmonic`, after S. B. Damelin and
//!   N. S. Hoang, "On surface completion and image inpainting by biharmonic functions:
//!   numerical aspects", IJMMS 2018), solved by sparse Cholesky. The fill continues the
//!   surface's slopes into a hole: exact for planes, and for quadrics such as x² + y² in a hole
//!   inside the known heights (where a membrane, Laplace's equation, flattens a cap into a
//!   cone); towards the edge of the samples read it extrapolates smoothly rather than
//!   exactly; finer detail than the known heights hold becomes a smooth patch that the shading
//!   then has to shape. Filling before interpolating keeps the surface smooth around a hole:
//!   interpolating from the remaining samples alone (weights renormalised) put a kink around
//!   every dropout and about doubled the start's normal error on rendered shapes with one
//!   sample in ten missing.
//! - **Resampling.** The centre of image pixel x lies at start coordinate x' = (x + ½)/s − ½
//!   along each axis; the height there is the bilinear interpolation of the four samples
//!   around it, multiplied by s, because heights are measured in each grid's pixels.
//!   Coordinates beyond the outer samples' centres are clamped to them. At s = 1 every image
//!   pixel is its own sample, unchanged, and nothing outside the mask is read.
//!
//! Fails where: the samples a part of the mask reads have no height and no neighbour with one
//! (nothing to fill them from): it is refused, naming a pixel of that part. A part of the
//! mask narrower than a start sample, whose samples' centres all fall outside the mask, is
//! filled from the heights beside it where its samples border one that has a height (a line
//! joining two regions), and refused otherwise. Large holes are filled, not refused;
//! [`StartSurface::filled`] says how many samples had no height of their own, and a
//! refinement from a start that is mostly filled is only as good as a refinement from a
//! smooth guess. The fill's factorisation grows as the samples it fills; a start finer than
//! the image is averaged first, so it never exceeds the image's own size.

use crate::error::{Error, Result};
use crate::grid::{Mask, ScalarMap, four_neighbours};
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
    /// a quarter of the resolution); the mean of the two axes' ratios.
    pub scale: f64,
    /// Samples inside the mask without a finite height (a sensor's dropouts) that the
    /// resampling reads, filled by biharmonic interpolation; samples of the start, or of its
    /// average on the image's grid when it was finer than the image.
    pub filled: usize,
}

/// Brings `start` (heights towards the camera in its own pixels, any offset; non-finite where
/// unknown) to the grid of `mask` (the image's): resampled to the image's resolution and
/// scaled to its pixels, holes filled (module documentation).
///
/// # Errors
/// [`Error::InvalidParameter`] (`start`) when it or the mask is empty, when its size is not
/// the image's at another resolution (no one factor rounds the one size to the other: another
/// field of view or aspect), or when the samples a part of the mask reads have no height and
/// none beside them (nothing to fill them from); (`solver`) when the fill's sparse
/// factorisation fails.
///
/// # Example
/// ```
/// use photostereo::sfs::start::prepare_start;
/// use photostereo::{Mask, ScalarMap};
///
/// // A sensor's 16×12 height map (in its own pixels) of a 64×48 image's view, a plane 2
/// // pixels up, one reading missing.
/// let mut sensor = ScalarMap::new(16, 12, 2.0);
/// sensor.data_mut()[5 * 16 + 7] = f32::NAN;
/// let start = prepare_start(&sensor, &Mask::new(64, 48, true))?;
/// assert_eq!((start.scale, start.filled), (4.0, 1));
/// // On the image's grid, in its pixels: 8 pixels up everywhere, the hole included.
/// assert!(start.heights.data().iter().all(|&z| (z - 8.0).abs() < 1e-4));
/// # Ok::<(), photostereo::Error>(())
/// ```
pub fn prepare_start(start: &ScalarMap, mask: &Mask) -> Result<StartSurface> {
    let (w, h) = (mask.width(), mask.height());
    let (sw, sh) = (start.width(), start.height());
    if sw == 0 || sh == 0 {
        return Err(Error::param("start", "is empty"));
    }
    if w == 0 || h == 0 {
        return Err(Error::param("start", "the image and its mask are empty"));
    }
    // Within a pixel of the image's size in both directions but not equal to it, a start is a
    // crop or a padding of the image's view, not another resolution of it (rounding allows a
    // factor of 1 ± 1/size there too).
    if (sw, sh) != (w, h) && sw.abs_diff(w) <= 1 && sh.abs_diff(h) <= 1 {
        return Err(Error::param(
            "start",
            format!(
                "size {sw}×{sh} is a pixel off the image's {w}×{h}: a crop or a padding of its \
                 view, not another resolution of it"
            ),
        ));
    }
    if !same_view(w, h, sw, sh) {
        return Err(Error::param(
            "start",
            format!(
                "size {sw}×{sh} is not the image's {w}×{h} at another resolution ({:.3}× \
                 across, {:.3}× down, beyond what rounding either size allows): the start must \
                 cover the image's field of view with square pixels",
                w as f64 / sw as f64,
                h as f64 / sh as f64
            ),
        ));
    }
    let scale = 0.5 * (w as f64 / sw as f64 + h as f64 / sh as f64);
    // A start finer than the image is averaged down to it first (point samples would alias
    // its noise), heights in image pixels; then it is resampled at s = 1.
    let averaged;
    let (grid, factor) = if scale < 1.0 {
        averaged = box_average(start, w, h, scale);
        (&averaged, 1.0)
    } else {
        (start, scale)
    };
    let (sw, sh) = (grid.width(), grid.height());
    let (sx, sy) = (w as f64 / sw as f64, h as f64 / sh as f64);
    // The image pixel that holds sample (i, j)'s centre.
    let pixel = |i: usize, j: usize| {
        (
            (((i as f64 + 0.5) * sx) as usize).min(w - 1),
            (((j as f64 + 0.5) * sy) as usize).min(h - 1),
        )
    };
    // The two samples around image coordinate p along an axis and the second's weight.
    let axis = |p: usize, s: f64, n: usize| -> (usize, usize, f64) {
        let t = ((p as f64 + 0.5) / s - 0.5).clamp(0.0, (n - 1) as f64);
        let i0 = (t.floor() as usize).min(n - 1);
        let i1 = (i0 + 1).min(n - 1);
        (i0, i1, t - i0 as f64)
    };
    // The samples each mask pixel reads (with a weight > 0) and their weights.
    let reads = |x: usize, y: usize| {
        let (i0, i1, fx) = axis(x, sx, sw);
        let (j0, j1, fy) = axis(y, sy, sh);
        [
            (i0, j0, (1.0 - fx) * (1.0 - fy)),
            (i1, j0, fx * (1.0 - fy)),
            (i0, j1, (1.0 - fx) * fy),
            (i1, j1, fx * fy),
        ]
        .into_iter()
        .filter(|&(_, _, c)| c > 0.0)
    };
    // Samples read, each with one mask pixel that reads it (to name in a refusal).
    let mut reader = vec![usize::MAX; sw * sh];
    for y in 0..h {
        for x in 0..w {
            if mask.data()[y * w + x] {
                for (i, j, _) in reads(x, y) {
                    let q = j * sw + i;
                    if reader[q] == usize::MAX {
                        reader[q] = y * w + x;
                    }
                }
            }
        }
    }
    // A sample's height is used where it is finite and its centre falls inside the mask (the
    // object's); the other samples read are filled.
    let mut samples = ScalarMap::new(sw, sh, f32::NAN);
    let mut missing = Mask::new(sw, sh, false);
    let mut filled = 0;
    for (q, (&v, &read_by)) in grid.data().iter().zip(&reader).enumerate() {
        let (x, y) = pixel(q % sw, q / sw);
        let inside = mask.data()[y * w + x];
        if inside && v.is_finite() {
            samples.data_mut()[q] = v;
        } else if read_by != usize::MAX {
            missing.data_mut()[q] = true;
            filled += usize::from(inside);
        }
    }
    if missing.count() > 0
        && let Err(q) = fill(&mut samples, &missing)?
    {
        let p = reader[q];
        let size = missing.count();
        return Err(Error::param(
            "start",
            format!(
                "the part of the mask around pixel ({}, {}) reads no start height, nor any \
                 beside the samples it reads ({size} samples without a height in all): nothing \
                 to fill them from",
                p % w,
                p / w
            ),
        ));
    }
    let mut heights = ScalarMap::new(w, h, f32::NAN);
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            if mask.data()[p] {
                let z: f64 = reads(x, y)
                    .map(|(i, j, c)| c * f64::from(samples.data()[j * sw + i]))
                    .sum();
                heights.data_mut()[p] = (factor * z) as f32;
            }
        }
    }
    Ok(StartSurface {
        heights,
        scale,
        filled,
    })
}

/// Whether a start of `sw`×`sh` samples can cover the view of a `w`×`h` image with square
/// pixels: some factor s makes both of its sizes round to the image's (w = round(s·sw),
/// h = round(s·sh)), or both of the image's round to its (sw = round(w/s), sh = round(h/s)).
fn same_view(w: usize, h: usize, sw: usize, sh: usize) -> bool {
    let (w, h, sw, sh) = (w as f64, h as f64, sw as f64, sh as f64);
    // Open intervals of s; a tie on their ends is not an overlap.
    let overlap = |(a0, a1): (f64, f64), (b0, b1): (f64, f64)| a0.max(b0) < a1.min(b1);
    let image_rounded = overlap(
        ((w - 0.5) / sw, (w + 0.5) / sw),
        ((h - 0.5) / sh, (h + 0.5) / sh),
    );
    let start_rounded = overlap(
        (w / (sw + 0.5), w / (sw - 0.5).max(f64::MIN_POSITIVE)),
        (h / (sh + 0.5), h / (sh - 0.5).max(f64::MIN_POSITIVE)),
    );
    image_rounded || start_rounded
}

/// `start`, finer than the `w`×`h` image by `scale` < 1, averaged over the finite samples whose
/// centre each image pixel holds, its heights times `scale` (in the image's pixels); NaN where
/// a pixel holds none.
fn box_average(start: &ScalarMap, w: usize, h: usize, scale: f64) -> ScalarMap {
    let (sw, sh) = (start.width(), start.height());
    let (sx, sy) = (w as f64 / sw as f64, h as f64 / sh as f64);
    let mut sum = vec![0.0f64; w * h];
    let mut count = vec![0usize; w * h];
    for j in 0..sh {
        let y = (((j as f64 + 0.5) * sy) as usize).min(h - 1);
        for i in 0..sw {
            let v = start.data()[j * sw + i];
            if v.is_finite() {
                let x = (((i as f64 + 0.5) * sx) as usize).min(w - 1);
                sum[y * w + x] += f64::from(v);
                count[y * w + x] += 1;
            }
        }
    }
    ScalarMap::from_fn(w, h, |x, y| {
        let p = y * w + x;
        if count[p] == 0 {
            f32::NAN
        } else {
            (scale * sum[p] / count[p] as f64) as f32
        }
    })
}

/// The membrane's weight beside the biharmonic energy in [`fill`]: enough to make the system
/// definite where a filled sample enters no Laplacian (a corner of the region), too small to
/// move a fill the biharmonic energy determines (its relative effect is of this order).
const MEMBRANE: f64 = 1e-6;

/// Fills the `missing` samples of `heights` by biharmonic interpolation: the least-squares
/// minimum of Σ (Δz)² over the 5-point Laplacians whose samples all have a height or are
/// missing, the heights fixed, plus [`MEMBRANE`] × Σ (z_i − z_j)² over the missing samples'
/// edges. `Ok(Err(q))`, `heights` unchanged, when a 4-connected part of the missing samples
/// (sample `q` one of them) has no neighbour with a height: nothing to fill it from.
///
/// Quadrics are reproduced where every Laplacian that reaches a filled sample can be formed
/// (a hole inside the known heights); towards the edge of the samples read, the fill
/// extrapolates with Laplacians set to zero, a smooth continuation rather than an exact one.
fn fill(heights: &mut ScalarMap, missing: &Mask) -> Result<std::result::Result<(), usize>> {
    let (w, h) = (missing.width(), missing.height());
    let u = Unknowns::new(missing);
    let n = u.len();
    let mut index = vec![NONE; w * h];
    for (k, &p) in u.pixel.iter().enumerate() {
        index[p as usize] = k as u32;
    }
    let has_height = |q: usize| heights.data()[q].is_finite();
    let available = |q: usize| has_height(q) || missing.data()[q];
    // The normal equations' entries of each column (lower triangle: rows ≥ the column), as
    // products to be sorted and summed.
    let mut columns: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
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
                    columns[i].push((j, weight * ci * cj));
                }
            }
        }
    };
    for p in 0..w * h {
        if !available(p) {
            continue;
        }
        let nb = four_neighbours(p, w, h);
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
        return Ok(Err(u.pixel[k] as usize));
    }
    let mut col_ptr = Vec::with_capacity(n + 1);
    let mut row_idx = Vec::new();
    let mut values: Vec<f64> = Vec::new();
    col_ptr.push(0);
    for column in &mut columns {
        column.sort_unstable_by_key(|&(i, _)| i);
        let first = row_idx.len();
        for &(i, v) in column.iter() {
            let last = row_idx.len();
            if last > first && row_idx[last - 1] == i {
                values[last - 1] += v;
            } else {
                row_idx.push(i);
                values.push(v);
            }
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
    Ok(Ok(()))
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
        // An empty image is refused, not indexed.
        assert!(prepare_start(&ScalarMap::new(4, 4, 0.0), &Mask::new(0, 0, true)).is_err());
        assert!(prepare_start(&ScalarMap::new(1, 4, 0.0), &Mask::new(0, 4, true)).is_err());
        // A row short or long is refused: at s = 1 (either way round; 128 and 129 both round
        // from one factor near 1.004, but that is a crop, not a resampling) and at s = 4.
        let square = Mask::new(128, 128, true);
        let err = prepare_start(&ScalarMap::new(128, 127, 0.0), &square).unwrap_err();
        assert!(err.to_string().contains("a crop or a padding"), "{err}");
        assert!(prepare_start(&ScalarMap::new(128, 129, 0.0), &square).is_err());
        assert!(prepare_start(&ScalarMap::new(128, 128, 0.0), &Mask::new(128, 129, true)).is_err());
        assert!(prepare_start(&ScalarMap::new(32, 31, 0.0), &square).is_err());
        // Sizes rounded from one factor are accepted either way round: a 1280×722 image's
        // view at 320×181 (722/4 = 180.5 rounds to 181), and a finer start whose size rounds
        // to the image's (250×188 from 1001×750 at s ≈ 0.2499).
        assert!(prepare_start(&ScalarMap::new(320, 181, 0.0), &Mask::new(1280, 722, true)).is_ok());
        let fine =
            prepare_start(&ScalarMap::new(1001, 750, 1.0), &Mask::new(250, 188, true)).unwrap();
        assert!((fine.scale - 0.2502).abs() < 1e-3, "{}", fine.scale);
        // Two parts; the right one has no height, and none beside it.
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
            matches!(&err, Error::InvalidParameter { name: "start", reason } if reason.contains("(11, 0)") && reason.contains("nothing to fill them from")),
            "{err}"
        );
    }

    #[test]
    fn a_thin_part_between_samples_is_filled_and_a_lone_one_is_named() {
        // At s = 4: two discs joined by a line one pixel wide that holds no sample's centre
        // (the centres are at 4i + 2); the line is filled from the discs' heights.
        let mut mask = Mask::new(64, 32, false);
        for y in 0..32 {
            for x in 0..64 {
                let disc = |cx: f64| (x as f64 - cx).hypot(y as f64 - 15.5) < 9.0;
                mask.data_mut()[y * 64 + x] = disc(12.0) || disc(52.0) || (y == 16 && x < 50);
            }
        }
        let start = plane_start(16, 8, (0.25, 0.0, 1.0));
        let s = prepare_start(&start, &mask).unwrap();
        for p in 0..64 * 32 {
            assert_eq!(s.heights.data()[p].is_finite(), mask.data()[p], "{p}");
        }
        // Along the line the fill bridges the discs: rising with x as the plane does, and
        // within 1% of the plane's range across the image (15 px). Not exactly the plane: the
        // line's samples are reached by few Laplacians, and the filled ring around the discs
        // ends in free boundaries.
        let mut last = f64::NEG_INFINITY;
        for x in 22..43 {
            let v = f64::from(s.heights.data()[16 * 64 + x]);
            let truth = plane_on_image(x, 16, 4.0, (0.25, 0.0, 1.0));
            assert!((v - truth).abs() < 0.15, "({x}, 16): {v} against {truth}");
            assert!(v > last, "({x}, 16): {v} after {last}");
            last = v;
        }
        // A blob far from every height: refused, naming one of its pixels.
        let mut lone = Mask::new(64, 32, false);
        for y in 0..32 {
            for x in 0..64 {
                let disc = (x as f64 - 12.0).hypot(y as f64 - 15.5) < 9.0;
                lone.data_mut()[y * 64 + x] =
                    disc || ((56..60).contains(&x) && (4..8).contains(&y));
            }
        }
        let mut holed = plane_start(16, 8, (0.25, 0.0, 1.0));
        for j in 0..3 {
            for i in 12..16 {
                holed.data_mut()[j * 16 + i] = f32::NAN;
            }
        }
        let err = prepare_start(&holed, &lone).unwrap_err();
        let named = |x: usize, y: usize| err.to_string().contains(&format!("pixel ({x}, {y})"));
        assert!((56..60).any(|x| (4..8).any(|y| named(x, y))), "{err}");
    }

    #[test]
    fn at_the_image_size_only_the_mask_is_read() {
        // A partial mask and a start that is finite everywhere: the mask's heights pass
        // unchanged, nothing outside is filled or written.
        let coef = (0.3, 0.1, 2.0);
        let mut mask = Mask::new(40, 30, false);
        for p in 0..40 * 30 {
            mask.data_mut()[p] = ((p % 40) as f64 - 20.0).hypot((p / 40) as f64 - 15.0) < 11.0;
        }
        let start = plane_start(40, 30, coef);
        let s = prepare_start(&start, &mask).unwrap();
        assert_eq!(s.filled, 0);
        for p in 0..40 * 30 {
            if mask.data()[p] {
                assert_eq!(s.heights.data()[p], start.data()[p]);
            } else {
                assert!(s.heights.data()[p].is_nan());
            }
        }
    }

    #[test]
    fn a_finer_start_is_averaged_to_the_image() {
        // 4× finer: each image pixel averages the 4×4 samples whose centres it holds, whose
        // mean lies at its centre, so a plane comes out as the same plane in image pixels
        // (a quarter of the heights); noise is averaged down by the 16 samples.
        let coef = (0.8, -0.4, 10.0);
        let mask = Mask::new(64, 48, true);
        let mut start = plane_start(256, 192, coef);
        let mut state = 12345u64;
        let mut noisy = start.clone();
        for v in noisy.data_mut() {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            *v += ((state >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.4;
        }
        // A missing sample: its pixel averages the other 15 (still a height, nothing filled).
        start.data_mut()[5] = f32::NAN;
        let s = prepare_start(&start, &mask).unwrap();
        assert_eq!((s.scale, s.filled), (0.25, 0));
        assert!(s.heights.data()[1].is_finite());
        let worst = (0..64 * 48)
            .filter(|&p| p != 1)
            .map(|p| {
                let truth = plane_on_image(p % 64, p / 64, 0.25, coef);
                (f64::from(s.heights.data()[p]) - truth).abs()
            })
            .fold(0.0, f64::max);
        assert!(worst < 1e-4, "{worst}");
        // Uniform noise of ±0.2 start pixels (σ 0.115): averaged over 16 samples and scaled
        // by a quarter, σ 0.0072 image pixels; the largest of 3 072 stays under 5σ.
        let n = prepare_start(&noisy, &mask).unwrap();
        let worst = (0..64 * 48)
            .map(|p| {
                let truth = plane_on_image(p % 64, p / 64, 0.25, coef);
                (f64::from(n.heights.data()[p]) - truth).abs()
            })
            .fold(0.0, f64::max);
        assert!(worst < 0.036, "{worst}");
    }

    #[test]
    fn a_start_one_sample_wide_is_resampled() {
        // 1×16 for a 4×64 image (s = 4): heights along y only, a line in image pixels.
        let mask = Mask::new(4, 64, true);
        let start = plane_start(1, 16, (0.0, 0.5, 1.0));
        let s = prepare_start(&start, &mask).unwrap();
        assert_eq!(s.scale, 4.0);
        for y in 2..62 {
            let truth = plane_on_image(0, y, 4.0, (0.0, 0.5, 1.0));
            for x in 0..4 {
                let v = f64::from(s.heights.data()[y * 4 + x]);
                assert!((v - truth).abs() < 1e-4, "({x}, {y}): {v} against {truth}");
            }
        }
    }
}
