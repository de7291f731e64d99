//! A light's direction from its highlight on a mirror sphere.
//!
//! Under the orthographic camera (view v = (0, 0, 1)) a mirror reflects a distant light l into
//! the camera where the sphere's normal is the half vector, so l = 2(n·v)n − v. A real lamp has
//! a size, so its highlight is a blob: every blob pixel reflects one direction of the lamp's
//! disc. This module averages those reflected directions, weighted by brightness above the
//! blob's threshold, instead of reflecting about the blob's pixel centroid. That is unbiased:
//! under orthographic projection an image area dA maps to the solid angle 4 dA / R² of
//! reflected directions whatever the normal (the 1/n_z of foreshortening cancels the 4 n_z of
//! reflection), so equal pixels are equal solid angles, and the mean of the directions of a
//! symmetric lamp is its centre — also for highlights near the rim, where the pixel centroid is
//! pulled towards the centre of the sphere.

use super::perspective::SphereCone;
use super::sphere::CircleFit;
use crate::stats::median_by;
use crate::synth::reflectance::reflect;
use nalgebra::{Matrix3, Vector3};
use serde::Serialize;

/// Options of [`find_highlight`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct HighlightOptions {
    /// Blob threshold between the sphere's background level (0) and the peak (1).
    pub level: f64,
    /// Pixels within this fraction of the radius from the rim are ignored (the normal there is
    /// ill-conditioned and the outline blends with the background).
    pub rim_margin: f64,
    /// A highlight must exceed the background by this many noise standard deviations.
    pub min_snr: f64,
    /// Below this share of the highlight energy the chosen blob is flagged ambiguous.
    pub ambiguous_share: f64,
    /// A light whose uncertainty (rms, degrees) exceeds this is not accepted.
    pub max_uncertainty_deg: f64,
    /// A highlight longer than this times its width (in reflected directions) is warned
    /// about: two reflections merged into one blob, or a lamp that is not round.
    pub max_elongation: f64,
}

impl Default for HighlightOptions {
    fn default() -> Self {
        HighlightOptions {
            level: 0.25,
            rim_margin: 0.02,
            min_snr: 10.0,
            ambiguous_share: 0.8,
            max_uncertainty_deg: 0.5,
            max_elongation: 2.5,
        }
    }
}

/// The highlight found in one image and the light direction it gives.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Highlight {
    /// Unit light direction (camera frame, towards the light).
    #[serde(serialize_with = "super::serialize_vector")]
    pub direction: Vector3<f64>,
    /// Weighted pixel centroid of the blob (column, row).
    pub centroid: [f64; 2],
    /// Pixels in the blob.
    pub pixels: usize,
    /// Peak value over the sphere's background level, in noise standard deviations.
    pub snr: f64,
    /// The blob's share of the energy of every blob above the threshold on the sphere (1: one
    /// clean highlight; lower: secondary reflections compete).
    pub share: f64,
    /// Other blobs above the threshold (secondary reflections), rejected.
    pub secondary: usize,
    /// Axis ratio of the blob in reflected-direction space (1: round, as a round lamp makes
    /// it; more: two reflections merged, or a lamp that is not round).
    pub elongation: f64,
    /// Root-mean-square angular error of the direction expected from what was measured, in
    /// degrees: the blob's sampling by the pixel grid (its centroid moves by √(B/12)/N px for
    /// B border pixels of N, a pixel turning the light by 2/(R n_z) rad), the image noise in
    /// its pixels, and the circle's uncertainty propagated, in quadrature. The true error is
    /// within twice this for about 95% of lights (checked on rendered captures).
    pub uncertainty_deg: f64,
    /// The probability that the direction is within 1° of the light's, under the error model
    /// of [`Highlight::uncertainty_deg`] (1 − exp(−(1°/u)²)), times the blob's energy share
    /// when the highlight is in doubt.
    pub confidence: f64,
    /// Whether the light can be used: one clear highlight away from the rim, with an
    /// uncertainty within [`HighlightOptions::max_uncertainty_deg`]. When false, the
    /// warnings say why.
    pub accepted: bool,
    /// What may be wrong with it.
    pub warnings: Vec<String>,
}

/// Why no highlight was found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Missing {
    /// Peak over background in noise standard deviations (below the option's minimum).
    pub snr: f64,
    /// What to do.
    pub reason: String,
}

/// Finds the light's highlight on the sphere in one grey image (`plane`, `width` columns,
/// row-major) and the light direction l = 2(n·v)n − v it gives (see the module doc): with
/// `cone` (a pinhole camera's view of the sphere, [`SphereCone`]) each pixel reflects its own
/// view ray ([`SphereCone::reflected`]), else the orthographic v = (0, 0, 1). The sphere's
/// pixels are those inside `sphere`'s circle either way.
///
/// Steps: the sphere's pixels (inside the rim margin) give a background level (median) and,
/// unless `noise` is given, a noise σ (1.4826 × MAD); pixels above background + level × (peak − background) form 8-connected
/// blobs; the blob with the largest energy Σ(I − threshold) is the highlight, the others are
/// secondary reflections.
///
/// `noise` is the image's noise standard deviation when known (else the robust spread of the
/// sphere's pixels stands in for it). `clipped` flags the pixels that are saturated (empty:
/// none known). Saturated blobs are
/// as bright as each other whatever the lamp's brightness, so when the chosen blob and another
/// both hold saturated pixels the highlight is ambiguous, whatever its energy share.
///
/// Returns `Err(Missing)` when the peak is not [`HighlightOptions::min_snr`] σ above the
/// background (no highlight, e.g. a light behind the sphere).
pub fn find_highlight(
    plane: &[f32],
    noise: Option<f64>,
    clipped: &[bool],
    width: usize,
    sphere: &CircleFit,
    cone: Option<&SphereCone>,
    options: &HighlightOptions,
) -> Result<Highlight, Missing> {
    let is_clipped = |i: usize| clipped.get(i).copied().unwrap_or(false);
    let c = sphere.circle;
    // Under a pinhole the ball's image is an ellipse a little longer than its best circle
    // (R(1/cos θ − 1) at θ off the axis): its pixels are those whose rays are inside the cone
    // by the rim margin, sought in a box that holds the ellipse.
    let excess = super::sphere::ellipse_excess(&c, cone.map(|k| &k.camera));
    let reflected = |x: f64, y: f64| match cone {
        Some(k) => k.reflected(x, y),
        None => c.normal_at(x, y).map(|n| reflect(&Vector3::z(), &n)),
    };
    let inner = c.radius * (1.0 - options.rim_margin);
    let height = plane.len() / width.max(1);
    if width == 0 || height == 0 || inner.is_nan() || inner <= 0.0 {
        return Err(Missing {
            snr: 0.0,
            reason: "the sphere lies outside the image".into(),
        });
    }
    let reach = inner + excess;
    let x0 = ((c.cx - reach).floor().max(0.0)) as usize;
    let x1 = ((c.cx + reach).ceil().max(0.0) as usize).min(width.saturating_sub(1));
    let y0 = ((c.cy - reach).floor().max(0.0)) as usize;
    let y1 = ((c.cy + reach).ceil().max(0.0) as usize).min(height.saturating_sub(1));
    let inside = |x: usize, y: usize| match cone {
        Some(k) => k.angular_distance(x as f64, y as f64) < -options.rim_margin * k.half_angle,
        None => (x as f64 - c.cx).hypot(y as f64 - c.cy) < inner,
    };
    let mut values = Vec::new();
    for y in y0..=y1 {
        for x in x0..=x1 {
            let v = plane[y * width + x];
            if inside(x, y) && v.is_finite() {
                values.push(f64::from(v));
            }
        }
    }
    if values.is_empty() {
        return Err(Missing {
            snr: 0.0,
            reason: "the sphere lies outside the image".into(),
        });
    }
    let peak = values.iter().copied().fold(f64::MIN, f64::max);
    let background = median_by(&mut values.clone(), f64::total_cmp).unwrap_or(0.0);
    let sigma = match noise {
        Some(s) if s.is_finite() => s,
        _ => {
            let mut dev: Vec<f64> = values.iter().map(|v| (v - background).abs()).collect();
            1.4826 * median_by(&mut dev, f64::total_cmp).unwrap_or(0.0)
        }
    };
    // Floor σ so that noise-free images do not divide by zero.
    let sigma = sigma.max(1e-6 * peak.abs()).max(f64::MIN_POSITIVE);
    let snr = (peak - background) / sigma;
    if snr.is_nan() || snr < options.min_snr {
        return Err(Missing {
            snr,
            reason: format!(
                "no highlight on the sphere: its peak is {snr:.1} noise σ above the background (at least {} needed); is the light behind the sphere, or the image dark?",
                options.min_snr
            ),
        });
    }
    let threshold = background + options.level * (peak - background);
    // 8-connected blobs above the threshold.
    let bw = x1 - x0 + 1;
    let bh = y1 - y0 + 1;
    let mut label = vec![u32::MAX; bw * bh];
    let mut blobs: Vec<Blob> = Vec::new();
    let mut stack = Vec::new();
    let above = |x: usize, y: usize| {
        let v = plane[y * width + x];
        inside(x, y) && v.is_finite() && f64::from(v) >= threshold
    };
    for y in y0..=y1 {
        for x in x0..=x1 {
            let li = (y - y0) * bw + (x - x0);
            if label[li] != u32::MAX || !above(x, y) {
                continue;
            }
            let id = blobs.len() as u32;
            let mut blob = Blob::default();
            label[li] = id;
            stack.push((x, y));
            while let Some((px, py)) = stack.pop() {
                let wgt = f64::from(plane[py * width + px]) - threshold;
                // Equal-area pixels weigh equally in reflected-direction space under the
                // orthographic camera (module doc); under a pinhole each pixel weighs as the
                // solid angle it reflects, relative to the orthographic 4/R².
                let (fx, fy) = (px as f64, py as f64);
                let solid = cone.map_or(Some(1.0), |k| {
                    reflected_solid_angle(k, fx, fy).map(|a| a * c.radius * c.radius / 4.0)
                });
                if let (Some(r), Some(a)) = (reflected(fx, fy), solid) {
                    blob.add(fx, fy, r, (wgt * a).max(f64::MIN_POSITIVE));
                }
                blob.clipped += usize::from(is_clipped(py * width + px));
                for dy in -1isize..=1 {
                    for dx in -1isize..=1 {
                        let (qx, qy) = (px as isize + dx, py as isize + dy);
                        if qx < x0 as isize
                            || qy < y0 as isize
                            || qx > x1 as isize
                            || qy > y1 as isize
                        {
                            continue;
                        }
                        let (qx, qy) = (qx as usize, qy as usize);
                        let qi = (qy - y0) * bw + (qx - x0);
                        if label[qi] == u32::MAX && above(qx, qy) {
                            label[qi] = id;
                            stack.push((qx, qy));
                        }
                    }
                }
            }
            blobs.push(blob);
        }
    }
    let total: f64 = blobs.iter().map(|b| b.energy).sum();
    let Some(best) = blobs
        .iter()
        .filter(|b| b.pixels > 0)
        .max_by(|a, b| a.energy.total_cmp(&b.energy))
    else {
        return Err(Missing {
            snr,
            reason: "no highlight blob inside the sphere".into(),
        });
    };
    let direction = best.sum_r.normalize();
    let share = best.energy / total;
    let centroid = [best.sum_x / best.energy, best.sum_y / best.energy];
    // Sampling: each of the blob's B border pixels is in or out by up to a pixel, a uniform
    // error of variance 1/12, so the centroid moves by √(B/12)/N px; a pixel turns the light by
    // up to 2/(R n_z) radians (reflection doubles the normal's turn, foreshortening divides by
    // n_z).
    let id = blobs
        .iter()
        .position(|b| std::ptr::eq(b, best))
        .unwrap_or_default() as u32;
    let border = (y0..=y1)
        .flat_map(|y| (x0..=x1).map(move |x| (x, y)))
        .filter(|&(x, y)| {
            let at = |x: usize, y: usize| label[(y - y0) * bw + (x - x0)] == id;
            at(x, y)
                && (x == x0
                    || x == x1
                    || y == y0
                    || y == y1
                    || !at(x - 1, y)
                    || !at(x + 1, y)
                    || !at(x, y - 1)
                    || !at(x, y + 1))
        })
        .count();
    let nz = c
        .normal_at(centroid[0], centroid[1])
        .map_or(MIN_NZ, |n| n.z.max(MIN_NZ));
    // Pixel sampling, as a root-mean-square angle (each axis alike).
    let sampling_px = (border as f64 / 12.0).sqrt() / best.pixels as f64;
    let sampling = std::f64::consts::SQRT_2 * sampling_px * 2.0 / (c.radius * nz);
    // Noise in the blob's pixels.
    let noise = best.noise_rms(&direction, sigma);
    // The circle's uncertainty, propagated by re-reflecting at the perturbed circle.
    let geom = match cone {
        Some(k) => cone_sensitivity(k, centroid),
        None => circle_sensitivity(sphere, centroid),
    };
    let uncertainty_deg = sampling.hypot(noise).to_degrees().hypot(geom);
    let elongation = best.elongation(&direction);
    let mut warnings = Vec::new();
    if share < options.ambiguous_share {
        warnings.push(format!(
            "ambiguous highlight: the chosen blob holds {:.0}% of the highlight energy on the sphere and {} other blob(s) the rest (secondary reflections?)",
            share * 100.0,
            blobs.len() - 1
        ));
    }
    let rim = match cone {
        Some(k) => (k.angular_distance(centroid[0], centroid[1]) / k.half_angle).abs(),
        None => c.distance(centroid[0], centroid[1]).abs() / c.radius,
    };
    if rim < 3.0 * options.rim_margin {
        warnings.push(format!(
            "the highlight is at the rim ({:.1}% of the radius from it): the light is nearly behind the sphere and its direction is poorly determined",
            rim * 100.0
        ));
    }
    if uncertainty_deg.is_nan() || uncertainty_deg > options.max_uncertainty_deg {
        warnings.push(format!(
            "the direction is uncertain: ±{uncertainty_deg:.2}° (rms), more than the {:.2}° accepted",
            options.max_uncertainty_deg
        ));
    }
    let clipped_rivals = blobs
        .iter()
        .filter(|b| !std::ptr::eq(*b, best) && b.clipped > 0)
        .count();
    if best.clipped > 0 && clipped_rivals > 0 {
        warnings.push(format!(
            "ambiguous highlight: it and {clipped_rivals} other blob(s) on the sphere are saturated, so their brightness cannot tell the lamp from a reflection of it"
        ));
    }
    let accepted = warnings.is_empty();
    // Lamps are often not round (a panel, a reflector), so shape alone does not reject.
    if best.pixels >= MIN_SHAPE_PIXELS && elongation > options.max_elongation {
        warnings.push(format!(
            "the highlight is {elongation:.1} times longer than wide: two reflections merged, or a lamp that is not round"
        ));
    }
    if best.pixels < 3 {
        warnings.push(format!(
            "the highlight covers only {} pixel(s): its position is not sub-pixel",
            best.pixels
        ));
    }
    Ok(Highlight {
        direction,
        centroid,
        pixels: best.pixels,
        snr,
        share,
        secondary: blobs.len() - 1,
        uncertainty_deg,
        elongation,
        confidence: {
            let p = if uncertainty_deg.is_finite() {
                1.0 - (-(1.0 / uncertainty_deg.max(1e-9)).powi(2)).exp()
            } else {
                0.0
            };
            if accepted { p } else { p * share }
        },
        accepted,
        warnings,
    })
}

/// Blobs of fewer pixels are too coarse for their shape to be judged.
const MIN_SHAPE_PIXELS: usize = 12;

/// Floor of n_z in the sensitivity of a highlight near the rim.
const MIN_NZ: f64 = 0.1;

/// Root-mean-square angle (degrees) by which the light moves when each circle parameter moves
/// by its standard error, in quadrature.
fn circle_sensitivity(sphere: &CircleFit, centroid: [f64; 2]) -> f64 {
    let Some(n0) = sphere.circle.normal_at(centroid[0], centroid[1]) else {
        return 0.0;
    };
    let l0 = reflect(&Vector3::z(), &n0);
    let mut sum = 0.0;
    for k in 0..3 {
        let mut c = sphere.circle;
        let d = sphere.std_err[k];
        if !d.is_finite() {
            return f64::INFINITY;
        }
        if d == 0.0 {
            continue;
        }
        match k {
            0 => c.cx += d,
            1 => c.cy += d,
            _ => c.radius += d,
        }
        if let Some(n) = c.normal_at(centroid[0], centroid[1]) {
            let l = reflect(&Vector3::z(), &n);
            sum += l.dot(&l0).clamp(-1.0, 1.0).acos().powi(2);
        }
    }
    sum.sqrt().to_degrees()
}

/// The solid angle (steradians per square pixel) of the directions that the sphere reflects
/// into the camera around pixel (u, v) under a pinhole camera: |∂r/∂u × ∂r/∂v| by central
/// differences of a quarter pixel. `None` off the sphere.
fn reflected_solid_angle(cone: &SphereCone, u: f64, v: f64) -> Option<f64> {
    const H: f64 = 0.25;
    let du = cone.reflected(u + H, v)? - cone.reflected(u - H, v)?;
    let dv = cone.reflected(u, v + H)? - cone.reflected(u, v - H)?;
    Some(du.cross(&dv).norm() / (4.0 * H * H))
}

/// As [`circle_sensitivity`], for the cone of a perspective view: each of its parameters moved
/// by its standard error.
fn cone_sensitivity(cone: &SphereCone, centroid: [f64; 2]) -> f64 {
    let Some(l0) = cone.reflected(centroid[0], centroid[1]) else {
        return 0.0;
    };
    let mut sum = 0.0;
    for (k, d) in cone.std_err.iter().enumerate() {
        if !d.is_finite() {
            return f64::INFINITY;
        }
        if *d == 0.0 {
            continue;
        }
        if let Some(l) = cone.perturbed(k, *d).reflected(centroid[0], centroid[1]) {
            sum += l.dot(&l0).clamp(-1.0, 1.0).acos().powi(2);
        }
    }
    sum.sqrt().to_degrees()
}

/// Running sums of one blob.
#[derive(Debug, Default)]
struct Blob {
    pixels: usize,
    energy: f64,
    sum_x: f64,
    sum_y: f64,
    sum_r: Vector3<f64>,
    /// Σ w r rᵀ: the spread of the reflected directions.
    sum_wrr: Matrix3<f64>,
    /// Σ r rᵀ, unweighted: how noise in the weights moves the mean.
    sum_rr: Matrix3<f64>,
    /// Saturated pixels.
    clipped: usize,
}

impl Blob {
    fn add(&mut self, x: f64, y: f64, r: Vector3<f64>, w: f64) {
        self.pixels += 1;
        self.energy += w;
        self.sum_x += w * x;
        self.sum_y += w * y;
        self.sum_r += w * r;
        let rr = r * r.transpose();
        self.sum_wrr += w * rr;
        self.sum_rr += rr;
    }

    /// Axis ratio (≥ 1) of the blob in reflected-direction space: the square root of the ratio
    /// of the eigenvalues of the weighted covariance of the directions on the plane normal to
    /// their mean `m`. A round lamp gives about 1.
    fn elongation(&self, m: &Vector3<f64>) -> f64 {
        let c = self.sum_wrr / self.energy;
        let e1 = m
            .cross(&if m.x.abs() < 0.9 {
                Vector3::x()
            } else {
                Vector3::y()
            })
            .normalize();
        let e2 = m.cross(&e1);
        let (a, b, d) = (e1.dot(&(c * e1)), e1.dot(&(c * e2)), e2.dot(&(c * e2)));
        let mean = 0.5 * (a + d);
        let root = (0.25 * (a - d) * (a - d) + b * b).sqrt();
        let (hi, lo) = (mean + root, (mean - root).max(f64::MIN_POSITIVE));
        (hi / lo).sqrt()
    }

    /// Root-mean-square angle (radians) by which noise of standard deviation `sigma` in every
    /// pixel's weight moves the mean direction `m`: σ √(Σ|r − (m·r)m|²) / |Σ w r|.
    fn noise_rms(&self, m: &Vector3<f64>, sigma: f64) -> f64 {
        let across = self.pixels as f64 - m.dot(&(self.sum_rr * m));
        sigma * across.max(0.0).sqrt() / self.sum_r.norm().max(f64::MIN_POSITIVE)
    }
}
