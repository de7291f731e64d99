//! Near-light scenes with ground truth: the near model ([`crate::ps::near`]) beside the distant
//! approximation on the same rendered images, as the light distance changes.
//!
//! A case places a [`SceneKind`] of `size`² scene pixels of a given material (1 camera unit each, so the object is
//! `size` units across) under two rings of LEDs, half at 25° and half at 45° from the optical
//! axis as seen from the scene's centre, all at `light_distance` object sizes from it, and the
//! camera at the same distance (a rig whose LEDs sit around the lens), with the pinhole camera
//! that sees the base plane at one pixel per scene pixel ([`NearPlacement::camera`]). The
//! distant approximation is what a user without the near model gets: the lights' directions
//! from the scene's centre, their intensities as given, the default solve, and depth from the
//! same perspective integration with its unknown scale fitted to the truth (which flatters it).

use crate::capture::stack::ColorMode;
use crate::error::{Error, Result};
use crate::eval::metrics::angular_errors;
use crate::grid::{Mask, NormalMap, ScalarMap};
use crate::integrate::{IntegrationOptions, integrate_normals};
use crate::progress::Silent;
use crate::ps::near::{NearOptions, NearSolve, solve_near};
use crate::ps::normals::albedo_and_normals;
use crate::ps::solve::{SolveOptions, solve};
use crate::synth::near::{NearPlacement, render_near, two_ring_rig};
use crate::synth::reflectance::Material;
use crate::synth::render::RenderOptions;
use crate::synth::scene::{Albedo, SceneKind};
use nalgebra::Vector3;
use serde::Serialize;
use std::time::Instant;

/// One rendered near-light case.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NearCase {
    /// The scene.
    pub kind: SceneKind,
    /// Image side in pixels (the object is this many camera units across).
    pub size: usize,
    /// Distance of every light (and of the camera) from the scene's centre, in object sizes.
    pub light_distance: f64,
    /// Number of lights (half on each ring).
    pub lights: usize,
    /// Read noise σ relative to the mean image level (0 for none).
    pub noise: f32,
    /// LED profile exponent μ (0: isotropic), each LED pointing at the scene's centre.
    pub mu: f64,
    /// The surface's material (albedo 0.8).
    pub material: Material,
}

/// The near model's and the distant approximation's errors on a [`NearCase`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NearResult {
    /// Mean angular error of the near model's normals, degrees.
    pub near_normal_deg: f64,
    /// RMS depth error of the near model (absolute depth), as a fraction of the true depth's
    /// range over the mask.
    pub near_depth: f64,
    /// Mean angular error of the distant approximation's normals, degrees.
    pub distant_normal_deg: f64,
    /// RMS depth error of the distant approximation after its scale is fitted to the truth
    /// (least squares), as a fraction of the range.
    pub distant_depth: f64,
    /// Alternations of the near solve.
    pub iterations: usize,
    /// Whether the near solve converged.
    pub converged: bool,
    /// Wall time of the near solve (normals, integration, scale), seconds.
    pub near_seconds: f64,
    /// Wall time of the distant solve and its integration, seconds.
    pub distant_seconds: f64,
}

/// Renders `case` and solves it with the near model (`options`) and the distant approximation.
///
/// # Errors
/// [`Error::InvalidParameter`] for a size under 16 pixels, fewer than 4 lights or a light
/// distance under 1 object size; the errors of the renderer and the solvers.
pub fn run_case(case: &NearCase, options: &NearOptions) -> Result<NearResult> {
    if case.size < 16
        || case.lights < 4
        || case.light_distance.is_nan()
        || case.light_distance < 1.0
    {
        return Err(Error::param(
            "case",
            format!(
                "size {} (≥ 16), lights {} (≥ 4), light distance {} object sizes (≥ 1)",
                case.size, case.lights, case.light_distance
            ),
        ));
    }
    let scene = case
        .kind
        .build(case.size, Albedo::Constant(0.8), case.material);
    let reach = case.light_distance * case.size as f64;
    let placement = NearPlacement {
        distance: reach,
        scale: 1.0,
    };
    let camera = placement.camera(&scene);
    let target = Vector3::new(0.0, 0.0, -reach);
    let lights = two_ring_rig(case.lights, reach, target, case.mu)?;
    let clean = render_near(
        &scene,
        &lights,
        &camera,
        &placement,
        &RenderOptions::default(),
    )?;
    let render = if case.noise > 0.0 {
        let level = mean_level(&clean.images.iter().map(|p| &p[0]).collect::<Vec<_>>());
        render_near(
            &scene,
            &lights,
            &camera,
            &placement,
            &RenderOptions {
                noise_sigma: case.noise * level,
                seed: 7,
                ..RenderOptions::default()
            },
        )?
    } else {
        clean
    };
    let stack = render.to_stack(&lights, ColorMode::Grey)?;
    let truth = &render.truth;
    let mask = &truth.mask;

    let t = Instant::now();
    let near = solve_near(&stack, 0, &lights, mask, &camera, options, &Silent)?;
    let near_seconds = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let distant = solve(&stack, 0, &lights, mask, &SolveOptions::default(), &Silent)?;
    let distant_normals = albedo_and_normals(&distant).1;
    let integration = integrate_normals(
        &distant_normals,
        mask,
        &IntegrationOptions {
            camera: Some(camera),
            ..options.integration
        },
        &Silent,
    )?;
    let distant_seconds = t.elapsed().as_secs_f64();

    let near_normal_deg = angular_errors(&near_normals(&near), &truth.normals, mask)?.mean_deg;
    let distant_normal_deg = angular_errors(&distant_normals, &truth.normals, mask)?.mean_deg;
    Ok(NearResult {
        near_normal_deg,
        near_depth: depth_error(&near.depth, &truth.depth, mask, false),
        distant_normal_deg,
        distant_depth: depth_error(&integration.depth, &truth.depth, mask, true),
        iterations: near.steps.len(),
        converged: near.converged,
        near_seconds,
        distant_seconds,
    })
}

/// The near solve's unit normals.
pub fn near_normals(near: &NearSolve) -> NormalMap {
    albedo_and_normals(&near.solution).1
}

fn mean_level(planes: &[&ScalarMap]) -> f32 {
    let (mut s, mut n) = (0.0f64, 0usize);
    for p in planes {
        for v in p.data() {
            if *v > 0.0 {
                s += f64::from(*v);
                n += 1;
            }
        }
    }
    if n == 0 { 0.0 } else { (s / n as f64) as f32 }
}

/// RMS of `est − truth` over the mask pixels where both are finite, over the range of the truth
/// there; with `fit_scale`, `est` is first multiplied by its least-squares scale.
pub fn depth_error(est: &ScalarMap, truth: &ScalarMap, mask: &Mask, fit_scale: bool) -> f64 {
    let pairs: Vec<(f64, f64)> = (0..mask.len())
        .filter(|&p| mask.data()[p])
        .map(|p| (f64::from(est.data()[p]), f64::from(truth.data()[p])))
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .collect();
    if pairs.is_empty() {
        return f64::NAN;
    }
    let s = if fit_scale {
        let (ab, aa) = pairs
            .iter()
            .fold((0.0, 0.0), |(ab, aa), (a, b)| (ab + a * b, aa + a * a));
        ab / aa
    } else {
        1.0
    };
    let (lo, hi) = pairs
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), (_, b)| {
            (lo.min(*b), hi.max(*b))
        });
    let rms =
        (pairs.iter().map(|(a, b)| (s * a - b).powi(2)).sum::<f64>() / pairs.len() as f64).sqrt();
    rms / (hi - lo).max(1e-30)
}

/// Light distances of [`sweep`] by default, in object sizes.
pub const DEFAULT_DISTANCES: [f64; 10] = [1.5, 2.0, 3.0, 5.0, 7.0, 10.0, 15.0, 25.0, 50.0, 100.0];
/// Scenes of [`sweep`].
pub const SWEEP_SCENES: [SceneKind; 3] = [SceneKind::Sphere, SceneKind::Vase, SceneKind::Bumps];

/// What [`sweep`] runs: every scene of [`SWEEP_SCENES`] at every distance, with these settings.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NearSweepOptions {
    /// Image side in pixels.
    pub size: usize,
    /// Number of LEDs.
    pub lights: usize,
    /// Read noise relative to the mean image level.
    pub noise: f32,
    /// LED profile exponent.
    pub mu: f64,
    /// Light distances, in object sizes.
    pub distances: Vec<f64>,
}

impl Default for NearSweepOptions {
    fn default() -> Self {
        NearSweepOptions {
            size: 128,
            lights: 16,
            noise: 0.01,
            mu: 1.0,
            distances: DEFAULT_DISTANCES.to_vec(),
        }
    }
}

/// One row of [`sweep`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NearRow {
    /// Scene name.
    pub scene: &'static str,
    /// Light distance, object sizes.
    pub distance: f64,
    /// Both models' errors and times.
    #[serde(flatten)]
    pub result: NearResult,
}

/// The rows of [`sweep`] and, per scene, the nearest distance from which the distant
/// approximation's mean normal error stays under 1°.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NearReport {
    /// What was run.
    pub options: NearSweepOptions,
    /// One row per scene and distance.
    pub rows: Vec<NearRow>,
    /// Per scene: the smallest distance of the sweep at and beyond which the distant model is
    /// within 1° (`None` when it never is).
    pub distant_within_1deg: Vec<(&'static str, Option<f64>)>,
}

/// The near model ([`NearOptions::default`]) beside the distant approximation on every scene of
/// [`SWEEP_SCENES`] at every light distance of `options`.
///
/// # Errors
/// As [`run_case`].
pub fn sweep(options: &NearSweepOptions) -> Result<NearReport> {
    let mut rows = Vec::new();
    for kind in SWEEP_SCENES {
        for &distance in &options.distances {
            let case = NearCase {
                kind,
                size: options.size,
                light_distance: distance,
                lights: options.lights,
                noise: options.noise,
                mu: options.mu,
                material: Material::lambertian(),
            };
            rows.push(NearRow {
                scene: kind.name(),
                distance,
                result: run_case(&case, &NearOptions::default())?,
            });
        }
    }
    let distant_within_1deg = SWEEP_SCENES
        .iter()
        .map(|k| {
            let mut own: Vec<&NearRow> = rows.iter().filter(|r| r.scene == k.name()).collect();
            own.sort_by(|a, b| a.distance.total_cmp(&b.distance));
            // The first distance from which every farther one is within 1°.
            let mut from = None;
            for r in own.iter().rev() {
                if r.result.distant_normal_deg <= 1.0 {
                    from = Some(r.distance);
                } else {
                    break;
                }
            }
            (k.name(), from)
        })
        .collect();
    Ok(NearReport {
        options: options.clone(),
        rows,
        distant_within_1deg,
    })
}
