//! The built-in default scene: render it, reconstruct it, and measure the error against its
//! ground truth.

use crate::capture::dataset::Capture;
use crate::capture::lights::Lights;
use crate::capture::stack::ColorMode;
use crate::error::Result;
use crate::eval::metrics::{
    AngularErrorStats, DepthErrorStats, albedo_relative_error, angular_errors, depth_errors,
};
use crate::grid::Mask;
use crate::run::pipeline::Reconstruction;
use crate::synth::render::{RenderOptions, Rendering, render};
use crate::synth::scene::{HeightField, Scene};
use serde::Serialize;

/// Noise level of the default scene: σ = 0.005 (about 1% of a mid-grey pixel).
pub const DEFAULT_NOISE: f32 = 0.005;

/// The default scene's twelve lights: eight on a ring 35° above the image plane and four at 65°.
pub fn demo_lights() -> Result<Lights> {
    let low = Lights::ring(8, 35.0, 0.0)?;
    let high = Lights::ring(4, 65.0, 45.0)?;
    Lights::new(low.lights().iter().chain(high.lights()).cloned().collect())
}

/// A rendered scene with its ground truth.
#[derive(Debug, Clone)]
pub struct SyntheticCapture {
    /// The scene description.
    pub scene: Scene,
    /// The true surface.
    pub truth: HeightField,
    /// The rendered images and shadow masks.
    pub rendering: Rendering,
    /// The capture to reconstruct (mask = the scene's mask).
    pub capture: Capture,
}

/// Renders `scene` under `lights` and wraps it as a capture.
///
/// # Errors
/// The errors of [`render`].
pub fn synthesize(
    scene: Scene,
    lights: Lights,
    options: &RenderOptions,
) -> Result<SyntheticCapture> {
    let rendering = render(&scene, &lights, options)?;
    let truth = rendering.truth.clone();
    let stack = rendering.to_stack(&lights, ColorMode::Grey)?;
    let capture = Capture::from_stack(stack, lights, Some(truth.mask.clone()))?;
    Ok(SyntheticCapture {
        scene,
        truth,
        rendering,
        capture,
    })
}

/// The default scene ([`Scene::default_scene`]) under [`demo_lights`] with noise σ = `noise`.
///
/// # Errors
/// [`crate::Error::InvalidParameter`] for a negative noise level.
pub fn default_capture(noise: f32, seed: u64) -> Result<SyntheticCapture> {
    synthesize(
        Scene::default_scene(),
        demo_lights()?,
        &RenderOptions {
            noise_sigma: noise,
            seed,
            ..RenderOptions::default()
        },
    )
}

/// Errors of a reconstruction against ground truth.
#[derive(Debug, Clone, Serialize)]
pub struct Evaluation {
    /// Angular error of the normals over solved pixels.
    pub normals: AngularErrorStats,
    /// Mean relative albedo error |ρ − ρ_gt|/ρ_gt.
    pub albedo_mean_relative_error: f64,
    /// Largest relative albedo error.
    pub albedo_max_relative_error: f64,
    /// Depth error after removing the mean offset, when depth was computed.
    pub depth: Option<DepthErrorStats>,
    /// Pixels of the object left without a normal.
    pub unsolved_pixels: usize,
}

/// Compares a reconstruction with the truth.
///
/// # Errors
/// [`crate::Error::DimensionMismatch`] when sizes differ; [`crate::Error::Mask`] when nothing can
/// be compared.
pub fn evaluate(recon: &Reconstruction, truth: &HeightField) -> Result<Evaluation> {
    let normals = angular_errors(&recon.maps.normals, &truth.normals, &truth.mask)?;
    let (mean, max) = albedo_relative_error(&recon.maps.albedo[0], &truth.albedo, &truth.mask)?;
    let depth = match recon.depth() {
        Some(d) => Some(depth_errors(d, &truth.depth, &truth.mask)?),
        None => None,
    };
    let solved_in_truth: Mask =
        crate::grid::Grid::from_fn(truth.mask.width(), truth.mask.height(), |x, y| {
            *truth.mask.at(x, y) && !*recon.maps.solved.at(x, y)
        });
    Ok(Evaluation {
        normals,
        albedo_mean_relative_error: mean,
        albedo_max_relative_error: max,
        depth,
        unsolved_pixels: solved_in_truth.count(),
    })
}
