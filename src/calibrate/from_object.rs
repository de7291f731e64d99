//! Lights recovered from the object itself: uncalibrated photometric stereo.
//!
//! Without a calibration object, a Lambertian image stack I (pixels × images) is the product of
//! the scaled normals B (b = ρn) and the scaled lights S, I = B S, known only up to an invertible
//! 3×3 A: I = (B A)(A⁻¹ S). Four steps narrow A down:
//!
//! 1. **Factorisation** (Hayakawa, JOSA A 11(11), 1994). The pixels lit in every image (no sample
//!    below [`FromObjectOptions::dark_fraction`] of its image's bright level) form a rank-3
//!    matrix whose three leading singular vectors start pseudo-lights S̃. Alternating least
//!    squares then refits every pixel's pseudo-normal b̃ from its usable samples and every
//!    light from the pixels where it is usable, leaving out samples more than 3 robust
//!    deviations off the rank-3 fit (highlights, interreflections) or predicted in shadow.
//! 2. **Integrability** (Yuille & Snow, CVPR 1997; Belhumeur, Kriegman & Yuille, IJCV 35(1),
//!    1999). The surface z with −∇z = (b₁, b₂)/b₃ exists only if ∂_y(b₁/b₃) = ∂_x(b₂/b₃), that is
//!    b₃∂_y b₁ − b₁∂_y b₃ = b₃∂_x b₂ − b₂∂_x b₃. With b = Aᵀb̃ each side is linear in the six
//!    components of a₃×a₁ and a₃×a₂ (a_i the columns of A): the 2×2 cells of well-fitted pixels
//!    give a homogeneous least-squares problem whose null vector fixes A up to the generalized
//!    bas-relief (GBR) transform b ↦ (b₁ + μb₃, b₂ + νb₃, λb₃), and up to the sign of the null
//!    vector, which mirrors the normals (the convex/concave ambiguity).
//! 3. **GBR by minimum albedo entropy** (Alldrin, Mallick & Kriegman, "Resolving the generalized
//!    bas-relief ambiguity by entropy minimization", CVPR 2007): the true (μ, ν, λ) makes the
//!    albedos of a surface painted in a few colours cluster, so the entropy of the histogram of
//!    ln ρ (shift-invariant: the overall scale does not matter) is smallest there. It is searched
//!    on a grid, then on finer grids around the best point.
//! 4. **GBR refined by local diffuse maxima** (Papadhimitri & Favaro, "A new perspective on
//!    uncalibrated photometric stereo", CVPR 2013): in each image the pixels brightest relative
//!    to their albedo (at the entropy's GBR) face the light; the GBR that best aligns their mean
//!    normal with the light is searched the same way.
//!
//! The sign is chosen so that the normals along the mask's outline point outwards (the object
//! is convex at its outline), and the report says so.
//!
//! # When it fails
//! - **Uniform albedo** leaves the entropy flat; the local diffuse maxima then decide, and they
//!   need some surface facing each light.
//! - **Non-Lambertian samples** beyond what the outlier test removes (broad highlights) take the
//!   data off rank 3: refused ([`FromObjectOptions::min_rank3_gap`]).
//! - **Too few pixels lit everywhere**, or lights in one plane: refused.
//! - **Noise** above about 1%: the integrability step's differences drown
//!   (docs/lights-from-the-object.md).

use crate::capture::lights::{Light, Lights};
use crate::error::{Error, Result};
use crate::grid::{Mask, ScalarMap};
use nalgebra::{DMatrix, Matrix3, Matrix6, SymmetricEigen, Vector3, Vector6};
use rayon::prelude::*;
use serde::Serialize;

/// Default [`FromObjectOptions::min_rank3_gap`], chosen on rendered spheres: glossy ones whose
/// recovery was 8–94° off had gaps of 1.0–1.8, those within 1.5° at least 3.2 (DiLiGenT cat,
/// bear and reading: 8.3, 3.7 and 3.0).
pub const MIN_RANK3_GAP: f64 = 2.0;

/// Options of [`lights_from_object`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FromObjectOptions {
    /// A sample below this fraction of its image's bright level (99th percentile of the mask)
    /// counts as shadowed; a pixel is used for the factorisation only when no sample is.
    pub dark_fraction: f64,
    /// Most pixels used by the factorisation and the entropy (evenly subsampled beyond).
    pub max_pixels: usize,
    /// Smallest ratio of the third to the fourth singular value of the lit pixels' brightness
    /// accepted: below it the data are not clearly rank 3 (broad highlights, strong
    /// interreflections) and the recovery is refused rather than answered wrong.
    pub min_rank3_gap: f64,
}

impl Default for FromObjectOptions {
    fn default() -> Self {
        FromObjectOptions {
            dark_fraction: 0.05,
            max_pixels: 40_000,
            min_rank3_gap: MIN_RANK3_GAP,
        }
    }
}

/// Lights recovered from the object, with what was assumed.
#[derive(Debug, Clone, Serialize)]
pub struct ObjectLights {
    /// Unit light directions, one per image.
    pub directions: Vec<[f64; 3]>,
    /// Relative intensities (mean 1).
    pub intensities: Vec<f64>,
    /// Each light's split-half spread (degrees): half the angle between the directions
    /// recovered from two halves of the pixels (alternate bands of rows); infinite when a half
    /// failed. A spread, not a bound: it misses errors both halves share and overstates noise
    /// (each half has half the pixels).
    pub uncertainty_deg: Vec<f64>,
    /// The GBR parameters (μ, ν, λ) chosen (local diffuse maxima, from the entropy's choice).
    pub gbr: [f64; 3],
    /// The GBR parameters the albedo entropy alone chose.
    pub gbr_entropy: [f64; 3],
    /// Mean angle between each image's local diffuse maxima's normal and its light at the
    /// chosen GBR (degrees; 0 for an ideal Lambertian surface with a normal facing each light).
    pub ldr_residual_deg: f64,
    /// Entropy (nats) of the log-albedo histogram at the chosen GBR.
    pub entropy: f64,
    /// How much lower that entropy is than the median over the searched grid (nats): a small
    /// drop means a flat criterion and an unreliable GBR.
    pub entropy_drop: f64,
    /// Pixels lit in every image (used for the factorisation and integrability).
    pub lit_pixels: usize,
    /// Ratio of the third to the fourth singular value of the lit pixels' matrix: how clearly the
    /// data are rank 3.
    pub rank3_gap: f64,
    /// Fraction of the usable samples (neither dark nor saturated) that the robust rank-3 fit
    /// left out as outliers (highlights, interreflections, shadows it predicts).
    pub outlier_fraction: f64,
    /// Robust deviation of the inlier samples from the rank-3 fit, over the mean inlier
    /// brightness.
    pub relative_deviation: f64,
    /// Fraction of outline pixels whose normal points outwards, after the sign choice.
    pub outline_outward: f64,
    /// What was assumed.
    pub assumptions: Vec<String>,
    /// What looks unreliable.
    pub warnings: Vec<String>,
}

/// Fraction of the outline's normals that must point outwards for the convex/concave choice
/// to count as settled.
pub const OUTLINE_SETTLED: f64 = 0.75;
/// Entropy drop (nats) below which the GBR is reported as weakly determined.
pub const WEAK_ENTROPY_DROP: f64 = 0.1;

impl ObjectLights {
    /// The lights, for photometric stereo.
    ///
    /// # Errors
    /// As [`Lights::new`].
    pub fn lights(&self) -> Result<Lights> {
        let lights = self
            .directions
            .iter()
            .zip(&self.intensities)
            .map(|(d, &i)| {
                let mut l = Light::new(Vector3::from(*d));
                l.intensity = [i; 3];
                l
            })
            .collect();
        Lights::new(lights)
    }

    /// The lights file: the JSON lights format with each light's `uncertainty_deg` (the
    /// split-half spread) and a `calibration` section holding this recovery.
    pub fn lights_file_json(&self) -> String {
        let entries: Vec<serde_json::Value> = self
            .directions
            .iter()
            .zip(&self.intensities)
            .zip(&self.uncertainty_deg)
            .map(|((d, i), u)| {
                serde_json::json!({
                    "direction": d,
                    "intensity": i,
                    "uncertainty_deg": if u.is_finite() { Some(*u) } else { None },
                })
            })
            .collect();
        let doc = serde_json::json!({
            "lights": entries,
            "calibration": {
                "method": "from the object (uncalibrated photometric stereo): rank-3 factorisation, integrability, minimum albedo entropy",
                "uncertainty": "half the angle between the directions recovered from two halves of the pixels: a spread, not a bound (it misses model errors both halves share, and overstates noise since each half has half the pixels)",
                "recovery": self,
            },
        });
        // Serialising numbers, strings and derived structs cannot fail.
        serde_json::to_string_pretty(&doc).unwrap_or_default()
    }
}

/// The images' bright level: the 99th percentile of each over the mask.
fn bright_levels(images: &[ScalarMap], mask: &Mask) -> Vec<f64> {
    images
        .iter()
        .map(|im| {
            let mut v: Vec<f32> = im
                .data()
                .iter()
                .zip(mask.data())
                .filter(|(x, m)| **m && x.is_finite())
                .map(|(x, _)| *x)
                .collect();
            crate::stats::quantile_in_place(&mut v, 0.99).map_or(0.0, f64::from)
        })
        .collect()
}

/// Lights (directions and relative intensities) of a stack of linear grey `images` of one
/// Lambertian-looking object inside `mask`, recovered from the images alone (see the module
/// documentation).
///
/// # Errors
/// [`Error::DimensionMismatch`] when an image's size differs from the mask's;
/// [`Error::InvalidParameter`] when fewer than 4 images are given, an image is black inside the
/// mask, the dark fraction is outside [0, 1), fewer than 64 pixels are lit in every image, the
/// data are rank 2 or not clearly rank 3 ([`FromObjectOptions::min_rank3_gap`]), or too few
/// pixels are well fitted to enforce integrability.
pub fn lights_from_object(
    images: &[ScalarMap],
    mask: &Mask,
    options: &FromObjectOptions,
) -> Result<ObjectLights> {
    let mut all = recover(images, mask, &|_| true, options)?;
    // Split-half check: the same recovery from alternate bands of rows.
    let w = mask.width();
    let band = |pix: usize| (pix / w / SPLIT_BAND).is_multiple_of(2);
    let halves = [
        recover(images, mask, &band, options),
        recover(images, mask, &|p| !band(p), options),
    ];
    match halves {
        [Ok(a), Ok(b)] => {
            all.uncertainty_deg = a
                .directions
                .iter()
                .zip(&b.directions)
                .map(|(x, y)| Vector3::from(*x).angle(&Vector3::from(*y)).to_degrees() / 2.0)
                .collect();
        }
        _ => {
            all.uncertainty_deg = vec![f64::INFINITY; images.len()];
            all.assumptions.push(
                "the split-half check failed (one half of the rows alone is not enough): the \
                 lights' uncertainty is unknown"
                    .to_string(),
            );
        }
    }
    Ok(all)
}

/// Rows per band of the split-half check.
const SPLIT_BAND: usize = 16;

/// The recovery from the pixels of `mask` for which `region` holds (the mask's outline is
/// still the whole mask's).
fn recover(
    images: &[ScalarMap],
    mask: &Mask,
    region: &dyn Fn(usize) -> bool,
    options: &FromObjectOptions,
) -> Result<ObjectLights> {
    let f = images.len();
    if f < 4 {
        return Err(Error::param(
            "images",
            format!("{f} given: recovering lights from the object needs at least 4"),
        ));
    }
    for im in images {
        im.check_same_size(mask, "mask")?;
    }
    if !(options.dark_fraction.is_finite() && (0.0..1.0).contains(&options.dark_fraction)) {
        return Err(Error::param(
            "dark-fraction",
            format!("{} is outside [0, 1)", options.dark_fraction),
        ));
    }
    let (w, h) = (mask.width(), mask.height());
    let bright = bright_levels(images, mask);
    if let Some(i) = bright.iter().position(|&b| b.is_nan() || b <= 0.0) {
        return Err(Error::param(
            "images",
            format!("image {i} is black inside the mask"),
        ));
    }
    let sample = |pix: usize, i: usize| f64::from(images[i].data()[pix]);
    let lit: Vec<bool> = (0..w * h)
        .map(|pix| {
            mask.data()[pix]
                && region(pix)
                && (0..f).all(|i| {
                    let v = sample(pix, i);
                    v.is_finite() && v > options.dark_fraction * bright[i]
                })
        })
        .collect();
    let lit_pixels = lit.iter().filter(|&&b| b).count();
    if lit_pixels < 64 {
        return Err(Error::param(
            "images",
            format!(
                "only {lit_pixels} pixels of the mask are lit in every image (64 needed): the \
                 lights cannot be recovered from the object"
            ),
        ));
    }
    // 1. Factorisation: the Gram matrix of the lit pixels (images × images).
    let step = lit_pixels.div_ceil(options.max_pixels.max(64));
    let chosen: Vec<usize> = (0..w * h).filter(|&p| lit[p]).step_by(step).collect();
    let mut gram = DMatrix::<f64>::zeros(f, f);
    for &pix in &chosen {
        for i in 0..f {
            let a = sample(pix, i);
            for j in i..f {
                gram[(i, j)] += a * sample(pix, j);
            }
        }
    }
    for i in 0..f {
        for j in 0..i {
            gram[(i, j)] = gram[(j, i)];
        }
    }
    let eig = SymmetricEigen::new(gram);
    let mut order: Vec<usize> = (0..f).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let sv: Vec<f64> = order
        .iter()
        .map(|&k| eig.eigenvalues[k].max(0.0).sqrt())
        .collect();
    if sv[2].is_nan() || sv[2] <= RANK_TOLERANCE * sv[0] {
        return Err(Error::param(
            "images",
            "the lit pixels' brightness is rank 2 or less (lights in one plane, or one light \
             repeated): the lights cannot be recovered",
        ));
    }
    let rank3_gap = if f > 3 && sv[3] > 0.0 {
        sv[2] / sv[3]
    } else {
        f64::INFINITY
    };
    if rank3_gap < options.min_rank3_gap {
        return Err(Error::param(
            "images",
            format!(
                "the brightness of the pixels lit in every image is not clearly rank 3 (third \
                 to fourth singular value {rank3_gap:.2}, below {:.2}): the object is far from \
                 Lambertian (broad highlights or strong interreflections), and lights recovered \
                 from it would be wrong; photograph a chrome ball instead",
                options.min_rank3_gap
            ),
        ));
    }
    // Pseudo-lights S̃ = Σ Vᵀ, refined below with the pseudo-normals (any split of Σ between
    // the two factors is absorbed by A).
    let v: Vec<Vector3<f64>> = (0..f)
        .map(|i| Vector3::from_fn(|r, _| eig.eigenvectors[(i, order[r])]))
        .collect();
    let mut pseudo_lights: Vec<Vector3<f64>> = v
        .iter()
        .map(|vi| Vector3::new(vi.x * sv[0], vi.y * sv[1], vi.z * sv[2]))
        .collect();
    // Robust refinement (alternating least squares with missing samples): every pixel's
    // pseudo-normal from its usable samples, each light from the pixels where it is usable;
    // samples off the rank-3 fit by more than OUTLIER_SCALES robust deviations (highlights,
    // interreflections) or predicted in shadow are left out, and the fit repeated.
    let usable = |pix: usize, i: usize| {
        let v = sample(pix, i);
        v.is_finite() && v > options.dark_fraction * bright[i]
    };
    let any: Vec<usize> = (0..w * h)
        .filter(|&p| mask.data()[p] && region(p) && (0..f).filter(|&i| usable(p, i)).count() >= 4)
        .collect();
    let any_step = any.len().div_ceil(options.max_pixels.max(64));
    let fit_set: Vec<usize> = any.iter().copied().step_by(any_step).collect();
    let mut sigma = f64::INFINITY;
    let usable_samples: usize = fit_set
        .iter()
        .map(|&p| (0..f).filter(|&i| usable(p, i)).count())
        .sum();
    let mut inlier_samples = usable_samples;
    let mut mean_inlier = 1.0;
    for _ in 0..ALS_ROUNDS {
        type Sums = (Vec<(Matrix3<f64>, Vector3<f64>)>, Vec<f64>, f64);
        let zero = || -> Sums {
            (
                vec![(Matrix3::zeros(), Vector3::zeros()); f],
                Vec::new(),
                0.0,
            )
        };
        // In fixed chunks and order, so that the lights do not change from run to run.
        let (normal_s, abs_res, inlier_sum) = crate::pool::ordered_fold(
            fit_set.len(),
            zero,
            |mut acc, k| {
                let pix = fit_set[k];
                let fitted = fit_pixel(
                    &pseudo_lights,
                    f,
                    |i| usable(pix, i).then(|| sample(pix, i)),
                    sigma,
                    options.dark_fraction,
                    &bright,
                );
                let Some((b, _)) = fitted else {
                    return acc;
                };
                let bb = b * b.transpose();
                for i in 0..f {
                    if !usable(pix, i) {
                        continue;
                    }
                    let pred = b.dot(&pseudo_lights[i]);
                    let r = sample(pix, i) - pred;
                    if pred > options.dark_fraction * bright[i] && r.abs() <= OUTLIER_SCALES * sigma
                    {
                        acc.1.push(r.abs());
                        acc.2 += sample(pix, i);
                        acc.0[i].0 += bb;
                        acc.0[i].1 += b * sample(pix, i);
                    }
                }
                acc
            },
            |mut a, b| {
                for (x, y) in a.0.iter_mut().zip(&b.0) {
                    x.0 += y.0;
                    x.1 += y.1;
                }
                a.1.extend(b.1);
                a.2 += b.2;
                a
            },
        );
        for (i, (m, r)) in normal_s.iter().enumerate() {
            if let Some(inv) = m.try_inverse() {
                pseudo_lights[i] = inv * r;
            }
        }
        if abs_res.is_empty() {
            break;
        }
        inlier_samples = abs_res.len();
        mean_inlier = inlier_sum / inlier_samples as f64;
        sigma = 1.4826 * crate::stats::median(abs_res);
    }
    let mut bt = vec![Vector3::zeros(); w * h];
    let mut good = vec![false; w * h];
    let fits: Vec<Option<(Vector3<f64>, usize)>> = any
        .par_iter()
        .map(|&pix| {
            fit_pixel(
                &pseudo_lights,
                f,
                |i| usable(pix, i).then(|| sample(pix, i)),
                sigma,
                options.dark_fraction,
                &bright,
            )
        })
        .collect();
    for (&pix, fit) in any.iter().zip(fits) {
        if let Some((b, n)) = fit {
            bt[pix] = b;
            good[pix] = n as f64 >= GOOD_FRACTION * f as f64;
        }
    }
    // Pixels with fewer than 4 usable samples (near the outline, in shadow): least squares on
    // the usable ones against the same lights, when 3 are left, for the sign test.
    for (pix, b) in bt.iter_mut().enumerate() {
        if mask.data()[pix] && *b == Vector3::zeros() {
            let (mut m, mut r, mut n) = (Matrix3::<f64>::zeros(), Vector3::<f64>::zeros(), 0);
            for (i, s) in pseudo_lights.iter().enumerate() {
                if usable(pix, i) {
                    m += s * s.transpose();
                    r += s * sample(pix, i);
                    n += 1;
                }
            }
            if n >= 3
                && let Some(inv) = m.try_inverse()
            {
                *b = inv * r;
            }
        }
    }
    // 2. Integrability over the 2×2 cells of well-fitted pixels (y up: the top row is +y).
    let Some((normal, _)) = integrability_system(&bt, &good, w, h, 1) else {
        return Err(Error::param(
            "images",
            "fewer than 16 2×2 blocks of pixels are well fitted in most images: too few to \
             enforce integrability",
        ));
    };
    let e6 = SymmetricEigen::new(normal);
    let k_min = (0..6)
        .min_by(|&a, &b| e6.eigenvalues[a].total_cmp(&e6.eigenvalues[b]))
        .unwrap_or(0);
    let c = e6.eigenvectors.column(k_min).into_owned();
    // c = (c1₁₂, c1₁₃, c1₂₃, c2₁₂, c2₁₃, c2₂₃) with c1 = a₃×a₁ = (c1₂₃, −c1₁₃, c1₁₂).
    let c1 = Vector3::new(c[2], -c[1], c[0]);
    let c2 = Vector3::new(c[5], -c[4], c[3]);
    let a3 = c1.cross(&c2);
    if a3.norm().is_nan() || a3.norm() == 0.0 {
        return Err(Error::param(
            "images",
            "integrability left the ambiguity undetermined (a degenerate surface)",
        ));
    }
    let a3 = a3.normalize();
    let a1 = c1.cross(&a3);
    let a2 = c2.cross(&a3);
    let base = Matrix3::from_columns(&[a1, a2, a3]);
    // b̄ = Aᵀ b̃; the sign of the null vector mirrors (b₁, b₂).
    let mut bbar: Vec<Vector3<f64>> = bt.iter().map(|b| base.transpose() * b).collect();
    // b₃ > 0 on most lit pixels (the other sign is the same surface seen from behind).
    // The lit pixels whose fit kept most samples: the sign vote, the column scales and the
    // albedo histogram use these.
    let chosen: Vec<usize> = chosen.into_iter().filter(|&p| good[p]).collect();
    if chosen.is_empty() {
        return Err(Error::param(
            "images",
            "no pixel lit in every image is well fitted by the rank-3 model",
        ));
    }
    let positive = chosen.iter().filter(|&&p| bbar[p].z > 0.0).count();
    if 2 * positive < chosen.len() {
        for b in &mut bbar {
            *b = -*b;
        }
    }
    // Column scales: b̄₃ to the size of (b̄₁, b̄₂), so the GBR grid is in natural units.
    let rms = |g: &dyn Fn(&Vector3<f64>) -> f64| {
        (chosen.iter().map(|&p| g(&bbar[p]).powi(2)).sum::<f64>() / chosen.len() as f64).sqrt()
    };
    let (rxy, rz) = (rms(&|b| b.xy().norm()), rms(&|b| b.z));
    let scale3 = if rz > 0.0 { rxy / rz } else { 1.0 };
    for b in &mut bbar {
        b.z *= scale3;
    }
    let entropy_step = chosen.len().div_ceil(ENTROPY_PIXELS);
    let lit_bbar: Vec<Vector3<f64>> = chosen
        .iter()
        .step_by(entropy_step)
        .map(|&p| bbar[p])
        .collect();
    // 3. GBR by minimum entropy of ln ρ.
    let (gbr0, entropy, entropy_drop) = minimise_entropy(&lit_bbar);
    // 4. GBR refined by local diffuse maxima (Papadhimitri & Favaro 2013): in each image, the
    // pixels brightest relative to their albedo (at the entropy's GBR) face the light.
    let flip = if 2 * positive < chosen.len() {
        -1.0
    } else {
        1.0
    };
    let (gbr, ldr_residual_deg) = {
        let good_px: Vec<usize> = any
            .iter()
            .copied()
            .filter(|&p| good[p])
            .step_by(any_step)
            .collect();
        let [mu0, nu0, l0] = gbr0;
        let rho = |p: usize| {
            Vector3::new(
                bbar[p].x + mu0 * bbar[p].z,
                bbar[p].y + nu0 * bbar[p].z,
                l0 * bbar[p].z,
            )
            .norm()
        };
        let top = (good_px.len() / LDR_SHARE).max(LDR_MIN_PIXELS);
        let mut sets: Vec<Vec<usize>> = Vec::with_capacity(f);
        for i in 0..f {
            let mut cand: Vec<(f64, usize)> = good_px
                .iter()
                .filter_map(|&p| {
                    let v = sample(p, i);
                    let pred = bt[p].dot(&pseudo_lights[i]);
                    (usable(p, i)
                        && pred > options.dark_fraction * bright[i]
                        && (v - pred).abs() <= OUTLIER_SCALES * sigma)
                        .then(|| (v / rho(p), p))
                })
                .collect();
            cand.sort_by(|a, b| b.0.total_cmp(&a.0));
            sets.push(cand.iter().take(top).map(|c| c.1).collect());
        }
        let obj = |mu: f64, nu: f64, lambda: f64| -> f64 {
            let m = Matrix3::new(1.0, 0.0, mu, 0.0, 1.0, nu, 0.0, 0.0, lambda)
                * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, scale3))
                * base.transpose()
                * flip;
            let Some(inv) = m.try_inverse() else {
                return f64::INFINITY;
            };
            let it = inv.transpose();
            let (mut sum, mut used) = (0.0, 0usize);
            for (i, set) in sets.iter().enumerate() {
                if set.is_empty() {
                    continue;
                }
                used += 1;
                let mut n = Vector3::zeros();
                for &p in set {
                    let b = bbar[p];
                    n += Vector3::new(b.x + mu * b.z, b.y + nu * b.z, lambda * b.z).normalize();
                }
                let s = it * pseudo_lights[i];
                sum += n.angle(&s);
            }
            if used == 0 {
                f64::INFINITY
            } else {
                sum / used as f64
            }
        };
        let (best, residual, _) = minimise(&obj);
        (best, residual.to_degrees())
    };
    let [mu, nu, lambda] = gbr;
    let to_true = |b: &Vector3<f64>| Vector3::new(b.x + mu * b.z, b.y + nu * b.z, lambda * b.z);
    // The convex/concave choice: normals on the outline point outwards.
    let mut outward = 0usize;
    let mut outline = 0usize;
    for y in 0..h {
        for x in 0..w {
            let pix = y * w + x;
            if !mask.data()[pix] {
                continue;
            }
            // Offsets (x right, y up) towards outside neighbours.
            let mut out = (0.0f64, 0.0f64);
            let outside = |xx: isize, yy: isize| {
                xx < 0
                    || yy < 0
                    || xx >= w as isize
                    || yy >= h as isize
                    || !mask.data()[yy as usize * w + xx as usize]
            };
            let (xi, yi) = (x as isize, y as isize);
            if outside(xi + 1, yi) {
                out.0 += 1.0;
            }
            if outside(xi - 1, yi) {
                out.0 -= 1.0;
            }
            if outside(xi, yi - 1) {
                out.1 += 1.0;
            }
            if outside(xi, yi + 1) {
                out.1 -= 1.0;
            }
            if out == (0.0, 0.0) {
                continue;
            }
            let n = to_true(&bbar[pix]);
            let d = n.x * out.0 + n.y * out.1;
            if d != 0.0 {
                outline += 1;
                if d > 0.0 {
                    outward += 1;
                }
            }
        }
    }
    let mirrored = 2 * outward < outline;
    let outline_outward = if outline == 0 {
        0.5
    } else if mirrored {
        (outline - outward) as f64 / outline as f64
    } else {
        outward as f64 / outline as f64
    };
    // Lights: b_trueᵀ s_true = b̃ᵀ s̃ with b_true = M b̃, so s_true = M⁻ᵀ s̃.
    let sign = if mirrored { -1.0 } else { 1.0 };
    let gbr_m = Matrix3::new(sign, 0.0, sign * mu, 0.0, sign, sign * nu, 0.0, 0.0, lambda)
        * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, scale3))
        * base.transpose()
        * flip;
    let inv_t = gbr_m
        .try_inverse()
        .ok_or_else(|| Error::param("images", "the recovered transform is singular"))?
        .transpose();
    let raw: Vec<Vector3<f64>> = pseudo_lights.iter().map(|s| inv_t * s).collect();
    let mean_norm = raw.iter().map(|s| s.norm()).sum::<f64>() / f as f64;
    let directions = raw
        .iter()
        .map(|s| {
            let d = s.normalize();
            [d.x, d.y, d.z]
        })
        .collect();
    let intensities = raw.iter().map(|s| s.norm() / mean_norm).collect();
    let assumptions = vec![
        "Lambertian: the pixels lit in every image span a three-dimensional space".to_string(),
        "the surface is integrable over the lit pixels".to_string(),
        "the albedo takes few distinct values (minimum-entropy GBR)".to_string(),
        format!(
            "the object is convex at its outline: {:.0}% of the outline's normals point outwards \
             with the sign chosen",
            100.0 * outline_outward
        ),
    ];
    let mut warnings = Vec::new();
    if outline_outward < OUTLINE_SETTLED {
        warnings.push(format!(
            "only {:.0}% of the outline's normals point outwards: the convex/concave choice is \
             not settled, and the lights may be mirrored about the view direction (x and y \
             negated)",
            100.0 * outline_outward
        ));
    }
    if entropy_drop.is_nan() || entropy_drop < WEAK_ENTROPY_DROP {
        warnings.push(format!(
            "the albedo entropy hardly varies over the bas-relief transforms (drop {entropy_drop:.3} \
             nats): the lights' elevation and tilt are weakly determined"
        ));
    }
    Ok(ObjectLights {
        directions,
        intensities,
        uncertainty_deg: Vec::new(),
        gbr: [sign * mu, sign * nu, lambda],
        gbr_entropy: [sign * gbr0[0], sign * gbr0[1], gbr0[2]],
        ldr_residual_deg,
        entropy,
        entropy_drop,
        lit_pixels,
        rank3_gap,
        outline_outward,
        outlier_fraction: 1.0 - inlier_samples as f64 / usable_samples.max(1) as f64,
        relative_deviation: sigma / mean_inlier,
        assumptions,
        warnings,
    })
}

/// A pixel takes part in the integrability constraint when at least this fraction of its samples
/// are inliers of the rank-3 fit (chosen on rendered scenes: 0.5 to 0.9 all work, 0.75 best).
const GOOD_FRACTION: f64 = 0.75;
/// Each image's local diffuse maxima are its brightest pixels relative to their albedo: one in
/// this many of the pixels searched, and at least [`LDR_MIN_PIXELS`].
const LDR_SHARE: usize = 1000;
/// The fewest local-diffuse-maximum pixels per image.
const LDR_MIN_PIXELS: usize = 5;
/// Most pixels in the albedo histogram (evenly subsampled beyond).
const ENTROPY_PIXELS: usize = 10_000;
/// A third singular value below this fraction of the first is rank 2 (lights in one plane):
/// well above the square-rooted Gram eigenvalues' and the samples' rounding (about 1e-7).
const RANK_TOLERANCE: f64 = 1e-4;
/// Rounds of the alternating robust refinement.
const ALS_ROUNDS: usize = 8;
/// Samples farther from the rank-3 fit than this many robust deviations are outliers.
const OUTLIER_SCALES: f64 = 3.0;

/// A pixel's pseudo-normal from its usable samples (`value(i)`), by least squares against
/// `lights`, then again without the samples off that fit by more than [`OUTLIER_SCALES`]·`sigma`
/// or predicted darker than the dark level. `None` with fewer than 4 samples left.
fn fit_pixel(
    lights: &[Vector3<f64>],
    f: usize,
    value: impl Fn(usize) -> Option<f64>,
    sigma: f64,
    dark_fraction: f64,
    bright: &[f64],
) -> Option<(Vector3<f64>, usize)> {
    let solve = |keep: &dyn Fn(usize, f64) -> bool| -> Option<(Vector3<f64>, usize)> {
        let (mut m, mut r, mut n) = (Matrix3::<f64>::zeros(), Vector3::<f64>::zeros(), 0);
        for (i, s) in lights.iter().enumerate().take(f) {
            if let Some(v) = value(i)
                && keep(i, v)
            {
                m += s * s.transpose();
                r += s * v;
                n += 1;
            }
        }
        if n < 4 {
            return None;
        }
        m.try_inverse().map(|inv| (inv * r, n))
    };
    let (b, n) = solve(&|_, _| true)?;
    if !sigma.is_finite() {
        return Some((b, n));
    }
    let keep = |i: usize, v: f64| {
        let pred = b.dot(&lights[i]);
        pred > dark_fraction * bright[i] && (v - pred).abs() <= OUTLIER_SCALES * sigma
    };
    solve(&keep)
}

/// The 6×6 normal matrix of the integrability constraint over 2×2 cells of blocks of
/// `scale`² pixels that are all `good`, with the number of cells; `None` under 16 cells.
/// (Blocks of 2² pixels cut the light error of noisy captures several times — a sphere under
/// 6 lights at 2% noise, 24° → 2.1° — but cost accuracy on clean ones; no rule to choose the
/// block size from the data has been found yet, and 1 is used.)
fn integrability_system(
    bt: &[Vector3<f64>],
    good: &[bool],
    w: usize,
    h: usize,
    scale: usize,
) -> Option<(Matrix6<f64>, usize)> {
    let (bw, bh) = (w / scale, h / scale);
    let blocks: Vec<Option<Vector3<f64>>> = (0..bw * bh)
        .map(|k| {
            let (bx, by) = (k % bw, k / bw);
            let mut sum = Vector3::zeros();
            for y in by * scale..(by + 1) * scale {
                for x in bx * scale..(bx + 1) * scale {
                    if !good[y * w + x] {
                        return None;
                    }
                    sum += bt[y * w + x];
                }
            }
            Some(sum / (scale * scale) as f64)
        })
        .collect();
    let mut normal = Matrix6::<f64>::zeros();
    let mut cells = 0usize;
    for y in 0..bh.saturating_sub(1) {
        for x in 0..bw.saturating_sub(1) {
            let (Some(tl), Some(tr), Some(bl), Some(br)) = (
                blocks[y * bw + x],
                blocks[y * bw + x + 1],
                blocks[(y + 1) * bw + x],
                blocks[(y + 1) * bw + x + 1],
            ) else {
                continue;
            };
            let mean = (tl + tr + bl + br) / 4.0;
            let dx = (tr + br - tl - bl) / 2.0;
            let dy = (tl + tr - bl - br) / 2.0;
            let t = |d: &Vector3<f64>, j: usize, k: usize| mean[j] * d[k] - mean[k] * d[j];
            let row = Vector6::new(
                t(&dy, 0, 1),
                t(&dy, 0, 2),
                t(&dy, 1, 2),
                -t(&dx, 0, 1),
                -t(&dx, 0, 2),
                -t(&dx, 1, 2),
            );
            normal += row * row.transpose();
            cells += 1;
        }
    }
    (cells >= 16).then_some((normal, cells))
}

/// Bin width of the log-albedo histogram (2% in albedo).
const LOG_BIN: f64 = 0.02;

/// Entropy (nats) of the histogram of ln |b| for b = (b̄₁ + μb̄₃, b̄₂ + νb̄₃, λb̄₃), with linear
/// (two-bin) weighting so that it varies smoothly with the parameters.
fn entropy(bbar: &[Vector3<f64>], mu: f64, nu: f64, lambda: f64, scratch: &mut Vec<f64>) -> f64 {
    scratch.clear();
    for b in bbar {
        let r = Vector3::new(b.x + mu * b.z, b.y + nu * b.z, lambda * b.z).norm();
        if r > 0.0 {
            scratch.push(r.ln() / LOG_BIN);
        }
    }
    if scratch.is_empty() {
        return f64::INFINITY;
    }
    let lo = scratch
        .iter()
        .cloned()
        .fold(f64::INFINITY, f64::min)
        .floor();
    let hi = scratch
        .iter()
        .cloned()
        .fold(f64::NEG_INFINITY, f64::max)
        .ceil();
    let bins = ((hi - lo) as usize + 2).min(1 << 20);
    let mut hist = vec![0.0f64; bins];
    for &t in scratch.iter() {
        let u = (t - lo).min((bins - 2) as f64);
        let i = u.floor() as usize;
        let frac = u - i as f64;
        hist[i] += 1.0 - frac;
        hist[i + 1] += frac;
    }
    let n = scratch.len() as f64;
    -hist
        .iter()
        .filter(|&&c| c > 0.0)
        .map(|&c| {
            let p = c / n;
            p * p.ln()
        })
        .sum::<f64>()
}

/// The (μ, ν, λ) of least albedo entropy ([`minimise`]).
fn minimise_entropy(bbar: &[Vector3<f64>]) -> ([f64; 3], f64, f64) {
    minimise(&|mu, nu, l| entropy(bbar, mu, nu, l, &mut Vec::with_capacity(bbar.len())))
}

/// The (μ, ν, λ) where `objective` is least: a 13³ grid over μ, ν ∈ [−3, 3] and λ ∈ [1/8, 8]
/// (logarithmic), then three grids each 2.5 steps of the last wide around its best point.
/// Returns it, its value and the first grid's median minus that value.
fn minimise(objective: &(dyn Fn(f64, f64, f64) -> f64 + Sync)) -> ([f64; 3], f64, f64) {
    let mut best = ([0.0, 0.0, 1.0], f64::INFINITY);
    let mut first_grid = Vec::new();
    const N: usize = 13;
    let (mut half_mu, mut half_ln) = (3.0f64, 8.0f64.ln());
    let mut centre = [0.0, 0.0, 0.0f64];
    for round in 0..4 {
        let t = |a: usize| -1.0 + 2.0 * a as f64 / (N - 1) as f64;
        let values: Vec<([f64; 3], f64)> = (0..N * N * N)
            .into_par_iter()
            .map(|g| {
                let (i, j, k) = (g / (N * N), g / N % N, g % N);
                let mu = centre[0] + half_mu * t(i);
                let nu = centre[1] + half_mu * t(j);
                let lambda = (centre[2] + half_ln * t(k)).exp();
                ([mu, nu, lambda], objective(mu, nu, lambda))
            })
            .collect();
        for (p, e) in values {
            if round == 0 {
                first_grid.push(e);
            }
            if e < best.1 {
                best = (p, e);
            }
        }
        centre = [best.0[0], best.0[1], best.0[2].ln()];
        half_mu *= 2.5 / (N - 1) as f64;
        half_ln *= 2.5 / (N - 1) as f64;
    }
    let median = crate::stats::median(first_grid.into_iter().filter(|e| e.is_finite()).collect());
    (best.0, best.1, median - best.1)
}

/// [`lights_from_object`] on an image stack (colour is mixed to grey; saturated samples count
/// as unusable, like shadowed ones).
///
/// # Errors
/// As [`lights_from_object`]; [`Error::Mask`] when the mask's size differs from the images'.
pub fn lights_from_stack(
    stack: &crate::capture::stack::ImageStack,
    mask: &Mask,
    options: &FromObjectOptions,
) -> Result<ObjectLights> {
    let (w, h) = (stack.width(), stack.height());
    if (mask.width(), mask.height()) != (w, h) {
        return Err(Error::Mask {
            path: std::path::PathBuf::from("the object's mask"),
            reason: format!(
                "is {}×{} but the images are {w}×{h}",
                mask.width(),
                mask.height()
            ),
        });
    }
    let grey = stack.grey_mix();
    let images: Vec<ScalarMap> = (0..grey.count())
        .map(|i| {
            crate::grid::Grid::from_fn(w, h, |x, y| {
                let pix = y * w + x;
                if grey.is_saturated(i, pix) {
                    f32::NAN
                } else {
                    grey.value(i, 0, pix)
                }
            })
        })
        .collect();
    lights_from_object(&images, mask, options)
}
