//! Relative light intensities, per colour channel, from a matte reference seen under every
//! light: a Lambertian sphere, or a flat grey card.
//!
//! A Lambertian reference of albedo ρ_c under light k of irradiance E_kc gives
//! I = E_kc ρ_c max(0, n·l_k). Only the products E_kc ρ_c are
//! observable, so intensities are **relative**: each channel is divided by its mean over the
//! lights. The reference's colour, and the lights' mean colour, go into the albedo of the
//! objects measured afterwards; the light-to-light ratios, which are what photometric stereo
//! needs, are exact.

use super::sphere::Circle;
use crate::capture::stack::ImageStack;
use crate::error::{Error, Result};
use crate::grid::Mask;
use nalgebra::{Matrix3, Vector3};
use serde::Serialize;

/// Options of [`intensities_from_sphere`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MatteOptions {
    /// Pixels used lie inside this fraction of the sphere's radius (the rim is foreshortened
    /// and blends with the background).
    pub max_radius_fraction: f64,
    /// Pixels used have n·l at least this (clear of the attached shadow's edge, so the clamp
    /// max(0, ·) and a slightly wrong light direction do not matter).
    pub min_cos: f64,
    /// Samples at or above this value are saturated and left out.
    pub saturation: f32,
}

impl Default for MatteOptions {
    fn default() -> Self {
        MatteOptions {
            max_radius_fraction: 0.95,
            min_cos: 0.2,
            saturation: 0.98,
        }
    }
}

/// What the matte sphere says about one light.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MatteLight {
    /// Relative intensity per channel (each channel's mean over the lights is 1; a grey stack
    /// repeats its one value).
    pub intensity: [f64; 3],
    /// The light direction the sphere's shading gives, b/|b| for the fitted I = b·n of the
    /// grey mix: a check on the mirror-sphere direction.
    #[serde(serialize_with = "super::serialize_vector")]
    pub direction: Vector3<f64>,
    /// Angle between that direction and the one given, in degrees.
    pub angle_to_given_deg: f64,
    /// Pixels fitted.
    pub pixels: usize,
    /// Root-mean-square residual of the grey fit relative to its mean brightness.
    pub relative_rms: f64,
}

/// Relative intensities from a matte (Lambertian) sphere of outline `sphere` in `stack`
/// (raw images: *not* divided by any intensity), lit by `directions` (one per image, e.g. from
/// the mirror sphere). For each image and channel, I = b·n is fitted by least squares over
/// the sphere's lit, unsaturated pixels (see [`MatteOptions`]) with n the sphere's normal; the
/// intensity is |b|, to first order independent of an error in the given direction.
///
/// There is no ambient term: fitting an offset a in I = b·n + a was tried, and on a real
/// capture (the classic 12-light grey sphere) it traded against b_z for lights near the view,
/// scattering the intensities by ±15% where the photometric-stereo fits say they are within
/// ±3%. Photograph the references in a dark room.
///
/// # Errors
/// [`Error::LightsMismatch`] when `directions` and images differ in number;
/// [`Error::BadImage`] naming the image when fewer than 20 pixels can be fitted, or the fit is
/// degenerate.
pub fn intensities_from_sphere(
    stack: &ImageStack,
    sphere: &Circle,
    directions: &[Vector3<f64>],
    options: &MatteOptions,
) -> Result<Vec<MatteLight>> {
    check_count(stack, directions)?;
    let (w, h) = (stack.width(), stack.height());
    let win = stack.window();
    let limit = sphere.radius * options.max_radius_fraction;
    let mut pixels = Vec::new();
    for y in win.y0..win.y1 {
        for x in win.x0..win.x1 {
            if (x as f64 - sphere.cx).hypot(y as f64 - sphere.cy) < limit
                && let Some(n) = sphere.normal_at(x as f64, y as f64)
            {
                pixels.push((y * w + x, n));
            }
        }
    }
    debug_assert!(pixels.iter().all(|(p, _)| *p < w * h));
    let channels = stack.channels();
    let mixed = stack.grey_mix();
    let mut out = Vec::with_capacity(directions.len());
    for (k, l) in directions.iter().enumerate() {
        let l = l.normalize();
        let lit: Vec<&(usize, Vector3<f64>)> = pixels
            .iter()
            .filter(|(_, n)| n.dot(&l) >= options.min_cos)
            .collect();
        let fit_channel = |read: &dyn Fn(usize) -> f32| -> Result<(Vector3<f64>, usize, f64)> {
            let mut ata = Matrix3::<f64>::zeros();
            let mut atb = Vector3::<f64>::zeros();
            let mut used = Vec::with_capacity(lit.len());
            for (p, n) in &lit {
                let v = read(*p);
                if !v.is_finite() || v >= options.saturation {
                    continue;
                }
                let row = *n;
                ata += row * row.transpose();
                atb += row * f64::from(v);
                used.push((row, f64::from(v)));
            }
            if used.len() < MIN_PIXELS {
                return Err(bad(
                    stack,
                    k,
                    format!(
                        "{} usable pixels on the matte sphere (at least {MIN_PIXELS}): is it lit by this light, or saturated?",
                        used.len()
                    ),
                ));
            }
            let sol = ata
                .lu()
                .solve(&atb)
                .filter(|s| s.iter().all(|v| v.is_finite()))
                .ok_or_else(|| bad(stack, k, "the matte sphere's shading is degenerate".into()))?;
            let mean = used.iter().map(|(_, v)| v).sum::<f64>() / used.len() as f64;
            let ss: f64 = used.iter().map(|(r, v)| (r.dot(&sol) - v).powi(2)).sum();
            let rel = (ss / used.len() as f64).sqrt() / mean.abs().max(f64::MIN_POSITIVE);
            Ok((sol, used.len(), rel))
        };
        let mut intensity = [0.0; 3];
        for (c, slot) in intensity.iter_mut().enumerate().take(channels) {
            let plane = stack.plane(k, c);
            let (sol, _, _) = fit_channel(&|p| value(stack, k, plane, p))?;
            *slot = sol.norm();
        }
        if channels == 1 {
            intensity = [intensity[0]; 3];
        }
        let (grey, used, rel) = fit_channel(&|p| value(&mixed, k, mixed.plane(k, 0), p))?;
        let b = grey;
        if b.norm() <= 0.0 {
            return Err(bad(stack, k, "the matte sphere is not lit".into()));
        }
        let direction = b.normalize();
        out.push(MatteLight {
            intensity,
            direction,
            angle_to_given_deg: direction.dot(&l).clamp(-1.0, 1.0).acos().to_degrees(),
            pixels: used,
            relative_rms: rel,
        });
    }
    normalise(&mut out.iter_mut().map(|m| &mut m.intensity).collect::<Vec<_>>());
    Ok(out)
}

/// Relative intensities from a flat grey card (the pixels of `card`) whose normal is
/// `card_normal`: E_kc ∝ mean_card(I_kc) / (n·l_k), each channel divided by its mean over the
/// lights. Ambient light is not separated here (a card has one normal), so the card should be
/// lit well by every light (n·l ≥ 0.2 is required).
///
/// # Errors
/// [`Error::LightsMismatch`] when `directions` and images differ in number;
/// [`Error::InvalidParameter`] (`card_normal`) for a zero normal; [`Error::BadImage`] when a
/// light grazes the card (n·l < 0.2) or the card holds no usable pixel in an image.
pub fn intensities_from_card(
    stack: &ImageStack,
    card: &Mask,
    card_normal: Vector3<f64>,
    directions: &[Vector3<f64>],
    saturation: f32,
) -> Result<Vec<[f64; 3]>> {
    check_count(stack, directions)?;
    let norm = card_normal.norm();
    if !norm.is_finite() || norm <= 0.0 {
        return Err(Error::param(
            "card_normal",
            "must be a finite, non-zero vector",
        ));
    }
    let n = card_normal.normalize();
    let pixels: Vec<usize> = (0..card.len()).filter(|p| card.data()[*p]).collect();
    let mut out = Vec::with_capacity(directions.len());
    for (k, l) in directions.iter().enumerate() {
        let cos = n.dot(&l.normalize());
        if cos < MIN_CARD_COS {
            return Err(bad(
                stack,
                k,
                format!(
                    "the light grazes the card (n·l = {cos:.3} < {MIN_CARD_COS}); its intensity cannot be read from it"
                ),
            ));
        }
        let mut e = [0.0; 3];
        for (c, slot) in e.iter_mut().enumerate().take(stack.channels()) {
            let plane = stack.plane(k, c);
            let vals: Vec<f64> = pixels
                .iter()
                .map(|p| value(stack, k, plane, *p))
                .filter(|v| v.is_finite() && *v < saturation)
                .map(f64::from)
                .collect();
            if vals.is_empty() {
                return Err(bad(stack, k, "no unsaturated pixel on the card".into()));
            }
            *slot = vals.iter().sum::<f64>() / vals.len() as f64 / cos;
        }
        if stack.channels() == 1 {
            e = [e[0]; 3];
        }
        out.push(e);
    }
    normalise(&mut out.iter_mut().collect::<Vec<_>>());
    Ok(out)
}

/// Fewest pixels a matte-sphere fit accepts.
const MIN_PIXELS: usize = 20;
/// Least n·l between a card and a light.
const MIN_CARD_COS: f64 = 0.2;

/// Divides each channel by its mean over the lights.
fn normalise(values: &mut [&mut [f64; 3]]) {
    for c in 0..3 {
        let mean = values.iter().map(|v| v[c]).sum::<f64>() / values.len().max(1) as f64;
        if mean > 0.0 {
            for v in values.iter_mut() {
                v[c] /= mean;
            }
        }
    }
}

fn check_count(stack: &ImageStack, directions: &[Vector3<f64>]) -> Result<()> {
    if directions.len() != stack.count() {
        return Err(Error::LightsMismatch {
            reason: format!(
                "{} light directions for {} reference images",
                directions.len(),
                stack.count()
            ),
        });
    }
    Ok(())
}

/// Pixel `pixel` of image `image` (its `plane`), NaN where the stack flags it saturated.
fn value(stack: &ImageStack, image: usize, plane: &[f32], pixel: usize) -> f32 {
    if stack.is_saturated(image, pixel) {
        return f32::NAN;
    }
    stack.local(pixel).map_or(f32::NAN, |i| plane[i])
}

fn bad(stack: &ImageStack, index: usize, reason: String) -> Error {
    Error::BadImage {
        path: stack.info()[index].path.clone(),
        index,
        reason,
    }
}
