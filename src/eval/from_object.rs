//! How lights recovered from the object ([`crate::calibrate::from_object`]) hold up as the
//! number of lights and the noise change: rendered scenes with two albedos (a checkerboard of
//! 0.9 and 0.45 in squares of 16 pixels) under Fibonacci light sets (no light below 35° of
//! elevation), each recovery's mean light error, and the default pipeline's normal error under
//! the recovered lights beside the true ones.

use crate::calibrate::from_object::{FromObjectOptions, lights_from_stack};
use crate::capture::dataset::Capture;
use crate::capture::lights::Lights;
use crate::capture::stack::ColorMode;
use crate::error::Result;
use crate::eval::metrics::angular_errors;
use crate::progress::Silent;
use crate::run::pipeline::{Config, reconstruct};
use crate::synth::reflectance::Material;
use crate::synth::render::{RenderOptions, render};
use crate::synth::scene::{Albedo, SceneKind};
use nalgebra::Vector3;
use serde::Serialize;
use std::time::Instant;

/// Light counts swept by default.
pub const DEFAULT_COUNTS: [usize; 5] = [6, 8, 12, 20, 32];
/// Noise levels (read noise relative to the mean image level) swept by default.
pub const DEFAULT_NOISES: [f32; 4] = [0.0, 0.005, 0.01, 0.02];
/// Scenes swept.
pub const SWEEP_SCENES: [SceneKind; 2] = [SceneKind::Sphere, SceneKind::Vase];
/// Lowest light elevation (degrees) of the light sets.
pub const MIN_ELEVATION_DEG: f64 = 35.0;

/// What to sweep.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FromObjectSweepOptions {
    /// Image size (square).
    pub size: usize,
    /// Light counts.
    pub counts: Vec<usize>,
    /// Noise levels.
    pub noises: Vec<f32>,
}

impl Default for FromObjectSweepOptions {
    fn default() -> Self {
        FromObjectSweepOptions {
            size: 128,
            counts: DEFAULT_COUNTS.to_vec(),
            noises: DEFAULT_NOISES.to_vec(),
        }
    }
}

/// One scene, light count and noise level.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FromObjectRow {
    /// Scene name.
    pub scene: &'static str,
    /// Number of lights.
    pub lights: usize,
    /// Noise level.
    pub noise: f32,
    /// Mean angle between recovered and true light directions (degrees); `None` when refused.
    pub light_deg: Option<f64>,
    /// Largest such angle.
    pub light_max_deg: Option<f64>,
    /// Mean normal error of the default pipeline under the recovered lights.
    pub normals_deg: Option<f64>,
    /// The same under the true lights.
    pub calibrated_deg: f64,
    /// Mean split-half spread the recovery reported (degrees).
    pub reported_deg: Option<f64>,
    /// Why the recovery was refused.
    pub refused: Option<String>,
    /// Seconds of the recovery.
    pub seconds: f64,
}

/// The sweep.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FromObjectReport {
    /// What was swept.
    pub options: FromObjectSweepOptions,
    /// Scenes outer, counts, then noises inner.
    pub rows: Vec<FromObjectRow>,
}

/// Mean normal error of the default pipeline (no integration) on `stack` under `lights`.
fn pipeline_error(
    stack: crate::capture::stack::ImageStack,
    lights: Lights,
    truth: &crate::synth::scene::HeightField,
) -> Result<f64> {
    let capture = Capture::from_stack(stack, lights, Some(truth.mask.clone()))?;
    let config = Config {
        integration: None,
        ..Config::default()
    };
    let recon = reconstruct(&capture, &config, &Silent)?;
    Ok(angular_errors(&recon.maps.normals, &truth.normals, &truth.mask)?.mean_deg)
}

/// Runs the sweep.
///
/// # Errors
/// Rendering and pipeline errors (a refused recovery is a row, not an error).
pub fn sweep(options: &FromObjectSweepOptions) -> Result<FromObjectReport> {
    let albedo = Albedo::Checker {
        size: 16.0,
        a: 0.9,
        b: 0.45,
    };
    let mut rows = Vec::new();
    for kind in SWEEP_SCENES {
        let scene = kind.build(options.size, albedo, Material::lambertian());
        for &count in &options.counts {
            let lights = Lights::fibonacci(count, MIN_ELEVATION_DEG)?;
            for &noise in &options.noises {
                let render_options = RenderOptions {
                    noise_sigma: noise,
                    seed: 11 + count as u64,
                    ..RenderOptions::default()
                };
                let r = render(&scene, &lights, &render_options)?;
                let stack = r.to_stack(&lights, ColorMode::Grey)?;
                let calibrated_deg = pipeline_error(stack.clone(), lights.clone(), &r.truth)?;
                let start = Instant::now();
                let got = lights_from_stack(&stack, &r.truth.mask, &FromObjectOptions::default());
                let seconds = start.elapsed().as_secs_f64();
                let row = match got {
                    Ok(got) => {
                        let e: Vec<f64> = got
                            .directions
                            .iter()
                            .zip(lights.directions())
                            .map(|(d, t)| Vector3::from(*d).angle(&t).to_degrees())
                            .collect();
                        let recovered = got.lights()?;
                        let divided = r.to_stack(&recovered, ColorMode::Grey)?;
                        let normals = pipeline_error(divided, recovered, &r.truth).ok();
                        let spread = got.uncertainty_deg.iter().sum::<f64>() / count as f64;
                        FromObjectRow {
                            scene: kind.name(),
                            lights: count,
                            noise,
                            light_deg: Some(e.iter().sum::<f64>() / count as f64),
                            light_max_deg: Some(e.iter().cloned().fold(0.0, f64::max)),
                            normals_deg: normals,
                            calibrated_deg,
                            reported_deg: Some(spread),
                            refused: None,
                            seconds,
                        }
                    }
                    Err(e) => FromObjectRow {
                        scene: kind.name(),
                        lights: count,
                        noise,
                        light_deg: None,
                        light_max_deg: None,
                        normals_deg: None,
                        calibrated_deg,
                        reported_deg: None,
                        refused: Some(e.to_string()),
                        seconds,
                    },
                };
                rows.push(row);
            }
        }
    }
    Ok(FromObjectReport {
        options: options.clone(),
        rows,
    })
}
