//! Rendering synthetic photometric-stereo images of a [`HeightField`] under distant lights.
//!
//! Image model (Lambertian): pixel = E_k · ρ · max(0, n·l_k) + ambient·ρ, with E_k the light's
//! grey intensity, so a solver fed images divided by E_k sees g = ρN exactly. Orthographic camera
//! looking down −z. Attached shadows come from n·l ≤ 0; cast shadows from marching a ray over the
//! height field towards each light. Optional Gaussian read noise, seeded per image so the same
//! seed gives the same images.

use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, ScalarMap};
use crate::input::ImageStack;
use crate::lights::Lights;
use crate::scene::{HeightField, Scene};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

/// Ray-march step along the light's image-plane direction, in pixels.
const MARCH_STEP: f64 = 0.5;
/// Height tolerance for cast-shadow tests, in pixel units.
const SHADOW_EPS: f64 = 1e-3;

/// Rendering options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    /// Compute cast shadows (attached shadows are always present).
    pub cast_shadows: bool,
    /// Ambient term added as ambient·ρ (0 for a dark room).
    pub ambient: f32,
    /// Standard deviation of additive Gaussian noise (image units; 0 for none).
    pub noise_sigma: f32,
    /// Seed of the noise; image k uses `seed + k`.
    pub seed: u64,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            cast_shadows: true,
            ambient: 0.0,
            noise_sigma: 0.0,
            seed: 0,
        }
    }
}

/// Rendered images and their shadow ground truth.
#[derive(Debug, Clone)]
pub struct Rendering {
    /// The rendered surface: depth, normals, albedo, mask.
    pub truth: HeightField,
    /// One image per light, 0 outside the mask.
    pub images: Vec<ScalarMap>,
    /// Per light: pixels in attached shadow (n·l ≤ 0).
    pub attached: Vec<Mask>,
    /// Per light: lit-facing pixels whose view of the light is blocked by the surface.
    pub cast: Vec<Mask>,
}

impl Rendering {
    /// The images as a stack for the solver, divided by the lights' grey intensities.
    ///
    /// # Errors
    /// [`Error::LightsMismatch`] when the counts differ.
    pub fn to_stack(&self, lights: &Lights) -> Result<ImageStack> {
        if lights.len() != self.images.len() {
            return Err(Error::LightsMismatch {
                reason: format!("{} lights for {} images", lights.len(), self.images.len()),
            });
        }
        let first = self
            .images
            .first()
            .ok_or(Error::TooFewImages { count: 0 })?;
        let images = self
            .images
            .iter()
            .zip(lights.lights())
            .map(|(im, l)| {
                let e = l.grey_intensity() as f32;
                im.data().iter().map(|v| v / e).collect()
            })
            .collect();
        ImageStack::from_images(first.width(), first.height(), 1, images)
    }
}

/// Whether the point (x, y, z) is hidden from a light in direction `l` by the scene's surface:
/// marches the ray (x, y, z) + s·l over the analytic height function.
fn in_cast_shadow(scene: &Scene, x: f64, y: f64, z: f64, l: &[f64; 3], zmax: f64) -> bool {
    let lxy = (l[0] * l[0] + l[1] * l[1]).sqrt();
    if lxy < 1e-9 {
        return false;
    }
    let (ux, uy) = (l[0] / lxy, l[1] / lxy);
    let rise = l[2] / lxy;
    let (hw, hh) = (scene.width as f64 / 2.0, scene.height as f64 / 2.0);
    let mut s = MARCH_STEP;
    loop {
        let (px, py) = (x + ux * s, y + uy * s);
        if px.abs() > hw || py.abs() > hh {
            return false;
        }
        let ray = z + s * rise;
        if ray > zmax {
            return false;
        }
        if scene
            .height_at(px, py)
            .is_some_and(|h| h > ray + SHADOW_EPS)
        {
            return true;
        }
        s += MARCH_STEP;
    }
}

/// Renders a Lambertian [`Scene`] under `lights`; the rendering carries the scene's
/// [`HeightField`] as ground truth.
///
/// # Errors
/// [`Error::InvalidParameter`] for a negative or non-finite noise level or ambient term.
pub fn render_lambertian(
    scene: &Scene,
    lights: &Lights,
    options: &RenderOptions,
) -> Result<Rendering> {
    if !(options.noise_sigma >= 0.0 && options.noise_sigma.is_finite()) {
        return Err(Error::param(
            "noise",
            format!("{} must be finite and ≥ 0", options.noise_sigma),
        ));
    }
    if !(options.ambient >= 0.0 && options.ambient.is_finite()) {
        return Err(Error::param(
            "ambient",
            format!("{} must be finite and ≥ 0", options.ambient),
        ));
    }
    let hf = scene.height_field();
    let (w, h) = (hf.mask.width(), hf.mask.height());
    // Primitives may peak between pixel centres: allow a margin over the sampled maximum.
    let zmax = 1.0
        + hf.depth
            .data()
            .iter()
            .filter(|v| v.is_finite())
            .fold(f64::NEG_INFINITY, |m, v| m.max(f64::from(*v)));
    let per_light: Vec<(ScalarMap, Mask, Mask)> = lights
        .lights()
        .par_iter()
        .enumerate()
        .map(|(k, light)| {
            let l = [light.direction.x, light.direction.y, light.direction.z];
            let e = light.grey_intensity() as f32;
            let mut img = Grid::new(w, h, 0f32);
            let mut attached = Grid::new(w, h, false);
            let mut cast = Grid::new(w, h, false);
            for r in 0..h {
                for c in 0..w {
                    if !*hf.mask.at(c, r) {
                        continue;
                    }
                    let n = hf.normals.at(c, r).cast::<f64>();
                    let rho = *hf.albedo.at(c, r);
                    let shade = n.x * l[0] + n.y * l[1] + n.z * l[2];
                    let mut v = options.ambient * rho;
                    if shade <= 0.0 {
                        *attached.at_mut(c, r) = true;
                    } else if options.cast_shadows && {
                        let (x, y) = scene.pixel_xy(c, r);
                        in_cast_shadow(scene, x, y, f64::from(*hf.depth.at(c, r)), &l, zmax)
                    } {
                        *cast.at_mut(c, r) = true;
                    } else {
                        v += e * rho * shade as f32;
                    }
                    *img.at_mut(c, r) = v;
                }
            }
            if options.noise_sigma > 0.0 {
                let mut rng =
                    rand::rngs::ChaCha8Rng::seed_from_u64(options.seed.wrapping_add(k as u64));
                // σ was checked finite and ≥ 0 above, so the distribution exists.
                if let Ok(noise) = Normal::new(0.0f32, options.noise_sigma) {
                    for (v, m) in img.data_mut().iter_mut().zip(hf.mask.data()) {
                        if *m {
                            *v += noise.sample(&mut rng);
                        }
                    }
                }
            }
            (img, attached, cast)
        })
        .collect();
    let mut out = Rendering {
        truth: hf,
        images: Vec::with_capacity(per_light.len()),
        attached: Vec::with_capacity(per_light.len()),
        cast: Vec::with_capacity(per_light.len()),
    };
    for (i, a, c) in per_light {
        out.images.push(i);
        out.attached.push(a);
        out.cast.push(c);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Albedo, Primitive};
    use nalgebra::Vector3;

    #[test]
    fn lambertian_sphere_matches_closed_form() {
        let scene = Scene::sphere(64, 28.0, Albedo::Constant(0.7));
        let lights = Lights::ring(5, 40.0, 10.0).unwrap();
        let r = render_lambertian(&scene, &lights, &RenderOptions::default()).unwrap();
        let hf = &r.truth;
        for (k, l) in lights.directions().iter().enumerate() {
            for i in 0..hf.mask.len() {
                if !hf.mask.data()[i] {
                    continue;
                }
                let n = hf.normals.data()[i].cast::<f64>();
                let expect = (0.7 * n.dot(l)).max(0.0) as f32;
                // A convex object casts no shadows on itself.
                let got = r.images[k].data()[i];
                assert!(
                    (got - expect).abs() < 1e-5,
                    "light {k} pixel {i}: {got} vs {expect}"
                );
                assert!(!r.cast[k].data()[i]);
            }
        }
    }

    #[test]
    fn hemisphere_casts_shadow_on_ground_away_from_light() {
        let scene = Scene {
            width: 81,
            height: 41,
            objects: vec![(
                Primitive::Sphere {
                    cx: 0.0,
                    cy: 0.0,
                    radius: 10.0,
                    base: 0.0,
                },
                Albedo::Constant(0.5),
            )],
            ground: Some(Albedo::Constant(0.5)),
        };
        // Light from the right (+x) at 30° elevation: the shadow falls to the left and ends where
        // the ray grazing the sphere meets the ground, R/sin(30°) = 20 px from the centre.
        let e = 30f64.to_radians();
        let lights = Lights::from_directions(&[Vector3::new(e.cos(), 0.0, e.sin())]).unwrap();
        let r = render_lambertian(&scene, &lights, &RenderOptions::default()).unwrap();
        let cast = &r.cast[0];
        let row = 20; // y = 0
        let shadowed: Vec<usize> = (0..81).filter(|&c| *cast.at(c, row)).collect();
        let leftmost = *shadowed.first().unwrap();
        let x_left = scene.pixel_xy(leftmost, row).0;
        assert!(
            x_left > -20.0 && x_left <= -19.0,
            "shadow ends at x = {x_left}"
        );
        assert!(shadowed.iter().all(|&c| scene.pixel_xy(c, row).0 < -9.0));
        assert!(r.images[0].at(leftmost, row).abs() < 1e-6);
    }

    #[test]
    fn noise_is_seeded_and_has_the_requested_sigma() {
        let scene = Scene {
            width: 100,
            height: 100,
            objects: vec![],
            ground: Some(Albedo::Constant(0.5)),
        };
        let lights = Lights::from_directions(&[Vector3::z()]).unwrap();
        let o = RenderOptions {
            noise_sigma: 0.01,
            seed: 3,
            ..RenderOptions::default()
        };
        let a = render_lambertian(&scene, &lights, &o).unwrap();
        let b = render_lambertian(&scene, &lights, &o).unwrap();
        assert_eq!(a.images[0], b.images[0]);
        let n = a.images[0].len() as f64;
        let var = a.images[0]
            .data()
            .iter()
            .map(|v| (f64::from(*v) - 0.5).powi(2))
            .sum::<f64>()
            / n;
        assert!((var.sqrt() - 0.01).abs() < 0.0005, "σ = {}", var.sqrt());
    }
}
