//! The whole reconstruction, stage by stage: solve → normals and albedo → integrability →
//! depth, and writing the results with a JSON report.
//!
//! Each stage is also callable alone (see [`crate::ps::solve`], [`crate::ps::normals`],
//! [`crate::integrate`], [`crate::io::output`]); this module only composes them.
//!
//! The files: `maps.rs` (the per-pixel maps [`PixelMaps`], tallies, the model summary and
//! `assemble`), `outputs.rs` (file names, EXR channels and attributes, staging the maps and
//! the depth outputs), `report.rs` (`report.json`: [`Report`] and its summaries); the run
//! itself — [`Config`], [`reconstruct`], [`reconstruct_and_write`] and the finishing stage —
//! is here.

mod interreflections;
mod maps;
mod near;
mod outputs;
mod report;

pub use interreflections::{InterreflectionRound, InterreflectionSummary};
pub use near::{NearConfig, NearSummary, near_applies};

pub use maps::*;
pub use outputs::*;
pub use report::*;

use crate::capture::dataset::Capture;
use crate::capture::lights::MAX_LIGHT_CONDITION;
use crate::capture::stack::{ColorMode, ImageStack};
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, NormalMap, ScalarMap};
use crate::integrate::{Integration, IntegrationOptions, integrate_normals};
use crate::io::output::{
    ExrChannel, OutputDir, depth_preview, mask_bytes, nan_outside, normal_planes, normal_preview,
    scalar_preview,
};
use crate::progress::Progress;
use crate::ps::color::ColorSolve;
use crate::ps::interreflection::InterreflectionOptions;
use crate::ps::normals::{
    IntegrabilitySummary, albedo_and_normals, combine_channels, integrability,
};
use crate::ps::solve::{ImageModel, PixelStatus, Solution, SolveOptions, StatusCounts};
use crate::run::bands::{Assemble, WholeStack, solve_bands};
use crate::run::warnings::{Warning, warnings};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What to compute. The default: [`SolveOptions::default`] and orthographic masked
/// least-squares integration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Config {
    /// Per-pixel estimator and its parameters.
    pub solve: SolveOptions,
    /// Normal integration (method, camera, solver), or `None` to skip depth.
    pub integration: Option<IntegrationOptions>,
    /// The intensities are calibrated so that albedo is at most 1: pixels with ρ > 1 are then
    /// reported as a warning.
    pub albedo_normalised: bool,
    /// Also write the depth map as a triangle mesh, `mesh.ply`.
    pub mesh: bool,
    /// How an RGB capture's channels are solved (grey captures have one channel).
    pub color: ColorSolve,
    /// Interreflection compensation ([`crate::ps::interreflection`]), or `None` (the
    /// default) for none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub interreflections: Option<InterreflectionOptions>,
    /// How a capture whose every light has a position is solved when the camera's intrinsics
    /// are given ([`crate::ps::near`]); `None` solves it with the distant approximation (each
    /// light's `direction`).
    pub near: Option<NearConfig>,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            solve: SolveOptions::default(),
            integration: Some(IntegrationOptions::default()),
            albedo_normalised: false,
            mesh: false,
            color: ColorSolve::default(),
            interreflections: None,
            near: Some(NearConfig::default()),
        }
    }
}

/// Wall-clock time of each stage, in seconds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Timings {
    /// Reading and converting images (filled in by the caller that loaded them).
    pub load: f64,
    /// The per-pixel solve.
    pub solve: f64,
    /// Albedo, normals, gradients and the curl.
    pub normals: f64,
    /// Normal integration.
    pub integrate: f64,
    /// Writing the outputs.
    pub write: f64,
}

/// Everything a reconstruction produced.
#[derive(Debug, Clone)]
pub struct Reconstruction {
    /// The per-pixel maps: normals, albedo, residual, samples, condition, status, solved and
    /// robust flags.
    pub maps: PixelMaps,
    /// Curl of the gradient field.
    pub curl: ScalarMap,
    /// Summary of |curl|.
    pub integrability: IntegrabilitySummary,
    /// Depth and its integration diagnostics, when integration was asked for.
    pub integration: Option<Integration>,
    /// Pixel outcome counts.
    pub counts: StatusCounts,
    /// Pixels with albedo above 1 (any channel).
    pub albedo_above_one: usize,
    /// How much model the data needed: robust pixels, intensity corrections, noise.
    pub model: ModelSummary,
    /// Stage timings.
    pub timings: Timings,
    /// Things the user should know (saturation, flagged pixels, …).
    pub warnings: Vec<Warning>,
    /// What interreflection compensation did, when it was asked for.
    pub interreflections: Option<InterreflectionSummary>,
    /// What the near-light solve did, when it ran (depth is then absolute).
    pub near: Option<NearSummary>,
}

impl Reconstruction {
    /// The depth map, when integration ran (see [`Integration::depth`] for its units).
    pub fn depth(&self) -> Option<&ScalarMap> {
        self.integration.as_ref().map(|i| &i.depth)
    }
}

/// Gains further than this from 1 are reported as a likely error in the intensity file.
pub const GAIN_WARNING: f32 = 0.1;
/// Median |curl| per pixel (of the gradient field, see [`crate::ps::normals::integrability`])
/// above which the run warns of poor integrability. Measured on the demo scene: 0.005 without
/// noise, 0.028 at noise σ = 0.03 (3° mean normal error), 0.085 at σ = 0.1 (9°); DiLiGenT cat
/// 0.010.
pub const POOR_CURL: f64 = 0.05;

/// Runs solve, normals, integrability and (optionally) integration on a capture.
///
/// # Errors
/// The errors of [`crate::ps::solve::solve`] and [`crate::integrate::integrate_normals`]; [`Error::DegenerateLights`] or
/// [`Error::TooFewImages`] when the light set cannot determine normals.
pub fn reconstruct(
    capture: &Capture,
    config: &Config,
    progress: &dyn Progress,
) -> Result<Reconstruction> {
    let mut recon = reconstruct_normals(capture, config, progress)?;
    // The near-light solve integrates as it goes.
    if recon.near.is_none() {
        let (integration, integrate_s) =
            integrate_stage(&recon.maps.normals, &recon.maps.solved, config, progress)?;
        recon.integration = integration;
        recon.timings.integrate = integrate_s;
    }
    Ok(recon)
}

/// [`reconstruct`] up to and including the integrability check, without the depth
/// (`integration` is `None` and its time 0) — except for near lights
/// ([`near_applies`]), whose solve estimates depth with the normals: what
/// [`reconstruct_and_write`] overlaps with writing.
///
/// # Errors
/// As [`reconstruct`], except the integration errors.
pub fn reconstruct_normals(
    capture: &Capture,
    config: &Config,
    progress: &dyn Progress,
) -> Result<Reconstruction> {
    reconstruct_normals_with_models(capture, config, None, progress)
}

/// The capture-wide image models a solve of `capture` under `config` uses, estimated from the
/// whole capture (one per solved channel; one for the shared-normal colour solve): what to
/// hand to [`reconstruct_normals_with_models`] for every part of a capture solved in parts
/// (tiles on a cluster, say), so that every part is fitted alike. Models that need no data
/// ([`ImageModel::needed`]) come back as [`ImageModel::unit`].
///
/// # Errors
/// As [`crate::ps::solve::solve`]: mismatched sizes or counts, invalid options.
pub fn estimate_models(capture: &Capture, config: &Config) -> Result<Vec<ImageModel>> {
    crate::run::bands::estimate_models(
        &capture.stack,
        &capture.mask,
        &capture.lights,
        config,
        &mut None,
    )
}

/// [`reconstruct_normals`] under the image models `models` (from [`estimate_models`] on the
/// whole capture, or a sample of it) instead of models estimated from `capture`: the solve of
/// one part of a larger capture. `None` estimates them, as [`reconstruct_normals`] does.
///
/// # Errors
/// As [`reconstruct_normals`]; [`Error::InvalidParameter`] (`models`) when the number of
/// models or their length does not fit the capture, or when interreflection compensation is
/// asked for (it re-estimates the model from corrected images).
pub fn reconstruct_normals_with_models(
    capture: &Capture,
    config: &Config,
    models: Option<&[ImageModel]>,
    progress: &dyn Progress,
) -> Result<Reconstruction> {
    if models.is_some() && config.interreflections.is_some() {
        return Err(Error::param(
            "models",
            "interreflection compensation re-estimates the image model from the corrected images, so it cannot run under a given one",
        ));
    }
    capture.lights.check_usable(MAX_LIGHT_CONDITION)?;
    let unmasked_files = capture.mask_source.is_none() && !capture.images.is_empty();
    let solve_config = fill_only_inside_a_mask(config, unmasked_files);
    let facts = InputFacts {
        info: capture.stack.info(),
        count: capture.stack.count(),
        unmasked_files,
        behind: capture.lights.behind(),
        positioned: capture.lights.positioned(),
        ambient_subtracted: capture.ambient_source.is_some(),
    };
    if near_applies(&capture.lights, config) {
        if models.is_some() {
            return Err(Error::param(
                "models",
                "the near-light solve estimates normals and depth of the whole capture together; it cannot run on a part under given models",
            ));
        }
        return near::reconstruct_near(capture, &solve_config, config, &facts, progress);
    }
    let recon = solve_whole(
        (&capture.stack, models),
        capture,
        &solve_config,
        config,
        &facts,
        progress,
    )?;
    match &config.interreflections {
        Some(options) => interreflections::compensate_and_resolve(
            capture,
            (&solve_config, config),
            options,
            recon,
            &facts,
            progress,
        ),
        None => Ok(recon),
    }
}

/// Solves `stack` (the capture's images, or a corrected copy of them) over the capture's mask
/// with `solve_config`, and assembles the maps and summaries with `config`.
fn solve_whole(
    (stack, models): (&ImageStack, Option<&[ImageModel]>),
    capture: &Capture,
    solve_config: &Config,
    config: &Config,
    facts: &InputFacts<'_>,
    progress: &dyn Progress,
) -> Result<Reconstruction> {
    let mut source = WholeStack::new(stack, &capture.mask).with_models(models);
    let (sink, times) = solve_bands(
        &mut source,
        &capture.lights,
        solve_config,
        progress,
        |setup| Ok(Assemble::new(setup)),
    )?;
    Ok(assemble(
        sink.into_solutions(),
        times.model + times.solve + times.sink,
        facts,
        config,
    ))
}

/// `config` for the solve: without a mask the unsolved pixels are mostly background (dark, or
/// lit by too few lights), not holes in the object, so nothing is filled
/// ([`crate::ps::fill`]) and they are reported unsolved.
pub(crate) fn fill_only_inside_a_mask(config: &Config, unmasked_files: bool) -> Config {
    let mut c = *config;
    c.solve.fill &= !unmasked_files;
    c
}

/// Integrates `normals` over `solved` as `config` says (`None` without integration or without
/// solved pixels); returns the result and its time in seconds.
fn integrate_stage(
    normals: &NormalMap,
    solved: &Mask,
    config: &Config,
    progress: &dyn Progress,
) -> Result<(Option<Integration>, f64)> {
    let t = Instant::now();
    let integration = match &config.integration {
        Some(options) if solved.count() > 0 => {
            Some(integrate_normals(normals, solved, options, progress)?)
        }
        _ => None,
    };
    Ok((integration, t.elapsed().as_secs_f64()))
}

/// Writes a reconstruction to `dir` atomically: the EXR maps, PNG previews and `report.json`.
/// Returns the report as written.
///
/// # Errors
/// [`Error::Io`] or [`Error::Encode`] when a file cannot be written; nothing is left behind then.
pub fn write_outputs(
    recon: &mut Reconstruction,
    capture: &Capture,
    config: &Config,
    dir: &Path,
    evaluation: Option<serde_json::Value>,
) -> Result<Report> {
    let t = Instant::now();
    let mut out = OutputDir::create(dir)?;
    let source = Described::of(capture);
    stage_maps(&mut out, recon, &source, config)?;
    stage_depth(
        &mut out,
        &recon.maps.normals,
        recon.integration.as_ref(),
        &source,
        config,
    )?;
    recon.timings.write = t.elapsed().as_secs_f64();
    commit_with_report(
        out,
        RunSummary::of(recon),
        recon.integration.as_ref(),
        &source,
        config,
        evaluation,
    )
}

/// [`reconstruct`] and [`write_outputs`] in one, with the integration running concurrently
/// with the writing of every output that does not depend on depth (normals, albedo, residual,
/// curl and their previews): the two are the longest stages after the solve and each uses
/// about one core. `evaluate` sees the finished reconstruction (depth included) and returns
/// what goes into the report's `evaluation` section. `load_s` is the time the caller spent
/// loading (or rendering) the capture, recorded as [`Timings::load`].
///
/// The outputs are the same as those of [`reconstruct`] followed by [`write_outputs`]. The
/// timings of the integration and the writing overlap, so their sum exceeds the wall time.
///
/// # Errors
/// The errors of [`reconstruct`], [`write_outputs`] and `evaluate`; nothing is left in `dir`
/// when any of them fails.
pub fn reconstruct_and_write(
    capture: &Capture,
    config: &Config,
    dir: &Path,
    load_s: f64,
    progress: &dyn Progress,
    evaluate: impl FnOnce(&Reconstruction) -> Result<Option<serde_json::Value>>,
) -> Result<(Reconstruction, Report)> {
    let mut recon = reconstruct_normals(capture, config, progress)?;
    recon.timings.load = load_s;
    integrate_and_write(
        recon,
        &Described::of(capture),
        config,
        dir,
        progress,
        evaluate,
    )
}

/// The second half of [`reconstruct_and_write`]: the finishing stage on an in-memory
/// reconstruction, whose per-pixel maps are written beside the integration.
pub(crate) fn integrate_and_write(
    mut recon: Reconstruction,
    source: &Described,
    config: &Config,
    dir: &Path,
    progress: &dyn Progress,
    evaluate: impl FnOnce(&Reconstruction) -> Result<Option<serde_json::Value>>,
) -> Result<(Reconstruction, Report)> {
    let mut out = OutputDir::create(dir)?;
    let given = recon.integration.take();
    let finished = finish(
        &mut out,
        (&recon.maps.normals, &recon.maps.solved, given),
        source,
        config,
        progress,
        |out| stage_maps(out, &recon, source, config),
    )?;
    recon.integration = finished.integration;
    if recon.near.is_none() {
        recon.timings.integrate = finished.integrate_s;
    }
    recon.timings.write = finished.write_s;
    let evaluation = evaluate(&recon)?;
    let report = commit_with_report(
        out,
        RunSummary::of(&recon),
        recon.integration.as_ref(),
        source,
        config,
        evaluation,
    )?;
    Ok((recon, report))
}

/// What the finishing stage made.
pub(crate) struct Finished {
    /// Depth and its diagnostics, when integration was asked for.
    pub integration: Option<Integration>,
    /// Seconds integrating.
    pub integrate_s: f64,
    /// Seconds staging files (the maps beside the integration, then depth).
    pub write_s: f64,
}

/// The finishing stage of every run that writes its outputs, in memory or streamed: the
/// integration of `normals` over `solved` (unless it is `given`, as the near-light solve's
/// is) runs beside `stage_rest`, which stages what does not
/// need depth and is not written yet (for an in-memory run, every per-pixel map; for a
/// streamed run, whose bands wrote their rows already, the curl); then the depth outputs are
/// staged. The two concurrent parts are the longest after the solve and use about one core
/// each. The report is the caller's, since it needs what the caller kept.
pub(crate) fn finish(
    out: &mut OutputDir,
    (normals, solved, given): (&NormalMap, &Mask, Option<Integration>),
    source: &Described,
    config: &Config,
    progress: &dyn Progress,
    stage_rest: impl FnOnce(&mut OutputDir) -> Result<()> + Send,
) -> Result<Finished> {
    let (integrated, staged) = rayon::join(
        || match given {
            Some(i) => Ok((Some(i), 0.0)),
            None => integrate_stage(normals, solved, config, progress),
        },
        || {
            let t = Instant::now();
            stage_rest(out).map(|()| t.elapsed().as_secs_f64())
        },
    );
    let (integration, integrate_s) = integrated?;
    let staged_s = staged?;
    let t = Instant::now();
    stage_depth(out, normals, integration.as_ref(), source, config)?;
    Ok(Finished {
        integration,
        integrate_s,
        write_s: staged_s + t.elapsed().as_secs_f64(),
    })
}

/// The per-pixel maps and what is tallied from them, on hand-made per-channel solutions whose
/// every number is known (worst channel for residual and condition, fewest samples, robust
/// only where solved, albedo above 1 counted once a pixel, tallies of bands adding up to the
/// whole, the model summary, the warnings of [`assemble`]); the file contents of the maps
/// ([`map_rows`]), the albedo channel names and the EXR attributes; and [`reconstruct`] on the
/// exact images of a sphere, within the rounding bound of its f32 solve.
#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::lights::Lights;
    use crate::capture::stack::ImageInfo;
    use crate::io::decode::SampleFormat;
    use crate::ps::intensities::{GainEstimate, MIN_LIGHTS};
    use crate::ps::solve::{Method, PixelSolution};
    use crate::synth::test_support::{
        assert_same_bits, hand_made_solution, lambertian_stack, sphere,
    };
    use nalgebra::Vector3;

    /// Images of the hand-made solutions.
    const COUNT: usize = 12;

    /// A pixel outcome: g, residual, samples, condition, status, robust.
    fn px(
        g: [f64; 3],
        residual: f64,
        samples: usize,
        condition: f64,
        status: PixelStatus,
        robust: bool,
    ) -> PixelSolution {
        let solved = status == PixelStatus::Solved;
        PixelSolution {
            g: if solved {
                Vector3::from(g)
            } else {
                Vector3::repeat(f64::NAN)
            },
            residual: if solved { residual } else { f64::NAN },
            samples,
            condition,
            status,
            robust,
        }
    }

    /// Three channels over 3×2 pixels:
    /// - (0, 0) outside the mask;
    /// - (1, 0) solved everywhere: residuals 0.1, 0.3, 0.2; samples 10, 7, 9; condition 2, 5,
    ///   3; robust in G only; |g_R| = 1.2;
    /// - (2, 0) solved and robust in R, too few samples in G (2), solved in B;
    /// - (0, 1) solved everywhere, not robust, albedo below 1;
    /// - (1, 1) dark in B;
    /// - (2, 1) solved everywhere, |g| = 1.5 in R and G.
    ///
    /// So 5 masked, 3 solved, 1 too few, 1 dark; 1 robust; 2 pixels with albedo above 1.
    fn channels() -> Vec<Solution> {
        use PixelStatus::{Dark, Solved, TooFewSamples};
        let z = |r: f64| [0.0, 0.0, r];
        let pixels: [[(usize, usize, PixelSolution); 5]; 3] = [
            [
                (1, 0, px(z(1.2), 0.1, 10, 2.0, Solved, false)),
                (2, 0, px(z(0.5), 0.05, 8, 2.5, Solved, true)),
                (0, 1, px([0.3, 0.0, 0.4], 0.02, 12, 1.5, Solved, false)),
                (1, 1, px(z(0.4), 0.01, 12, 1.5, Solved, false)),
                (2, 1, px(z(1.5), 0.01, 12, 1.5, Solved, false)),
            ],
            [
                (1, 0, px(z(0.6), 0.3, 7, 5.0, Solved, true)),
                (
                    2,
                    0,
                    px(z(0.5), 0.0, 2, f64::INFINITY, TooFewSamples, false),
                ),
                (0, 1, px([0.0, 0.3, 0.4], 0.04, 11, 1.6, Solved, false)),
                (1, 1, px(z(0.4), 0.01, 12, 1.5, Solved, false)),
                (2, 1, px([0.9, 0.0, 1.2], 0.01, 12, 1.5, Solved, false)),
            ],
            [
                (1, 0, px(z(0.3), 0.2, 9, 3.0, Solved, false)),
                (2, 0, px(z(0.5), 0.07, 8, 2.5, Solved, false)),
                (0, 1, px([0.0, 0.0, 0.5], 0.03, 10, 1.7, Solved, false)),
                (1, 1, px(z(0.0), 0.0, 12, 1.5, Dark, false)),
                (2, 1, px(z(0.2), 0.01, 12, 1.5, Solved, false)),
            ],
        ];
        pixels
            .iter()
            .map(|p| hand_made_solution(3, 2, COUNT, p))
            .collect()
    }

    /// Rows `y0..y1` of a solution.
    fn rows(s: &Solution, y0: usize, y1: usize) -> Solution {
        fn cut<T: Clone>(g: &Grid<T>, y0: usize, y1: usize) -> Grid<T> {
            Grid::from_fn(g.width(), y1 - y0, |x, y| g.at(x, y0 + y).clone())
        }
        Solution {
            g: cut(&s.g, y0, y1),
            residual: cut(&s.residual, y0, y1),
            samples: cut(&s.samples, y0, y1),
            condition: cut(&s.condition, y0, y1),
            status: cut(&s.status, y0, y1),
            robust: cut(&s.robust, y0, y1),
            gains: s.gains.clone(),
            noise: s.noise.clone(),
            shadow_labels: s.shadow_labels,
            lobes: s.lobes,
            shadow_light: s.shadow_light.clone(),
            light_agreement: s.light_agreement.clone(),
        }
    }

    /// Per pixel, the worst channel: largest residual and condition, fewest samples; the
    /// status of the first channel not solved; robust where solved and robust in any channel;
    /// normals of unit length where solved, NaN elsewhere, along g_R + g_G + g_B.
    #[test]
    fn pixel_maps_take_the_worst_channel() {
        let m = pixel_maps(&channels());
        assert_eq!(*m.residual.at(1, 0), 0.3);
        assert_eq!(*m.condition.at(1, 0), 5.0);
        assert_eq!(*m.samples.at(1, 0), 7);
        assert_eq!(*m.samples.at(2, 0), 2);
        assert_eq!(*m.residual.at(0, 1), 0.04);
        assert_eq!(*m.condition.at(0, 1), 1.7);
        assert_eq!(*m.samples.at(0, 1), 10);
        let status = [
            PixelStatus::Outside,
            PixelStatus::Solved,
            PixelStatus::TooFewSamples,
            PixelStatus::Solved,
            PixelStatus::Dark,
            PixelStatus::Solved,
        ];
        assert_eq!(m.status.data(), status);
        assert_eq!(m.solved.data(), status.map(|s| s == PixelStatus::Solved));
        // Robust in G at (1, 0); robust in R at (2, 0) but not solved there.
        assert_eq!(m.robust.data(), [false, true, false, false, false, false]);
        for (i, n) in m.normals.data().iter().enumerate() {
            if m.solved.data()[i] {
                assert!((n.norm() - 1.0).abs() < 1e-6, "pixel {i}: {n:?}");
            } else {
                assert!(n.iter().all(|v| v.is_nan()), "pixel {i}: {n:?}");
            }
        }
        // (0, 1): g sums to (0.3, 0.3, 1.3).
        let want = Vector3::new(0.3f32, 0.3, 1.3).normalize();
        assert!((m.normals.at(0, 1) - want).norm() < 1e-6);
        assert_eq!(m.albedo.len(), 3);
        assert_eq!(albedo_above_one(&m.albedo), 2);
    }

    /// One channel is taken as it is, but robust still only where solved.
    #[test]
    fn pixel_maps_of_one_channel_are_its_own() {
        let mut one = channels().swap_remove(0);
        // Robust where not solved: dropped from the robust map.
        one.status.data_mut()[4] = PixelStatus::IllConditioned;
        one.robust.data_mut()[4] = true;
        let m = pixel_maps(std::slice::from_ref(&one));
        assert_same_bits(m.residual.data(), one.residual.data(), "residual");
        assert_same_bits(m.condition.data(), one.condition.data(), "condition");
        assert_eq!(m.samples, one.samples);
        assert_eq!(m.status, one.status);
        assert_eq!(m.robust.data(), [false, false, true, false, false, false]);
        assert_eq!(m.albedo.len(), 1);
        assert_eq!(albedo_above_one(&m.albedo), 2);
    }

    /// The tallies of the bands (row 0, row 1) add up to those of the whole image.
    #[test]
    fn tallies_of_bands_add_up_to_the_whole() {
        let all = channels();
        let whole = Tallies::of(&pixel_maps(&all));
        assert_eq!(
            whole.counts,
            StatusCounts {
                masked: 5,
                solved: 3,
                too_few_samples: 1,
                ill_conditioned: 0,
                dark: 1,
                filled: 0,
            }
        );
        assert_eq!((whole.robust, whole.albedo_above_one), (1, 2));
        let band = |y0, y1| {
            let b: Vec<Solution> = all.iter().map(|s| rows(s, y0, y1)).collect();
            Tallies::of(&pixel_maps(&b))
        };
        let mut sum = band(0, 1);
        let second = band(1, 2);
        // Each band holds part of every tally.
        assert!(sum.counts.solved > 0 && second.counts.solved > 0);
        sum.add(&second);
        assert_eq!(sum.counts, whole.counts);
        assert_eq!(sum.robust, whole.robust);
        assert_eq!(sum.albedo_above_one, whole.albedo_above_one);
    }

    /// Channel models with distinct gains, estimates and noise per channel.
    fn models() -> Vec<ChannelModel> {
        (0..3)
            .map(|c| {
                let f = 1.0 + 0.1 * c as f32;
                ChannelModel {
                    gains: GainEstimate {
                        gains: if c == 1 {
                            vec![1.0; COUNT]
                        } else {
                            vec![f; COUNT]
                        },
                        estimated: vec![f; COUNT],
                        applied: c != 1,
                        ..GainEstimate::unit(COUNT)
                    },
                    noise: vec![0.01 * f; COUNT],
                    shadow_labels: None,
                    lobes: None,
                    shadow_light: None,
                    light_agreement: None,
                }
            })
            .collect()
    }

    /// The robust fraction is of the solved pixels (0 when none is solved); gains, whether they
    /// were applied and the noise are reported per channel; the estimated gains only when the
    /// run recalibrated (the default method with at least [`MIN_LIGHTS`] images).
    #[test]
    fn model_summary_reports_the_channels_and_the_robust_fraction() {
        let tallies = Tallies::of(&pixel_maps(&channels()));
        let ms = models();
        let config = Config::default();
        let s = model_summary(&ms, &tallies, COUNT, &config);
        assert_eq!(s.method, Method::Auto.name());
        assert_eq!(s.robust_pixels, 1);
        assert_eq!(s.robust_fraction, 1.0 / 3.0);
        assert!(s.recalibrated);
        assert_eq!(s.gains_applied, [true, false, true]);
        for (c, m) in ms.iter().enumerate() {
            assert_eq!(s.gains[c], m.gains.gains, "channel {c}");
            assert_eq!(s.estimated_gains[c], m.gains.estimated, "channel {c}");
            assert_eq!(s.noise[c], m.noise, "channel {c}");
        }
        // Not recalibrated: too few images, or turned off.
        let off = Config {
            solve: SolveOptions {
                recalibrate: Some(false),
                ..SolveOptions::default()
            },
            ..Config::default()
        };
        for (count, config) in [(MIN_LIGHTS - 1, &config), (COUNT, &off)] {
            let s = model_summary(&ms, &tallies, count, config);
            assert!(!s.recalibrated, "{count} images");
            assert!(s.estimated_gains.is_empty(), "{count} images");
            assert_eq!(s.gains.len(), 3);
        }
        // Nothing solved: 0, not NaN.
        let none = Tallies::default();
        assert_eq!(
            model_summary(&ms, &none, COUNT, &config).robust_fraction,
            0.0
        );
    }

    /// [`assemble`] on the hand-made channels: the counts, the albedo above 1, the robust map
    /// and the warnings carry the numbers of the construction and of the input facts.
    #[test]
    fn assemble_counts_and_warns_with_the_numbers() {
        let info: Vec<ImageInfo> = (0..COUNT)
            .map(|k| ImageInfo {
                path: PathBuf::from(format!("img_{k}.png")),
                format: SampleFormat::U16,
                channels: 3,
                linearised: false,
                saturated: if k < 2 { 3 + k } else { 0 },
                non_finite: 0,
                raw: None,
            })
            .collect();
        let facts = InputFacts {
            info: &info,
            count: COUNT,
            unmasked_files: false,
            behind: vec![3],
            positioned: 2,
            ambient_subtracted: false,
        };
        let config = Config {
            albedo_normalised: true,
            integration: None,
            ..Config::default()
        };
        let r = assemble(channels(), 0.5, &facts, &config);
        assert_eq!(r.counts.masked, 5);
        assert_eq!(r.counts.solved, 3);
        assert_eq!(r.albedo_above_one, 2);
        assert_eq!(r.maps.robust.count(), 1);
        assert_eq!(r.model.robust_pixels, 1);
        assert_eq!(r.timings.solve, 0.5);
        assert!(r.integration.is_none());
        assert!(r.warnings.contains(&Warning::Saturated {
            samples: 7,
            used: false
        }));
        assert!(r.warnings.contains(&Warning::Unsolved {
            unsolved: 2,
            masked: 5,
            too_few_samples: 1,
            ill_conditioned: 0,
            dark: 1,
            no_mask: false
        }));
        assert!(r.warnings.contains(&Warning::AlbedoAboveOne { pixels: 2 }));
        assert!(r.warnings.contains(&Warning::LightsBehind {
            lights: vec![3],
            count: COUNT
        }));
        assert!(r.warnings.contains(&Warning::NearLights {
            positioned: 2,
            count: COUNT
        }));
        // Not declared normalised: no albedo warning.
        let r = assemble(
            channels(),
            0.0,
            &facts,
            &Config {
                albedo_normalised: false,
                ..config
            },
        );
        assert!(
            !r.warnings
                .iter()
                .any(|w| matches!(w, Warning::AlbedoAboveOne { .. }))
        );
    }

    /// The file contents: samples, condition, robust and filled NaN outside the mask and robust
    /// and filled 0 or 1 inside; albedo NaN where not solved; the residual as it is; mask 255
    /// where solved.
    #[test]
    fn map_rows_mark_what_is_outside_the_mask() {
        let m = pixel_maps(&channels());
        let rows = map_rows(&m);
        let [_, samples, condition, robust, filled] = &rows.residual[..] else {
            panic!("{} residual planes", rows.residual.len());
        };
        assert_same_bits(&rows.residual[0], m.residual.data(), "residual");
        for i in 0..6 {
            let status = m.status.data()[i];
            if status == PixelStatus::Outside {
                assert!(samples[i].is_nan() && condition[i].is_nan() && robust[i].is_nan());
                assert!(filled[i].is_nan());
            } else {
                let is_filled = status == PixelStatus::Filled;
                assert_eq!(filled[i], if is_filled { 1.0 } else { 0.0 });
                assert_eq!(samples[i], f32::from(m.samples.data()[i]), "pixel {i}");
                assert_eq!(condition[i].to_bits(), m.condition.data()[i].to_bits());
                assert_eq!(robust[i], if m.robust.data()[i] { 1.0 } else { 0.0 });
            }
            let solved = m.solved.data()[i];
            for (c, a) in rows.albedo.iter().enumerate() {
                if solved {
                    assert_eq!(a[i], m.albedo[c].data()[i], "pixel {i}, channel {c}");
                } else {
                    assert!(a[i].is_nan(), "pixel {i}, channel {c}: {}", a[i]);
                }
            }
            assert_eq!(rows.mask[i], if solved { 255 } else { 0 });
            for (axis, plane) in rows.normal.iter().enumerate() {
                assert_eq!(plane[i].to_bits(), m.normals.data()[i][axis].to_bits());
            }
        }
        // The too-few pixel's R channel was solved, yet its albedo is not written.
        assert!(m.albedo[0].at(2, 0).is_finite() && rows.albedo[0][2].is_nan());
        assert_eq!(robust[1], 1.0);
        assert_eq!(rows.normal_png.len(), 3 * 6);
    }

    /// One or three albedo channels are named; any other count is refused, naming it.
    #[test]
    fn albedo_channels_are_y_or_rgb() {
        assert_eq!(albedo_channels(1).unwrap(), ["Y"]);
        assert_eq!(albedo_channels(3).unwrap(), ["R", "G", "B"]);
        for n in [0, 2, 4] {
            let e = albedo_channels(n).unwrap_err();
            assert!(
                matches!(&e, Error::InvalidParameter { name: "albedo", reason } if reason.starts_with(&format!("{n} "))),
                "{e}"
            );
        }
    }

    /// The EXR attributes: the method's name, the frame, the units, the light count and the
    /// light directions as JSON that reads back to the same numbers.
    #[test]
    fn exr_attributes_describe_method_and_lights() {
        let lights = Lights::fibonacci(5, 30.0).unwrap();
        for method in [Method::Auto, Method::Threshold] {
            let config = Config {
                solve: SolveOptions::with_method(method),
                ..Config::default()
            };
            // Every file's units say what that file holds, in ASCII (EXR text is Latin-1).
            for file in ["normal.exr", "albedo.exr", "residual.exr", "curl.exr"] {
                let units = units_of(file, &config);
                assert!(
                    units.is_ascii() && !units.starts_with("Z:"),
                    "{file}: {units}"
                );
                assert!(
                    units.starts_with(&file[..3]) || file == "normal.exr",
                    "{units}"
                );
            }
            let camera = Config {
                integration: Some(crate::integrate::IntegrationOptions {
                    camera: Some(crate::camera::Intrinsics {
                        fx: 500.0,
                        fy: 500.0,
                        cx: 32.0,
                        cy: 24.0,
                    }),
                    ..Default::default()
                }),
                ..config
            };
            assert!(units_of("curl.exr", &camera).contains("log-depth"));
            assert!(units_of("depth.exr", &camera).contains("optical axis"));
            let attrs = exr_attributes(&lights, &config, "depth.exr");
            let keys: Vec<&str> = attrs.iter().map(|a| a.0).collect();
            assert_eq!(
                keys,
                [
                    "photostereo:method",
                    "photostereo:frame",
                    "photostereo:units",
                    "photostereo:lights",
                    "photostereo:light_directions"
                ]
            );
            assert_eq!(attrs[0].1, method.name());
            assert_eq!(attrs[2].1, ORTHOGRAPHIC_UNITS);
            assert_eq!(attrs[3].1, "5");
            let dirs: Vec<[f64; 3]> = serde_json::from_str(&attrs[4].1).unwrap();
            let want: Vec<[f64; 3]> = lights
                .directions()
                .iter()
                .map(|d| [d.x, d.y, d.z])
                .collect();
            assert_eq!(dirs, want);
        }
    }

    /// Unit roundoff of f32 (2⁻²⁴).
    const U: f64 = f32::EPSILON as f64 / 2.0;

    /// [`reconstruct`] of the exact images of a 32×32 sphere (normals up to 60° from the view,
    /// albedo 0.7, 12 lights at 30°–90° elevation, default method and integration) solves every
    /// masked pixel and nothing else, and integrates depth over exactly those pixels. Each
    /// normal and albedo is within the rounding bound of the f32 normal equations: with m used
    /// samples of condition κ (the pixel's `condition`), the directions and samples are
    /// rounded to f32 and LᵀL and LᵀI summed in f32, so each entry is off by at most
    /// γ = (m+2)u/(1−(m+2)u) of Σ|l_i||l_j| (resp. Σ|l_i||I|); as ‖|L|‖ ≤ √3‖L‖, the relative
    /// error of g is at most (3 + √3)·γ·κ²; storing g in f32, normalising it and taking its norm
    /// add at most 4u.
    #[test]
    fn reconstruct_recovers_a_sphere_within_the_rounding_bound() {
        let (truth, mask) = sphere(32, 60.0);
        let lights = Lights::fibonacci(12, 30.0).unwrap();
        let stack = lambertian_stack(&truth, &mask, &lights, &[0.7], &[1.0; 12]);
        let capture = Capture::from_stack(stack, lights, Some(mask.clone())).unwrap();
        let r = reconstruct(&capture, &Config::default(), &crate::progress::Silent).unwrap();
        assert_eq!(r.counts.masked, mask.count());
        assert_eq!(r.counts.solved, mask.count());
        assert_eq!(r.maps.solved, mask);
        let depth = r.depth().expect("integration ran");
        let mut worst: f64 = 0.0;
        for p in 0..mask.len() {
            if !mask.data()[p] {
                assert!(r.maps.normals.data()[p].iter().all(|v| v.is_nan()));
                assert!(depth.data()[p].is_nan(), "pixel {p}");
                continue;
            }
            assert!(depth.data()[p].is_finite(), "pixel {p}");
            let m = f64::from(r.maps.samples.data()[p]);
            let kappa = f64::from(r.maps.condition.data()[p]);
            let gamma = (m + 2.0) * U / (1.0 - (m + 2.0) * U);
            let bound = (3.0 + 3f64.sqrt()) * gamma * kappa * kappa + 4.0 * U;
            let n = r.maps.normals.data()[p].cast::<f64>();
            let t = truth.data()[p];
            let angle = n.cross(&t).norm().atan2(n.dot(&t));
            let albedo = (f64::from(r.maps.albedo[0].data()[p]) - 0.7).abs() / 0.7;
            worst = worst.max(angle.max(albedo) / bound);
            assert!(
                angle <= bound && albedo <= bound,
                "pixel {p}: angle {angle:e}, albedo {albedo:e}, bound {bound:e}"
            );
        }
        println!("worst error / bound: {worst:.3}");
        assert!(
            !r.warnings
                .iter()
                .any(|w| matches!(w, Warning::Unsolved { .. }))
        );
    }
}
