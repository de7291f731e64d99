//! Light direction and albedo from a single image, after Zheng & Chellappa ("Estimation of
//! illuminant direction, albedo, and shape from shading", IEEE PAMI 13(7), 1991).
//!
//! Assumes a Lambertian surface whose normals are distributed over the image like those of a
//! sphere (the statistical assumption of Pentland 1982 and Zheng–Chellappa):
//! - **Tilt** τ (the light's azimuth in the image plane) is the direction of the mean image
//!   gradient: for a sphere, the mean of ∇E is ρ (s_x, s_y)/r, the shading term of n_z averaging
//!   to zero.
//! - **Slant** σ and **albedo** ρ come from the first two moments of the brightness. For normals
//!   uniform over the projected hemisphere, m₁ = E\[E\] = ρ f₁(σ) and m₂ = E\[E²\] = ρ² f₂(σ), with
//!   f₁, f₂ the moments of max(0, n·s) (attached shadows included; without them f₁ = ⅔ cos σ and
//!   f₂ = (1 + cos² σ)/4). m₁²/m₂ = f₁²/f₂ depends on σ alone and decreases with it: it is
//!   inverted on a table, then ρ = m₁/f₁(σ).
//!
//! Surfaces whose normals are not sphere-like (a mostly flat object, a single slope) bias the
//! estimate: it is a starting point when nothing is known, and [`LightEstimate`] says so.

use crate::error::{Error, Result};
use crate::grid::{Mask, ScalarMap};
use nalgebra::Vector3;
use serde::Serialize;

/// Slant table step, degrees.
const TABLE_STEP_DEG: f64 = 0.5;
/// Radial and angular samples of the hemisphere integrals.
const RADIAL: usize = 400;
const ANGULAR: usize = 720;

/// An estimated light and albedo.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LightEstimate {
    /// Unit light direction.
    pub direction: [f64; 3],
    /// Angle from the viewing direction, degrees.
    pub slant_deg: f64,
    /// Azimuth in the image plane (x right, y up), degrees.
    pub tilt_deg: f64,
    /// Albedo times the light's irradiance (the brightness of a surface facing the light).
    pub albedo: f64,
}

impl LightEstimate {
    /// The direction as a vector.
    pub fn light(&self) -> Vector3<f64> {
        Vector3::from(self.direction)
    }
}

/// (f₁(σ), f₂(σ)): the first two moments of max(0, n·s) for normals uniform over the unit disk
/// of the projected hemisphere (a sphere's image) and a light at slant σ.
pub fn sphere_moments(slant_deg: f64) -> (f64, f64) {
    let (ss, cs) = slant_deg.to_radians().sin_cos();
    let (mut m1, mut m2) = (0.0, 0.0);
    for i in 0..RADIAL {
        // Midpoint rule in r², so that every ring has equal area.
        let r2 = (i as f64 + 0.5) / RADIAL as f64;
        let r = r2.sqrt();
        let nz = (1.0 - r2).sqrt();
        for j in 0..ANGULAR {
            let phi = (j as f64 + 0.5) / ANGULAR as f64 * std::f64::consts::TAU;
            let v = (r * phi.cos() * ss + nz * cs).max(0.0);
            m1 += v;
            m2 += v * v;
        }
    }
    let count = (RADIAL * ANGULAR) as f64;
    (m1 / count, m2 / count)
}

/// Estimates the light direction and albedo of `image` inside `mask` (see the module
/// documentation).
///
/// # Errors
/// [`Error::InvalidParameter`] when the sizes differ, fewer than 16 finite mask pixels exist,
/// or the image is dark inside the mask.
pub fn estimate_light(image: &ScalarMap, mask: &Mask) -> Result<LightEstimate> {
    image.check_same_size(mask, "mask")?;
    let (w, h) = (image.width(), image.height());
    let at = |x: usize, y: usize| {
        let i = y * w + x;
        (mask.data()[i] && image.data()[i].is_finite()).then(|| f64::from(image.data()[i]))
    };
    let (mut s1, mut s2, mut count) = (0.0, 0.0, 0usize);
    let (mut gx, mut gy) = (0.0, 0.0);
    for y in 0..h {
        for x in 0..w {
            let Some(v) = at(x, y) else { continue };
            s1 += v;
            s2 += v * v;
            count += 1;
            if x + 1 < w
                && let Some(r) = at(x + 1, y)
            {
                gx += r - v;
            }
            // y is up: the row above is y + 1.
            if y >= 1
                && let Some(a) = at(x, y - 1)
            {
                gy += a - v;
            }
        }
    }
    if count < 16 {
        return Err(Error::param(
            "mask",
            format!("{count} usable pixels: too few to estimate the light"),
        ));
    }
    let (m1, m2) = (s1 / count as f64, s2 / count as f64);
    if !(m1 > 0.0 && m2 > 0.0) {
        return Err(Error::param(
            "image",
            "is dark inside the mask: no light to estimate",
        ));
    }
    let ratio = m1 * m1 / m2;
    // Invert the decreasing ratio f₁²/f₂ on a table of slants.
    let steps = (89.5 / TABLE_STEP_DEG) as usize;
    let mut prev = (0.0, {
        let (a, b) = sphere_moments(0.0);
        a * a / b
    });
    let mut slant = 0.0;
    if ratio < prev.1 {
        slant = 89.5;
        for i in 1..=steps {
            let sd = i as f64 * TABLE_STEP_DEG;
            let (a, b) = sphere_moments(sd);
            let g = a * a / b;
            if g <= ratio {
                let t = (prev.1 - ratio) / (prev.1 - g);
                slant = prev.0 + t * (sd - prev.0);
                break;
            }
            prev = (sd, g);
        }
    }
    let (f1, _) = sphere_moments(slant);
    let albedo = m1 / f1;
    let tilt = gy.atan2(gx);
    let (ss, cs) = slant.to_radians().sin_cos();
    let dir = [ss * tilt.cos(), ss * tilt.sin(), cs];
    Ok(LightEstimate {
        direction: dir,
        slant_deg: slant,
        tilt_deg: tilt.to_degrees(),
        albedo,
    })
}

/// Estimates the albedo alone when the light's slant is known: ρ = m₁/f₁(σ), with the same
/// sphere-like assumption as [`estimate_light`].
///
/// # Errors
/// As [`estimate_light`].
pub fn estimate_albedo(image: &ScalarMap, mask: &Mask, slant_deg: f64) -> Result<f64> {
    image.check_same_size(mask, "mask")?;
    let (sum, count) = image
        .data()
        .iter()
        .zip(mask.data())
        .filter(|(v, m)| **m && v.is_finite())
        .fold((0.0, 0usize), |(s, c), (v, _)| (s + f64::from(*v), c + 1));
    if count < 16 || sum <= 0.0 {
        return Err(Error::param(
            "image",
            format!(
                "{count} usable pixels with total brightness {sum}: cannot estimate the albedo"
            ),
        ));
    }
    Ok(sum / count as f64 / sphere_moments(slant_deg.clamp(0.0, 89.5)).0)
}

/// The distant light and albedo of a shape-from-shading run, and where each came from.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Illumination {
    /// The light direction used: as given (not normalised), or the estimate's unit direction.
    pub light: [f64; 3],
    /// The albedo used.
    pub albedo: f64,
    /// Whether the light was estimated from the image (not given).
    pub light_estimated: bool,
    /// Whether the albedo was estimated from the image (not given).
    pub albedo_estimated: bool,
    /// The estimate of light and albedo ([`estimate_light`]), when the light was not given.
    pub estimate: Option<LightEstimate>,
}

/// The reflectance map and [`Illumination`] of a distant-light shape-from-shading run: the
/// light and albedo given, and whichever is missing estimated from `image` over `mask` — the
/// light with [`estimate_light`] (which gives the albedo too), the albedo alone with
/// [`estimate_albedo`] at the given light's slant.
///
/// # Errors
/// [`Error::InvalidParameter`] naming `light` when the light or the albedo is missing and
/// `material` is not Lambertian (both estimates assume Lambert's law); the errors of [`ReflectanceMap::new`](super::reflectance_map::ReflectanceMap::new),
/// [`estimate_light`] and [`estimate_albedo`].
pub fn illumination(
    image: &ScalarMap,
    mask: &Mask,
    light: Option<Vector3<f64>>,
    albedo: Option<f64>,
    material: crate::synth::reflectance::Material,
) -> Result<(super::reflectance_map::ReflectanceMap, Illumination)> {
    if (light.is_none() || albedo.is_none())
        && material != crate::synth::reflectance::Material::lambertian()
    {
        return Err(Error::param(
            if light.is_none() { "light" } else { "albedo" },
            "the light and albedo are estimated for a Lambertian surface only; give both for \
             this reflectance",
        ));
    }
    let (light, estimate) = match light {
        Some(l) => (l, None),
        None => {
            let e = estimate_light(image, mask)?;
            (e.light(), Some(e))
        }
    };
    let rmap = super::reflectance_map::ReflectanceMap::new(light, material)?;
    let albedo_used = match (albedo, &estimate) {
        (Some(v), _) => v,
        (None, Some(e)) => e.albedo,
        (None, None) => estimate_albedo(image, mask, rmap.slant_deg())?,
    };
    Ok((
        rmap,
        Illumination {
            light: [light.x, light.y, light.z],
            albedo: albedo_used,
            light_estimated: estimate.is_some(),
            albedo_estimated: albedo.is_none(),
            estimate,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moments_match_the_closed_forms_without_shadow() {
        // Below the slant where the terminator reaches the disk (σ = 0 here), no shadow.
        let (f1, f2) = sphere_moments(0.0);
        assert!((f1 - 2.0 / 3.0).abs() < 1e-4, "{f1}");
        assert!((f2 - 0.5).abs() < 1e-4, "{f2}");
        // At σ = 90° half the disk is dark: f₁ = 2/(3π), f₂ = 1/8.
        let (f1, f2) = sphere_moments(90.0);
        assert!(
            (f1 - 2.0 / (3.0 * std::f64::consts::PI)).abs() < 1e-4,
            "{f1}"
        );
        assert!((f2 - 0.125).abs() < 1e-4, "{f2}");
    }

    /// What is given is used as given; what is missing is estimated (the light with the
    /// albedo, or the albedo alone at the given light's slant); a reflectance other than
    /// Lambert's is refused without both.
    #[test]
    fn illumination_estimates_only_what_is_missing() {
        use crate::synth::reflectance::{Diffuse, Material};
        use crate::synth::scene::{Albedo, Scene};
        let l = Vector3::new(0.3, 0.25, 0.92).normalize();
        let rmap = super::super::reflectance_map::ReflectanceMap::lambertian(l).unwrap();
        let truth = Scene::sphere(80, 30.0, Albedo::Constant(0.7)).height_field();
        let image = truth.normals.map(|n| {
            let n = n.cast::<f64>();
            if n.x.is_nan() {
                0.0
            } else {
                (0.7 * rmap.eval(-n.x / n.z, -n.y / n.z)) as f32
            }
        });
        let lambert = Material::lambertian();
        let (_, given) = illumination(&image, &truth.mask, Some(l), Some(0.5), lambert).unwrap();
        assert_eq!((given.albedo, given.light_estimated), (0.5, false));
        assert!(!given.albedo_estimated && given.estimate.is_none());
        let (_, albedo_only) = illumination(&image, &truth.mask, Some(l), None, lambert).unwrap();
        assert!(albedo_only.albedo_estimated && !albedo_only.light_estimated);
        assert!(
            (albedo_only.albedo - 0.7).abs() < 0.02,
            "{}",
            albedo_only.albedo
        );
        let (rm, both) = illumination(&image, &truth.mask, None, None, lambert).unwrap();
        let off = Vector3::from(both.light).angle(&l).to_degrees();
        assert!(both.light_estimated && off < 3.0, "{off}°");
        assert!((rm.slant_deg() - both.estimate.unwrap().slant_deg).abs() < 1e-9);
        let rough = Material {
            diffuse: Diffuse::OrenNayar { sigma: 0.3 },
            ..lambert
        };
        let named = |e: Error| match e {
            Error::InvalidParameter { name, .. } => name,
            other => panic!("{other}"),
        };
        let e = illumination(&image, &truth.mask, Some(l), None, rough).unwrap_err();
        assert_eq!(named(e), "albedo");
        let e = illumination(&image, &truth.mask, None, Some(0.7), rough).unwrap_err();
        assert_eq!(named(e), "light");
        assert!(illumination(&image, &truth.mask, Some(l), Some(0.7), rough).is_ok());
    }
}
