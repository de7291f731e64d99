//! Each estimator's error against specular strength (`bench specularity`):
//! [`Scene::sphere_on_ground`] (attached and cast shadows) rendered with a Blinn–Phong
//! (n = 50) and a Torrance–Sparrow (m = 0.2) lobe of strength k_s and Gaussian noise, under one
//! Fibonacci light set; the mean, median and 95th-percentile angular error of each estimator.

use crate::capture::dataset::Capture;
use crate::capture::lights::Lights;
use crate::capture::stack::ColorMode;
use crate::error::{Error, Result};
use crate::ps::solve::{Method, SolveOptions};
use crate::run::pipeline::Config;
use crate::synth::reflectance::{BlinnPhong, Material, Specular, TorranceSparrow};
use crate::synth::render::{RenderOptions, render};
use crate::synth::scene::Scene;
use serde::Serialize;

/// Image size (square) by default.
pub const DEFAULT_SIZE: usize = 128;
/// Number of lights by default.
pub const DEFAULT_LIGHTS: usize = 32;
/// Specular strengths k_s swept by default.
pub const DEFAULT_KS: [f64; 6] = [0.0, 0.05, 0.1, 0.2, 0.4, 0.8];
/// Gaussian image noise σ by default (images peak near 1).
pub const DEFAULT_NOISE: f32 = 0.005;
/// Lowest light elevation of the Fibonacci light set, degrees above the horizon (so the lights
/// are at most 60° from the view direction).
pub const MIN_ELEVATION_DEG: f64 = 30.0;
/// Seed of the image noise.
pub const SEED: u64 = 7;
/// The name of the rendered scene in the report.
pub const SCENE: &str = "sphere_on_ground";

/// A specular lobe family: its name in the rows and the lobe of strength k_s.
#[derive(Debug, Clone, Copy)]
pub struct Lobe {
    /// Name in the rows, with its shape parameter.
    pub name: &'static str,
    /// The lobe of strength k_s.
    pub specular: fn(f64) -> Specular,
}

/// The lobes swept, in the order of the rows: Blinn–Phong n = 50, Torrance–Sparrow m = 0.2
/// (Fresnel off, F0 = 1).
pub const LOBES: [Lobe; 2] = [
    Lobe {
        name: "blinn-phong n=50",
        specular: |ks| Specular::BlinnPhong(BlinnPhong { ks, exponent: 50.0 }),
    },
    Lobe {
        name: "torrance-sparrow m=0.2",
        specular: |ks| {
            Specular::TorranceSparrow(TorranceSparrow {
                ks,
                roughness: 0.2,
                f0: 1.0,
            })
        },
    },
];

/// What to sweep.
#[derive(Debug, Clone, PartialEq)]
pub struct SpecularityOptions {
    /// Image size (square), at least 16.
    pub size: usize,
    /// Number of lights, at least 3.
    pub lights: usize,
    /// Specular strengths k_s, in the order of the rows.
    pub ks: Vec<f64>,
    /// Gaussian image noise σ.
    pub noise: f32,
    /// The estimators' [`SolveOptions::highlight_fraction`].
    pub highlight_fraction: f32,
    /// Estimators, in the order of the rows.
    pub methods: Vec<Method>,
}

impl Default for SpecularityOptions {
    fn default() -> Self {
        SpecularityOptions {
            size: DEFAULT_SIZE,
            lights: DEFAULT_LIGHTS,
            ks: DEFAULT_KS.to_vec(),
            noise: DEFAULT_NOISE,
            highlight_fraction: crate::ps::solve::DEFAULT_HIGHLIGHT_FRACTION,
            methods: Method::ALL.to_vec(),
        }
    }
}

impl SpecularityOptions {
    /// Checks the size and the light count (the materials are checked as they are made).
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] naming the first bad one.
    pub fn validate(&self) -> Result<()> {
        if self.size < 16 {
            return Err(Error::param("size", format!("{} is below 16", self.size)));
        }
        if self.lights < 3 {
            return Err(Error::param(
                "lights",
                format!("{}: photometric stereo needs at least 3", self.lights),
            ));
        }
        Ok(())
    }
}

/// One estimator under one lobe and strength.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SpecularityRow {
    /// The lobe's name ([`Lobe::name`]).
    pub lobe: &'static str,
    /// Specular strength k_s.
    pub ks: f64,
    /// Estimator name.
    pub method: &'static str,
    /// Mean angular error, degrees.
    pub mean_deg: f64,
    /// Median angular error, degrees.
    pub median_deg: f64,
    /// 95th percentile, degrees.
    pub p95_deg: f64,
    /// Pixels of the mask left without a normal.
    pub unsolved: usize,
    /// Fraction of the solved pixels that needed the robust path.
    pub robust_fraction: f64,
    /// Wall time of the reconstruction (solve and normals), seconds.
    pub seconds: f64,
}

/// The sweep and its rows.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SpecularityReport {
    /// The scene's name ([`SCENE`]).
    pub scene: &'static str,
    /// Image size (square).
    pub size: usize,
    /// Number of lights.
    pub lights: usize,
    /// Gaussian image noise σ.
    pub noise_sigma: f32,
    /// Lobes outer, strengths, then estimators inner: `methods.len()` rows per (lobe, k_s).
    pub rows: Vec<SpecularityRow>,
}

/// Renders the scene for each lobe of [`LOBES`] and strength of `options.ks` (Lambertian at
/// k_s = 0) and solves it with each estimator.
///
/// # Errors
/// [`Error::InvalidParameter`] for bad options or materials; any error of rendering or
/// solving.
pub fn specularity(options: &SpecularityOptions) -> Result<SpecularityReport> {
    options.validate()?;
    let lights = Lights::fibonacci(options.lights, MIN_ELEVATION_DEG)?;
    let mut rows = Vec::new();
    for lobe in LOBES {
        for &ks in &options.ks {
            let material = if ks > 0.0 {
                Material::with_specular((lobe.specular)(ks))
            } else {
                Material::lambertian()
            };
            material.validate()?;
            let scene = Scene::sphere_on_ground(options.size, material);
            let render_options = RenderOptions {
                noise_sigma: options.noise,
                seed: SEED,
                ..RenderOptions::default()
            };
            let rendering = render(&scene, &lights, &render_options)?;
            let stack = rendering.to_stack(&lights, ColorMode::Grey)?;
            let capture =
                Capture::from_stack(stack, lights.clone(), Some(rendering.truth.mask.clone()))?;
            for &m in &options.methods {
                let config = Config {
                    solve: SolveOptions {
                        highlight_fraction: options.highlight_fraction,
                        ..SolveOptions::with_method(m)
                    },
                    integration: None,
                    ..Config::default()
                };
                let (recon, e, seconds) =
                    super::timed_normal_errors(&capture, &config, &rendering.truth.normals)?;
                rows.push(SpecularityRow {
                    lobe: lobe.name,
                    ks,
                    method: m.name(),
                    mean_deg: e.mean_deg,
                    median_deg: e.median_deg,
                    p95_deg: e.p95_deg,
                    unsolved: e.missing,
                    robust_fraction: recon.model.robust_fraction,
                    seconds,
                });
            }
        }
    }
    Ok(SpecularityReport {
        scene: SCENE,
        size: options.size,
        lights: options.lights,
        noise_sigma: options.noise,
        rows,
    })
}
