//! Rendering under near point lights (LEDs) seen by a pinhole camera: the scenes of
//! [`crate::ps::near`], where each pixel sees each light from its own direction and distance.
//!
//! Geometry: the scene's height field (in its pixel units) is placed in the camera frame
//! (x right, y up, z towards the viewer, [`crate::camera`]) by a [`NearPlacement`]: the scene
//! point (x, y, h) is at (s·x, s·y, s·h − D), s camera units (say millimetres) per scene pixel,
//! the base plane h = 0 at distance D in front of the camera. Each pixel's ray
//! d·((u − c_x)/f_x, −(v − c_y)/f_y, −1) is marched in depth d every half scene pixel from the
//! top of the scene and its first crossing of the surface located by bisection, so the ground
//! truth (depth along the optical axis, the analytic normal) is exact to 10⁻⁹ of a pixel.
//!
//! Image model for a light at P of intensity Φ_c with angular profile cos^μ θ about its
//! principal direction (θ between it and X − P; [`crate::capture::lights::Anisotropy`]):
//! pixel_c = Φ_c·cos^μ θ/|P − X|² · π f_c(l, v)·max(0, n·l), with l = (P − X)/|P − X| and
//! v = −X/|X| the direction to the camera — the inverse-square fall-off of a point source and
//! the per-point light and view directions that the distant model ([`crate::synth::render`])
//! takes as constant. Cast shadows march from the surface point towards P over the height
//! field ([`crate::synth::raymarch`]); the camera's noise and clipping are the distant
//! renderer's. Mirror lobes, area lights and interreflections are not rendered here.

use crate::camera::Intrinsics;
use crate::capture::lights::{Anisotropy, Light, Lights};
use crate::capture::stack::GREY_WEIGHTS;
use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::synth::raymarch::{HeightBounds, MARCH_STEP, in_cast_shadow};
use crate::synth::reflectance::Frame;
use crate::synth::render::{LightImages, RenderOptions, Rendering, apply_camera};
use crate::synth::scene::{HeightField, Scene};
use nalgebra::Vector3;
use rayon::prelude::*;

/// Bisection steps that locate a pixel ray's first hit within the half-pixel step that crossed
/// (0.5 · 2⁻³⁰ pixel).
const HIT_BISECTIONS: usize = 30;

/// Where a scene stands in front of the camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NearPlacement {
    /// Distance D of the scene's base plane (height 0) from the camera centre along the optical
    /// axis, in camera units.
    pub distance: f64,
    /// Camera units per scene pixel (the size of a scene pixel, say in millimetres).
    pub scale: f64,
}

impl NearPlacement {
    /// The camera-frame point of scene point (x, y) at height `h`.
    pub fn to_camera(&self, x: f64, y: f64, h: f64) -> Vector3<f64> {
        Vector3::new(
            self.scale * x,
            self.scale * y,
            self.scale * h - self.distance,
        )
    }

    /// The scene point (x, y, height) of camera-frame point `p`.
    pub fn to_scene(&self, p: &Vector3<f64>) -> Vector3<f64> {
        Vector3::new(
            p.x / self.scale,
            p.y / self.scale,
            (p.z + self.distance) / self.scale,
        )
    }

    /// The pinhole camera that sees the base plane at one image pixel per scene pixel, centred
    /// on the scene (focal length D/s).
    pub fn camera(&self, scene: &Scene) -> Intrinsics {
        let f = self.distance / self.scale;
        Intrinsics {
            fx: f,
            fy: f,
            cx: (scene.width as f64 - 1.0) / 2.0,
            cy: (scene.height as f64 - 1.0) / 2.0,
        }
    }

    fn validate(&self) -> Result<()> {
        if !(self.distance.is_finite() && self.distance > 0.0) {
            return Err(Error::param(
                "distance",
                format!("{} must be finite and > 0", self.distance),
            ));
        }
        if !(self.scale.is_finite() && self.scale > 0.0) {
            return Err(Error::param(
                "scale",
                format!("{} must be finite and > 0", self.scale),
            ));
        }
        Ok(())
    }
}

/// `count` LEDs evenly spaced on a ring of radius `radius` about the optical axis in the plane
/// z = `z` (camera frame; 0 is the camera's plane), starting at angle `phase_deg`, each of
/// unit intensity and pointing at `target` with the profile cos^`mu` (isotropic for μ = 0).
/// Their `direction` is the direction to them from `target`.
///
/// # Errors
/// [`Error::InvalidParameter`] for no lights or a non-finite or non-positive radius; the errors
/// of [`Lights::new`] (a light at `target`).
pub fn led_ring(
    count: usize,
    radius: f64,
    z: f64,
    phase_deg: f64,
    target: Vector3<f64>,
    mu: f64,
) -> Result<Lights> {
    if count == 0 {
        return Err(Error::param("count", "a ring needs at least one light"));
    }
    if !(radius.is_finite() && radius > 0.0 && z.is_finite()) {
        return Err(Error::param(
            "radius",
            format!("{radius} (at z = {z}) must be finite and > 0"),
        ));
    }
    let lights = (0..count)
        .map(|k| {
            let a = phase_deg.to_radians() + 2.0 * std::f64::consts::PI * k as f64 / count as f64;
            let p = Vector3::new(radius * a.cos(), radius * a.sin(), z);
            let mut light = Light::near(p, target);
            if mu > 0.0 {
                light.anisotropy = Some(Anisotropy {
                    principal: target - p,
                    mu,
                });
            }
            light
        })
        .collect();
    Lights::new(lights)
}

/// The rig of the near-light tests and of `data-synth --near-distance`: `count` LEDs, half on a
/// ring at 25° and half on a ring at 45° from the optical axis as seen from `target`, all at
/// `distance` from it, each of intensity distance² (so that the target receives an irradiance
/// of 1 from each) and profile cos^`mu` about the direction to the target.
///
/// # Errors
/// [`Error::InvalidParameter`] for fewer than 4 lights or a non-positive distance; the errors of
/// [`led_ring`].
pub fn two_ring_rig(count: usize, distance: f64, target: Vector3<f64>, mu: f64) -> Result<Lights> {
    if count < 4 || !(distance.is_finite() && distance > 0.0) {
        return Err(Error::param(
            "lights",
            format!("{count} lights at distance {distance}: at least 4, at a positive distance"),
        ));
    }
    if !(mu.is_finite() && mu >= 0.0) {
        return Err(Error::param("mu", format!("{mu} must be ≥ 0")));
    }
    let ring = |n: usize, deg: f64, phase: f64| {
        let t: f64 = deg.to_radians();
        led_ring(
            n,
            distance * t.sin(),
            target.z + distance * t.cos(),
            phase,
            target,
            mu,
        )
    };
    let mut all = ring(count / 2, 25.0, 0.0)?.lights().to_vec();
    all.extend_from_slice(ring(count - count / 2, 45.0, 22.5)?.lights());
    for l in &mut all {
        l.intensity = [distance * distance; 3];
    }
    Lights::new(all)
}

/// The irradiance factor and unit direction of near light `light` at camera-frame point `x`:
/// (Φ-less fall-off cos^μ θ / |P − X|², (P − X)/|P − X|); `None` for a light without a position
/// or at the point itself.
pub fn near_light_at(light: &Light, x: &Vector3<f64>) -> Option<(f64, Vector3<f64>)> {
    let w = light.position? - x;
    let r2 = w.norm_squared();
    if !(r2 > 0.0 && r2.is_finite()) {
        return None;
    }
    let r = r2.sqrt();
    let l = w / r;
    let profile = match light.anisotropy {
        Some(a) if a.mu > 0.0 => {
            let c = (-a.principal.dot(&l)).max(0.0);
            // Whole exponents (a Lambertian LED has μ = 1) by multiplication.
            if a.mu == a.mu.round() && a.mu <= 64.0 {
                c.powi(a.mu as i32)
            } else {
                c.powf(a.mu)
            }
        }
        _ => 1.0,
    };
    Some((profile / r2, l))
}

/// Renders `scene`, placed by `placement`, through the pinhole `camera` under the near lights
/// `lights` (every one with a position, above the scene's top); the rendering's ground truth
/// holds the depth along the optical axis (camera units) in [`HeightField::depth`], the
/// normals, albedo and mask of what each pixel sees.
///
/// # Errors
/// [`Error::InvalidParameter`] for invalid options or placement, options this renderer does not
/// support (mirror lobes, area lights, interreflections), an empty image, or a light without a
/// position or not above every surface; [`Error::InvalidLight`] naming the light.
pub fn render_near(
    scene: &Scene,
    lights: &Lights,
    camera: &Intrinsics,
    placement: &NearPlacement,
    options: &RenderOptions,
) -> Result<Rendering> {
    options.validate()?;
    placement.validate()?;
    if scene.width == 0 || scene.height == 0 {
        return Err(Error::param("size", "the image must have pixels"));
    }
    if options.bounces > 0 || options.area_light_samples > 1 || options.pixel_samples > 1 {
        return Err(Error::param(
            "options",
            "near-light rendering has no interreflections, area lights or sub-pixel samples",
        ));
    }
    for o in &scene.objects {
        o.material.validate()?;
        if o.material.mirror().is_some() {
            return Err(Error::param(
                "material",
                "near-light rendering has no mirror lobes",
            ));
        }
    }
    let bounds = HeightBounds::new(scene);
    let top = bounds.zmax();
    for (index, l) in lights.lights().iter().enumerate() {
        let Some(p) = l.position else {
            return Err(Error::InvalidLight {
                index,
                reason: "a near light needs a position".into(),
            });
        };
        if placement.to_scene(&p).z <= top {
            return Err(Error::InvalidLight {
                index,
                reason: format!(
                    "position {:?} is not above the scene's top (height {top:.1} scene pixels)",
                    p.as_slice()
                ),
            });
        }
    }
    let (truth, depths) = trace(scene, camera, placement, top);
    let (w, h) = (scene.width, scene.height);
    let channels = if options.color { 3 } else { 1 };
    // The ambient term lights every surface pixel, shadowed or not.
    let ambient_light =
        crate::synth::render::ambient_light(scene, &truth, channels, options.ambient);
    let per_light: Vec<LightImages> = lights
        .lights()
        .par_iter()
        .enumerate()
        .map(|(k, light)| {
            let mut planes = vec![Grid::new(w, h, 0f32); channels];
            let mut attached = Grid::new(w, h, false);
            let mut cast = Grid::new(w, h, false);
            let mut saturated = Grid::new(w, h, false);
            let p_scene = light.position.map(|p| placement.to_scene(&p));
            // The hits' depths in full precision (the truth map holds them in f32).
            for (i, &d) in depths.iter().enumerate() {
                if !truth.mask.data()[i] {
                    continue;
                }
                let (c, r) = (i % w, i / w);
                let x = Vector3::from(camera.unproject(c as f64, r as f64, d));
                let n = truth.normals.data()[i].cast::<f64>();
                let Some((fall, l)) = near_light_at(light, &x) else {
                    continue;
                };
                let cos_i = n.dot(&l);
                if cos_i <= 0.0 {
                    attached.data_mut()[i] = true;
                    continue;
                }
                if options.cast_shadows
                    && let Some(ps) = p_scene
                {
                    let xs = placement.to_scene(&x);
                    if in_cast_shadow(
                        scene,
                        &bounds,
                        (xs.x, xs.y, xs.z),
                        &(ps - xs),
                        MARCH_STEP,
                        0,
                    ) {
                        cast.data_mut()[i] = true;
                        continue;
                    }
                }
                let obj = &scene.objects[*truth.object.at(c, r) as usize];
                let rho = f64::from(truth.albedo.data()[i]);
                let frame = Frame::from_normal(n);
                let view = -x.normalize();
                let f = obj
                    .material
                    .eval(rho, &frame.to_local(&l), &frame.to_local(&view));
                let rgb = [0, 1, 2]
                    .map(|ch| light.intensity[ch] * fall * std::f64::consts::PI * f[ch] * cos_i);
                if channels == 1 {
                    planes[0].data_mut()[i] =
                        (0..3).map(|ch| GREY_WEIGHTS[ch] * rgb[ch] as f32).sum();
                } else {
                    for (plane, v) in planes.iter_mut().zip(rgb) {
                        plane.data_mut()[i] = v as f32;
                    }
                }
            }
            if let Some(ambient) = &ambient_light {
                for (plane, a) in planes.iter_mut().zip(ambient) {
                    for (v, a) in plane.data_mut().iter_mut().zip(a.data()) {
                        *v += a;
                    }
                }
            }
            apply_camera(&mut planes, &truth.mask, &mut saturated, options, k);
            (planes, attached, cast, saturated)
        })
        .collect();
    let ambient =
        crate::synth::render::ambient_frame(scene, &truth, channels, options, lights.len());
    let mut out = Rendering::assemble(truth, channels, per_light);
    out.ambient = ambient;
    Ok(out)
}

/// What each pixel's ray meets first: depth along the optical axis, normal, albedo, object;
/// and the depths in full precision (NaN where the ray meets nothing).
fn trace(
    scene: &Scene,
    camera: &Intrinsics,
    placement: &NearPlacement,
    top: f64,
) -> (HeightField, Vec<f64>) {
    let (w, h) = (scene.width, scene.height);
    // The lowest surface height seen orthographically bounds the march from below.
    let ortho = scene.height_field();
    let bottom = ortho
        .depth
        .data()
        .iter()
        .filter(|v| v.is_finite())
        .fold(f64::INFINITY, |a, &b| a.min(f64::from(b)));
    let mut depth = Grid::new(w, h, f32::NAN);
    let mut normals = Grid::new(w, h, Vector3::repeat(f32::NAN));
    let mut albedo = Grid::new(w, h, f32::NAN);
    let mut mask = Grid::new(w, h, false);
    let mut object = Grid::new(w, h, u32::MAX);
    let mut exact = vec![f64::NAN; w * h];
    if !bottom.is_finite() {
        return (
            HeightField {
                depth,
                normals,
                albedo,
                mask,
                object,
            },
            exact,
        );
    }
    let s = placement.scale;
    let near = placement.distance - s * top;
    let far = placement.distance - s * (bottom - 1.0);
    let step = 0.5 * s;
    // Per pixel: depth, normal, object, albedo.
    type Hit = Option<(f64, Vector3<f64>, usize, f32)>;
    let hits: Vec<Hit> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (u, v) = ((i % w) as f64, (i / w) as f64);
            let ray = Vector3::from(camera.unproject(u, v, 1.0));
            // Height of the surface over the ray's point at depth d, minus the point's height.
            let gap = |d: f64| {
                let p = placement.to_scene(&(ray * d));
                scene.height_at(p.x, p.y).map(|hs| hs - p.z)
            };
            let mut lo = near.max(1e-9 * s);
            let mut found = None;
            let mut d = lo;
            while d <= far + step {
                if gap(d).is_some_and(|g| g >= 0.0) {
                    if d > lo || gap(lo).is_some_and(|g| g < 0.0) {
                        found = Some((lo, d));
                    }
                    break;
                }
                lo = d;
                d += step;
            }
            let (mut a, mut b) = found?;
            // The ray was clear at a; a hit at the first sample means it started inside.
            if gap(a).is_some_and(|g| g >= 0.0) {
                return None;
            }
            for _ in 0..HIT_BISECTIONS {
                let m = 0.5 * (a + b);
                if gap(m).is_some_and(|g| g >= 0.0) {
                    b = m;
                } else {
                    a = m;
                }
            }
            let p = placement.to_scene(&(ray * b));
            let (_, n, o) = scene.surface_at(p.x, p.y)?;
            Some((b, n, o, scene.objects[o].albedo.at(p.x, p.y)))
        })
        .collect();
    for (i, hit) in hits.into_iter().enumerate() {
        if let Some((d, n, o, rho)) = hit {
            exact[i] = d;
            depth.data_mut()[i] = d as f32;
            normals.data_mut()[i] = n.cast::<f32>();
            albedo.data_mut()[i] = rho;
            mask.data_mut()[i] = true;
            object.data_mut()[i] = o as u32;
        }
    }
    (
        HeightField {
            depth,
            normals,
            albedo,
            mask,
            object,
        },
        exact,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::scene::Albedo;

    /// A Lambertian sphere under one isotropic point light: every pixel is ρ Φ n·l/r², with l
    /// and r from the closed-form intersection of the pixel's ray with the sphere.
    #[test]
    fn lambertian_sphere_matches_the_closed_form() {
        let scene = Scene::sphere(64, 24.0, Albedo::Constant(0.6));
        let placement = NearPlacement {
            distance: 300.0,
            scale: 1.0,
        };
        let camera = placement.camera(&scene);
        let light = Light::near(
            Vector3::new(60.0, -40.0, -100.0),
            Vector3::new(0.0, 0.0, -300.0),
        );
        let mut light = light;
        light.intensity = [2.0e4; 3];
        let lights = Lights::new(vec![light]).unwrap();
        let opts = RenderOptions::default();
        let r = render_near(&scene, &lights, &camera, &placement, &opts).unwrap();
        let centre = Vector3::new(0.0, 0.0, -300.0);
        let mut checked = 0;
        for i in 0..64 * 64 {
            let (u, v) = ((i % 64) as f64, (i / 64) as f64);
            let ray = Vector3::from(camera.unproject(u, v, 1.0));
            // |t·ray − c|² = R²: the nearer root.
            let (a, b, c) = (
                ray.norm_squared(),
                -2.0 * ray.dot(&centre),
                centre.norm_squared() - 24.0f64.powi(2),
            );
            let disc = b * b - 4.0 * a * c;
            let hit = r.truth.mask.data()[i];
            if disc < 0.0 {
                assert!(!hit, "pixel {i} hit outside the sphere");
                continue;
            }
            let t = (-b - disc.sqrt()) / (2.0 * a);
            let x = ray * t;
            // Grazing pixels, where a half-pixel march may miss the rim, are not compared.
            let n = (x - centre) / 24.0;
            if n.dot(&(-x.normalize())) < 0.05 {
                continue;
            }
            assert!(hit, "pixel {i} missed the sphere");
            assert!((f64::from(*r.truth.depth.at(i % 64, i / 64)) - t).abs() < 1e-3);
            let w = lights.lights()[0].position.unwrap() - x;
            let expect = (0.6 * 2.0e4 * n.dot(&w.normalize()) / w.norm_squared()).max(0.0);
            let got = f64::from(r.images[0][0].data()[i]);
            assert!(
                (got - expect).abs() < 1e-4 * expect.max(1e-3),
                "pixel {i}: {got} against {expect}"
            );
            checked += 1;
        }
        assert!(checked > 1500, "{checked} pixels compared");
    }

    /// The angular profile: an LED pointing away from a point lights it less by cos^μ θ.
    #[test]
    fn the_profile_falls_as_a_cosine_power() {
        let x = Vector3::new(0.0, 0.0, -100.0);
        let mut l = Light::near(Vector3::new(0.0, 0.0, 0.0), x);
        let (iso, _) = near_light_at(&l, &x).unwrap();
        assert!((iso - 1e-4).abs() < 1e-12);
        let theta = 30f64.to_radians();
        l.anisotropy = Some(Anisotropy {
            principal: Vector3::new(theta.sin(), 0.0, -theta.cos()),
            mu: 3.0,
        });
        let (led, _) = near_light_at(&l, &x).unwrap();
        assert!((led / iso - theta.cos().powi(3)).abs() < 1e-12);
    }

    #[test]
    fn refuses_a_light_inside_the_scene() {
        let scene = Scene::sphere(32, 12.0, Albedo::Constant(0.5));
        let placement = NearPlacement {
            distance: 100.0,
            scale: 1.0,
        };
        let lights = Lights::new(vec![Light::near(
            Vector3::new(0.0, 0.0, -95.0),
            Vector3::new(0.0, 0.0, -100.0),
        )])
        .unwrap();
        let e = render_near(
            &scene,
            &lights,
            &placement.camera(&scene),
            &placement,
            &RenderOptions::default(),
        )
        .unwrap_err();
        assert!(e.to_string().contains("above the scene"), "{e}");
    }
}
