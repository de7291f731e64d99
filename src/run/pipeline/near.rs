//! The near-light run: when every light has a position and the camera's intrinsics are given,
//! normals and absolute depth are estimated together ([`crate::ps::near`]), and the report says
//! how far the distant-light approximation would have moved the normals.

use super::*;
use crate::ps::near::{DEFAULT_MAX_ITERATIONS, DEFAULT_TOLERANCE, NearOptions, solve_near};

/// How a capture with positioned lights is solved ([`Config::near`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NearConfig {
    /// Depth of the alternation's start plane along the optical axis, in the units of the light
    /// positions; `None`: searched from the images around the lights' mean distance.
    pub start_distance: Option<f64>,
    /// Largest number of alternations.
    pub max_iterations: usize,
    /// Convergence threshold: RMS depth change over the depth range.
    pub tolerance: f64,
}

impl Default for NearConfig {
    fn default() -> Self {
        NearConfig {
            start_distance: None,
            max_iterations: DEFAULT_MAX_ITERATIONS,
            tolerance: DEFAULT_TOLERANCE,
        }
    }
}

/// What the near-light solve did (`report.json`'s `near` section).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NearSummary {
    /// Alternations of normals and depth.
    pub iterations: usize,
    /// Whether the depth change fell below the tolerance before the iteration cap.
    pub converged: bool,
    /// Depth of the start plane (camera units).
    pub start_distance: f64,
    /// Geometric-mean depth of the largest part (camera units).
    pub distance: f64,
    /// The last alternation's RMS depth change over the depth range.
    pub depth_change: f64,
    /// Relative residual of the last scale fit.
    pub residual: f64,
    /// Mean angle between these normals and those of the distant-light approximation (each
    /// light's `direction`, its intensity as given, the same estimator without specular lobes
    /// or shadow labels), degrees, over the pixels both solved; NaN when that solve failed.
    pub distant_deviation_deg: f64,
    /// 95th percentile of that angle, degrees.
    pub distant_deviation_p95_deg: f64,
}

/// Whether `config` solves a capture lit by `lights` with the near model: every light has a
/// position, a pinhole camera is given, and the near model is not turned off.
pub fn near_applies(lights: &crate::capture::lights::Lights, config: &Config) -> bool {
    config.near.is_some()
        && lights.positioned() == lights.len()
        && !lights.is_empty()
        && config.integration.is_some_and(|i| i.camera.is_some())
}

/// The near-light reconstruction of `capture` (see [`near_applies`]), depth included (absolute,
/// along the optical axis, in the units of the light positions). An RGB capture is solved on
/// its grey mix.
pub(super) fn reconstruct_near(
    capture: &Capture,
    solve_config: &Config,
    config: &Config,
    facts: &InputFacts<'_>,
    progress: &dyn Progress,
) -> Result<Reconstruction> {
    let (Some(near), Some(integration)) = (config.near, config.integration) else {
        return Err(Error::param(
            "near",
            "the near-light model needs its options and the camera's intrinsics",
        ));
    };
    if config.interreflections.is_some() {
        return Err(Error::param(
            "interreflections",
            "interreflection compensation assumes distant lights; it is not available with positioned lights solved as near ones",
        ));
    }
    let Some(camera) = integration.camera else {
        return Err(Error::param(
            "camera",
            "near-light photometric stereo needs the camera's intrinsics",
        ));
    };
    let t = Instant::now();
    let grey;
    let stack = if capture.stack.channels() == 1 {
        &capture.stack
    } else {
        grey = capture.stack.grey_mix();
        &grey
    };
    let options = NearOptions {
        solve: solve_config.solve,
        integration,
        start_distance: near.start_distance,
        max_iterations: near.max_iterations,
        tolerance: near.tolerance,
    };
    let solved = solve_near(
        stack,
        0,
        &capture.lights,
        &capture.mask,
        &camera,
        &options,
        progress,
    )?;
    // The distant approximation on the same images, for the report (the same estimator without
    // the refits it would add; a failure only leaves the comparison out).
    let distant = crate::ps::solve::solve(
        stack,
        0,
        &capture.lights,
        &capture.mask,
        &SolveOptions {
            lobes: false,
            shadow_labels: None,
            ..solve_config.solve
        },
        &crate::progress::Silent,
    );
    let deviation = match &distant {
        Ok(d) => deviation(&solved.solution.g, &d.g),
        Err(_) => (f64::NAN, f64::NAN),
    };
    let last = solved.steps.last().copied();
    let summary = NearSummary {
        iterations: solved.steps.len(),
        converged: solved.converged,
        start_distance: solved.start_distance,
        distance: last.map_or(f64::NAN, |s| s.distance),
        depth_change: last.map_or(f64::NAN, |s| s.depth_change),
        residual: last.map_or(f64::NAN, |s| s.residual),
        distant_deviation_deg: deviation.0,
        distant_deviation_p95_deg: deviation.1,
    };
    let solve_s = t.elapsed().as_secs_f64();
    let facts = InputFacts {
        positioned: 0,
        ..facts.clone()
    };
    // What the near solve ran: no intensity correction, no lobes, no shadow labels.
    let ran = Config {
        solve: SolveOptions {
            recalibrate: Some(false),
            lobes: false,
            shadow_labels: None,
            ..config.solve
        },
        ..*config
    };
    let mut recon = assemble(vec![solved.solution], solve_s, &facts, &ran);
    recon
        .warnings
        .retain(|w| !matches!(w, Warning::NearLights { .. }));
    if !summary.converged {
        recon.warnings.push(Warning::NearNotConverged {
            iterations: summary.iterations,
            change: summary.depth_change,
        });
    }
    recon.integration = Some(Integration {
        depth: solved.depth,
        ..solved.integration
    });
    recon.near = Some(summary);
    Ok(recon)
}

/// Mean and 95th percentile of the angle between the directions of `a` and `b` (degrees) over
/// the pixels where both are finite and non-zero.
fn deviation(a: &Grid<nalgebra::Vector3<f32>>, b: &Grid<nalgebra::Vector3<f32>>) -> (f64, f64) {
    let mut angles: Vec<f64> = a
        .data()
        .iter()
        .zip(b.data())
        .filter_map(|(x, y)| {
            let (x, y) = (x.cast::<f64>(), y.cast::<f64>());
            let c = x.dot(&y) / (x.norm() * y.norm());
            c.is_finite()
                .then(|| c.clamp(-1.0, 1.0).acos().to_degrees())
        })
        .collect();
    if angles.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let mean = angles.iter().sum::<f64>() / angles.len() as f64;
    angles.sort_by(f64::total_cmp);
    let p95 = angles[((angles.len() - 1) as f64 * 0.95).round() as usize];
    (mean, p95)
}
