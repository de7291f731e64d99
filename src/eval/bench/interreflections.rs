//! Interreflection compensation on rendered concave scenes (`bench interreflections`): a
//! V-groove, a bowl and a relief of dimples and bumps (and a sphere, convex, as the control)
//! rendered with diffuse interreflections and cast shadows, solved without compensation, with
//! the reflectance scale known and with it estimated from the data
//! ([`crate::ps::interreflection`]); and, for reference, the same scene rendered without
//! interreflections (the error that is left from other causes).

use crate::capture::dataset::Capture;
use crate::capture::lights::Lights;
use crate::capture::stack::ColorMode;
use crate::error::{Error, Result};
use crate::ps::interreflection::InterreflectionOptions;
use crate::run::pipeline::Config;
use crate::synth::reflectance::Material;
use crate::synth::render::{RenderOptions, render};
use crate::synth::scene::{Albedo, SceneKind};
use serde::Serialize;

/// Image size (square) by default.
pub const DEFAULT_SIZE: usize = 96;
/// Number of lights by default.
pub const DEFAULT_LIGHTS: usize = 32;
/// The surface's albedo by default (the reflectance: the renderer's images are radiometric, so
/// the true scale is 1).
pub const DEFAULT_ALBEDO: f64 = 0.7;
/// Bounces rendered.
pub const BOUNCES: usize = 4;
/// Rays per pixel of the renderer's gather.
pub const RENDER_RAYS: usize = 128;
/// Gaussian image noise σ (images peak near 1).
pub const NOISE: f32 = 0.005;
/// Lowest light elevation, degrees above the horizon.
pub const MIN_ELEVATION_DEG: f64 = 30.0;
/// Seed of the noise and the renderer's rays.
pub const SEED: u64 = 11;
/// The scenes, concave ones first and the convex control last.
pub const SCENES: [SceneKind; 4] = [
    SceneKind::Groove,
    SceneKind::Bowl,
    SceneKind::Relief,
    SceneKind::Sphere,
];

/// What to run.
#[derive(Debug, Clone, PartialEq)]
pub struct InterreflectionBenchOptions {
    /// Image size (square), at least 32.
    pub size: usize,
    /// Number of lights, at least 3.
    pub lights: usize,
    /// The surfaces' albedo, in (0, 1].
    pub albedo: f64,
}

impl Default for InterreflectionBenchOptions {
    fn default() -> Self {
        InterreflectionBenchOptions {
            size: DEFAULT_SIZE,
            lights: DEFAULT_LIGHTS,
            albedo: DEFAULT_ALBEDO,
        }
    }
}

/// One scene solved one way.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct InterreflectionRow {
    /// Scene name.
    pub scene: &'static str,
    /// `no bounces` (rendered without interreflections, solved as is), `uncompensated`,
    /// `scale known`, `scale estimated`.
    pub step: &'static str,
    /// Mean angular error, degrees.
    pub mean_deg: f64,
    /// Median angular error, degrees.
    pub median_deg: f64,
    /// 95th percentile, degrees.
    pub p95_deg: f64,
    /// The brightest reflectance the compensation used (0 when it applied none).
    pub reflectance: f64,
    /// Mean fraction of the hemisphere filled by the surface, on the final round's shape.
    pub occlusion: f64,
    /// Wall time of the reconstruction, seconds.
    pub seconds: f64,
}

/// The rows of the benchmark.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct InterreflectionReport {
    /// Image size (square).
    pub size: usize,
    /// Number of lights.
    pub lights: usize,
    /// The surfaces' albedo (= the true reflectance scale × the brightest albedo).
    pub albedo: f64,
    /// Four rows per scene, in the order of [`SCENES`].
    pub rows: Vec<InterreflectionRow>,
}

/// Renders and solves every scene of [`SCENES`] each way.
///
/// # Errors
/// [`Error::InvalidParameter`] for bad options; any error of rendering or solving.
pub fn interreflections(options: &InterreflectionBenchOptions) -> Result<InterreflectionReport> {
    if options.size < 32 {
        return Err(Error::param(
            "size",
            format!("{} is below 32", options.size),
        ));
    }
    if options.lights < 3 {
        return Err(Error::param(
            "lights",
            format!("{} is below 3", options.lights),
        ));
    }
    if !(options.albedo > 0.0 && options.albedo <= 1.0) {
        return Err(Error::param(
            "albedo",
            format!("{} is outside (0, 1]", options.albedo),
        ));
    }
    let lights = Lights::fibonacci(options.lights, MIN_ELEVATION_DEG)?;
    let mut rows = Vec::new();
    for kind in SCENES {
        let scene = kind.build(
            options.size,
            Albedo::Constant(options.albedo as f32),
            Material::lambertian(),
        );
        for bounces in [0, BOUNCES] {
            let render_options = RenderOptions {
                noise_sigma: NOISE,
                seed: SEED,
                bounces,
                bounce_samples: RENDER_RAYS,
                ..RenderOptions::default()
            };
            let rendering = render(&scene, &lights, &render_options)?;
            let stack = rendering.to_stack(&lights, ColorMode::Grey)?;
            let capture =
                Capture::from_stack(stack, lights.clone(), Some(rendering.truth.mask.clone()))?;
            let steps: &[(&'static str, Option<InterreflectionOptions>)] = if bounces == 0 {
                &[("no bounces", None)]
            } else {
                &[
                    ("uncompensated", None),
                    (
                        "scale known",
                        Some(InterreflectionOptions {
                            scale: Some(1.0),
                            ..InterreflectionOptions::default()
                        }),
                    ),
                    ("scale estimated", Some(InterreflectionOptions::default())),
                ]
            };
            for &(step, ir) in steps {
                let config = Config {
                    interreflections: ir,
                    ..Config::default()
                };
                let (recon, e, seconds) =
                    super::timed_normal_errors(&capture, &config, &rendering.truth.normals)?;
                let rounds = recon.interreflections.as_ref().map(|s| s.rounds.as_slice());
                let last = rounds.and_then(|r| r.last());
                let applied = rounds.and_then(|r| r.iter().rev().find(|r| r.scale.scale > 0.0));
                rows.push(InterreflectionRow {
                    scene: kind.name(),
                    step,
                    mean_deg: e.mean_deg,
                    median_deg: e.median_deg,
                    p95_deg: e.p95_deg,
                    reflectance: applied.map_or(0.0, |r| r.scale.bright_reflectance),
                    occlusion: last.map_or(0.0, |r| r.mean_occlusion),
                    seconds,
                });
            }
        }
    }
    Ok(InterreflectionReport {
        size: options.size,
        lights: options.lights,
        albedo: options.albedo,
        rows,
    })
}
