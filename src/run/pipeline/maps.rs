//! The per-pixel maps of a solve ([`PixelMaps`]), over a whole image or a band, and what is
//! tallied from them: outcome counts, the model summary, the integrability check; [`assemble`]
//! turns per-channel solutions into a [`Reconstruction`] without depth.

use super::*;

/// What [`assemble`] needs to know of the input for its warnings.
#[derive(Clone)]
pub(crate) struct InputFacts<'a> {
    /// Per image, what loading found.
    pub info: &'a [crate::capture::stack::ImageInfo],
    /// Number of images.
    pub count: usize,
    /// Files were loaded without a mask (the background counts as object then).
    pub unmasked_files: bool,
    /// Indices of the lights behind the surface (z < 0).
    pub behind: Vec<usize>,
    /// Lights given with a position (near lights), solved as distant ones.
    pub positioned: usize,
    /// An ambient image was subtracted from the images.
    pub ambient_subtracted: bool,
}

/// The per-pixel maps of a solve, over a whole image or a band of rows: what every pixel's
/// outputs are made of.
#[derive(Debug, Clone)]
pub struct PixelMaps {
    /// Unit normals; NaN where not solved.
    pub normals: NormalMap,
    /// Albedo per channel (one map for grey solves, R, G, B for colour ones).
    pub albedo: Vec<ScalarMap>,
    /// RMS residual of the model over used samples (largest over channels).
    pub residual: ScalarMap,
    /// Samples used per pixel (fewest over channels).
    pub samples: Grid<u16>,
    /// Condition number of the used lights (largest over channels).
    pub condition: ScalarMap,
    /// Outcome per pixel.
    pub status: Grid<PixelStatus>,
    /// Pixels with a normal.
    pub solved: Mask,
    /// Solved pixels fitted by a robust estimator (any channel).
    pub robust: Mask,
}

/// Albedo, normals and status of the per-channel solutions (one channel taken as it is).
pub(super) fn albedo_normals_status(
    solutions: &[Solution],
) -> (Vec<ScalarMap>, NormalMap, Grid<PixelStatus>) {
    match solutions {
        [one] => {
            let (a, n) = albedo_and_normals(one);
            (vec![a], n, one.status.clone())
        }
        _ => combine_channels(solutions),
    }
}

/// Residual, condition, samples and the robust flag per pixel: the worst channel.
pub(super) fn per_pixel(
    solutions: &[Solution],
    solved: &Mask,
) -> (ScalarMap, ScalarMap, Grid<u16>, Mask) {
    let (w, h) = (solved.width(), solved.height());
    let fold = |f: &dyn Fn(&Solution) -> &ScalarMap, pick: fn(f32, f32) -> f32| match solutions {
        [one] => f(one).clone(),
        _ => Grid::from_fn(w, h, |x, y| {
            solutions
                .iter()
                .map(|s| *f(s).at(x, y))
                .reduce(pick)
                .unwrap_or(f32::NAN)
        }),
    };
    let residual = fold(&|s| &s.residual, f32::max);
    let condition = fold(&|s| &s.condition, f32::max);
    let samples = match solutions {
        [one] => one.samples.clone(),
        _ => Grid::from_fn(w, h, |x, y| {
            solutions
                .iter()
                .map(|s| *s.samples.at(x, y))
                .min()
                .unwrap_or(0)
        }),
    };
    let robust = Grid::from_fn(w, h, |x, y| {
        *solved.at(x, y) && solutions.iter().any(|s| *s.robust.at(x, y))
    });
    (residual, condition, samples, robust)
}

/// The per-pixel maps of per-channel solutions of equal size (a whole image or a band).
pub(crate) fn pixel_maps(solutions: &[Solution]) -> PixelMaps {
    pixel_maps_beside(solutions, |_, _| ()).0
}

/// [`pixel_maps`], with `beside` run on the normals and the solved mask concurrently with the
/// per-pixel summaries (residual, condition, samples, robust flag).
fn pixel_maps_beside<T: Send>(
    solutions: &[Solution],
    beside: impl FnOnce(&NormalMap, &Mask) -> T + Send,
) -> (PixelMaps, T) {
    let (albedo, normals, status) = albedo_normals_status(solutions);
    let solved = status.map(|s| s.has_normal());
    let (other, (residual, condition, samples, robust)) = rayon::join(
        || beside(&normals, &solved),
        || per_pixel(solutions, &solved),
    );
    let maps = PixelMaps {
        normals,
        albedo,
        residual,
        samples,
        condition,
        status,
        solved,
        robust,
    };
    (maps, other)
}

/// Pixels whose albedo is above 1 in any channel.
pub(crate) fn albedo_above_one(albedo: &[ScalarMap]) -> usize {
    let n = albedo.first().map_or(0, |a| a.len());
    (0..n)
        .filter(|&i| albedo.iter().any(|a| a.data()[i] > 1.0))
        .count()
}

/// What the solve of one channel assumed over the whole image: its intensity gains and the
/// fit test's per-image noise.
#[derive(Debug, Clone)]
pub(crate) struct ChannelModel {
    /// The intensity gains, estimated or not.
    pub gains: crate::ps::intensities::GainEstimate,
    /// Per-image noise σ (`auto` only; empty otherwise).
    pub noise: Vec<f32>,
    /// What the shadow labelling changed, when it ran.
    pub shadow_labels: Option<crate::ps::shadows::ShadowSummary>,
    /// What the refit with specular lobes did, when it ran.
    pub lobes: Option<crate::ps::lobes::LobeSummary>,
    /// The light in attached shadows ([`crate::ps::ambient`]).
    pub shadow_light: Option<crate::ps::ambient::ShadowLight>,
    /// Each light checked against the others ([`crate::ps::light_agreement`]).
    pub light_agreement: Option<crate::ps::light_agreement::LightAgreement>,
}

impl ChannelModel {
    /// The model of each solution.
    pub(crate) fn of(solutions: &[Solution]) -> Vec<Self> {
        solutions
            .iter()
            .map(|s| ChannelModel {
                gains: s.gains.clone(),
                noise: s.noise.clone(),
                shadow_labels: s.shadow_labels,
                lobes: s.lobes,
                shadow_light: s.shadow_light.clone(),
                light_agreement: s.light_agreement.clone(),
            })
            .collect()
    }

    /// Adds the shadow labelling and lobe refit counts of `band`, a solved band of this
    /// channel.
    pub(crate) fn add_band_passes(&mut self, band: &Solution) {
        if let Some(b) = &band.shadow_labels {
            self.shadow_labels.get_or_insert_default().add(b);
        }
        if let Some(b) = &band.lobes {
            self.lobes.get_or_insert_default().add(b);
        }
        if let Some(b) = &band.shadow_light {
            self.shadow_light.get_or_insert_default().add(b);
        }
        if let Some(b) = &band.light_agreement {
            self.light_agreement.get_or_insert_default().add(b);
        }
    }
}

/// Whole-image tallies of the per-pixel maps.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Tallies {
    /// Pixel outcome counts.
    pub counts: StatusCounts,
    /// Solved pixels fitted by a robust estimator.
    pub robust: usize,
    /// Pixels with albedo above 1.
    pub albedo_above_one: usize,
}

impl Tallies {
    /// The tallies of `maps`.
    pub(crate) fn of(maps: &PixelMaps) -> Self {
        Tallies {
            counts: StatusCounts::from_grid(&maps.status),
            robust: maps.robust.count(),
            albedo_above_one: albedo_above_one(&maps.albedo),
        }
    }

    /// Adds the tallies of another band.
    pub(crate) fn add(&mut self, other: &Tallies) {
        self.counts.add(&other.counts);
        self.robust += other.robust;
        self.albedo_above_one += other.albedo_above_one;
    }
}

/// The model summary of a run from its channel models and tallies.
pub(crate) fn model_summary(
    models: &[ChannelModel],
    tallies: &Tallies,
    count: usize,
    config: &Config,
) -> ModelSummary {
    let recalibrated = config.solve.recalibrates(count);
    ModelSummary {
        method: config.solve.method.name(),
        robust_pixels: tallies.robust,
        robust_fraction: tallies.robust as f64 / tallies.counts.solved.max(1) as f64,
        gains: models.iter().map(|m| m.gains.gains.clone()).collect(),
        recalibrated,
        gains_applied: models.iter().map(|m| m.gains.applied).collect(),
        estimated_gains: if recalibrated {
            models.iter().map(|m| m.gains.estimated.clone()).collect()
        } else {
            Vec::new()
        },
        noise: models.iter().map(|m| m.noise.clone()).collect(),
        shadow_labels: models.iter().filter_map(|m| m.shadow_labels).collect(),
        lobes: models.iter().filter_map(|m| m.lobes).collect(),
        shadow_light: models
            .iter()
            .filter_map(|m| m.shadow_light.clone())
            .collect(),
        light_agreement: models
            .iter()
            .filter_map(|m| m.light_agreement.clone())
            .collect(),
    }
}

/// The integrability check of normals `normals` solved at `solved`, on the field that is
/// integrated: log-depth gradients under a pinhole camera, orthographic ones otherwise.
pub(crate) fn integrability_of(
    normals: &NormalMap,
    solved: &Mask,
    config: &Config,
) -> crate::ps::normals::Integrability {
    let camera = config.integration.as_ref().and_then(|o| o.camera.as_ref());
    let (p, q) = crate::integrate::normal_gradients(normals, solved, camera);
    integrability(&p, &q)
}

/// From the per-channel solutions to a [`Reconstruction`] without depth: albedo, normals,
/// the integrability check, per-pixel summaries, the model summary and the warnings.
pub(crate) fn assemble(
    solutions: Vec<Solution>,
    solve_s: f64,
    facts: &InputFacts,
    config: &Config,
) -> Reconstruction {
    let t = Instant::now();
    // The integrability check (the longest part) runs beside the per-pixel summaries.
    let (maps, integ) = pixel_maps_beside(&solutions, |normals, solved| {
        integrability_of(normals, solved, config)
    });
    let tallies = Tallies::of(&maps);
    let models = ChannelModel::of(&solutions);
    let model = model_summary(&models, &tallies, facts.count, config);
    let normals_s = t.elapsed().as_secs_f64();
    let warnings = warnings(facts, &tallies, &models, &integ.summary, config);
    Reconstruction {
        maps,
        curl: integ.curl,
        integrability: integ.summary,
        integration: None,
        counts: tallies.counts,
        albedo_above_one: tallies.albedo_above_one,
        model,
        timings: Timings {
            load: 0.0,
            solve: solve_s,
            normals: normals_s,
            integrate: 0.0,
            write: 0.0,
        },
        warnings,
        interreflections: None,
        near: None,
    }
}
