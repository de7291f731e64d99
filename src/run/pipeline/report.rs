//! `report.json`: what a run read ([`InputSummary`]), how much model the data needed
//! ([`ModelSummary`]), residual and integration summaries, and the [`Report`] itself, staged with
//! every other output and committed with them.

use super::*;

/// How much model the data needed, for the report.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ModelSummary {
    /// The estimator.
    pub method: &'static str,
    /// Solved pixels fitted by a robust estimator (for `auto`: those whose residuals failed
    /// the Lambertian fit test).
    pub robust_pixels: usize,
    /// `robust_pixels` as a fraction of the solved pixels.
    pub robust_fraction: f64,
    /// Per channel, the per-image intensity gains applied (all 1 unless an estimate was
    /// applied).
    pub gains: Vec<Vec<f32>>,
    /// Whether the intensity gains were estimated from the data.
    pub recalibrated: bool,
    /// Per channel, whether the estimate was applied: it converged and fitted the data better
    /// than the stated intensities ([`crate::ps::intensities::GainEstimate::applied`]).
    pub gains_applied: Vec<bool>,
    /// Per channel, the estimated gains, applied or not (empty without recalibration).
    pub estimated_gains: Vec<Vec<f32>>,
    /// Per channel, the per-image noise σ the fit test assumed (`auto` only).
    pub noise: Vec<Vec<f32>>,
    /// Per channel, what the shadow labelling changed ([`crate::ps::shadows`]; absent when it
    /// did not run).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub shadow_labels: Vec<crate::ps::shadows::ShadowSummary>,
    /// Per channel, what the refit with specular lobes did: how many of the pixels that failed
    /// the Lambertian fit test the lobe model explains ([`crate::ps::lobes`]; absent when it did
    /// not run).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub lobes: Vec<crate::ps::lobes::LobeSummary>,
    /// Per channel, the light in attached shadows — ambient light, a black level,
    /// interreflections — and the mean angle such an offset turns the normals by
    /// ([`crate::ps::ambient`]).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub shadow_light: Vec<crate::ps::ambient::ShadowLight>,
    /// Per channel, each light checked against the others: the direction the other images
    /// give it, its angle from the given one, and the lights that disagree beyond chance
    /// ([`crate::ps::light_agreement`]).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub light_agreement: Vec<crate::ps::light_agreement::LightAgreement>,
}

/// Summary of the input, for the report.
#[derive(Debug, Clone, Serialize)]
pub struct InputSummary {
    /// Image files (empty for in-memory captures).
    pub images: Vec<PathBuf>,
    /// Number of images.
    pub count: usize,
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Lights file.
    pub lights: Option<PathBuf>,
    /// Mask file.
    pub mask: Option<PathBuf>,
    /// The ambient image subtracted from every image, if any.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ambient: Option<PathBuf>,
    /// Condition number of the full light matrix.
    pub light_condition_number: f64,
    /// Storage format of the first image.
    pub format: Option<crate::io::decode::SampleFormat>,
    /// 8-bit images decoded as sRGB.
    pub linearised_images: usize,
    /// Saturated samples over all images.
    pub saturated_samples: usize,
    /// Grey mix or per-channel.
    pub color: ColorMode,
    /// How camera RAW inputs were developed (black and white levels, white balance, binning;
    /// those of the first image), when they are RAW.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub raw: Option<crate::io::raw::RawDevelopment>,
}

impl InputSummary {
    /// Summarises a capture.
    pub fn of(capture: &Capture) -> Self {
        let mut s = Self::of_files(
            &capture.images,
            &capture.lights,
            capture.lights_source.as_deref(),
            capture.mask_source.as_deref(),
            capture.stack.info(),
        );
        s.ambient.clone_from(&capture.ambient_source);
        s.count = capture.stack.count();
        s.width = capture.stack.width();
        s.height = capture.stack.height();
        s.color = if capture.stack.channels() == 3 {
            ColorMode::PerChannel
        } else {
            ColorMode::Grey
        };
        s
    }

    /// Summarises the files of a capture and what loading found in them (`info`); the size is
    /// left 0×0 and the colour mode grey for the caller to set.
    pub fn of_files(
        images: &[PathBuf],
        lights: &crate::capture::lights::Lights,
        lights_source: Option<&Path>,
        mask_source: Option<&Path>,
        info: &[crate::capture::stack::ImageInfo],
    ) -> Self {
        InputSummary {
            images: images.to_vec(),
            count: info.len(),
            width: 0,
            height: 0,
            lights: lights_source.map(Path::to_path_buf),
            mask: mask_source.map(Path::to_path_buf),
            ambient: None,
            light_condition_number: lights.condition_number(),
            format: info.first().map(|i| i.format),
            linearised_images: info.iter().filter(|i| i.linearised).count(),
            saturated_samples: info.iter().map(|i| i.saturated).sum(),
            color: ColorMode::Grey,
            raw: info.first().and_then(|i| i.raw.clone()),
        }
    }
}

/// Residual statistics over solved pixels.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct ResidualSummary {
    /// Mean RMS residual.
    pub mean: f64,
    /// Median RMS residual.
    pub median: f64,
}

/// `auto`'s decision in the report.
#[derive(Debug, Clone, Serialize)]
pub struct AutoSummary {
    /// The numbers of the test.
    #[serde(flatten)]
    pub decision: crate::integrate::AutoDecision,
    /// The decision in one sentence.
    pub reason: String,
}

/// How depth was integrated and how faithful it is to the normals.
#[derive(Debug, Clone, Serialize)]
pub struct IntegrationSummary {
    /// The method's name (the one whose depth was kept: `auto` reports its choice here and
    /// its evidence in `auto`).
    pub method: &'static str,
    /// What `auto` found and chose, with the reason in words.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub auto: Option<AutoSummary>,
    /// Perspective (with intrinsics) or orthographic.
    pub perspective: bool,
    /// How the linear system was solved, for the masked methods.
    pub solve: Option<crate::integrate::SolveInfo>,
    /// Reweighting iterations (bilateral).
    pub iterations: usize,
    /// Regions the bilateral integrator's cuts close off, whose depth offset is a guess.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub closed_off: Option<crate::integrate::ClosedOff>,
    /// Mean of the per-pixel integration residual (see [`Integration::residual`]).
    pub mean_residual: f64,
    /// Median of the per-pixel integration residual.
    pub median_residual: f64,
}

/// The `report.json` written beside the outputs.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Crate version that wrote it.
    pub version: &'static str,
    /// The input.
    pub inputs: InputSummary,
    /// Method and parameters.
    pub config: Config,
    /// Pixel outcome counts.
    pub pixels: StatusCounts,
    /// How much model the data needed (robust pixels, intensity gains, noise).
    pub model: ModelSummary,
    /// Pixels with albedo > 1.
    pub albedo_above_one: usize,
    /// Model residual over solved pixels.
    pub residual: ResidualSummary,
    /// The integrability check.
    pub integrability: IntegrabilitySummary,
    /// Stage timings in seconds.
    pub timings_s: Timings,
    /// Warnings raised (in the file, as their text).
    pub warnings: Vec<Warning>,
    /// Normal integration: method, solver and how well the depth fits the normals.
    pub integration: Option<IntegrationSummary>,
    /// Files written (names within the output folder).
    pub outputs: Vec<String>,
    /// Errors against ground truth, when known (e.g. for the demo scene).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub evaluation: Option<serde_json::Value>,
    /// What interreflection compensation did, when it was asked for
    /// ([`crate::ps::interreflection`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub interreflections: Option<super::InterreflectionSummary>,
    /// How a run streamed in row bands used memory ([`crate::run::stream::StreamPlan`]); absent
    /// for in-memory runs.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub streaming: Option<serde_json::Value>,
    /// What the near-light solve did, when it ran ([`crate::ps::near`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub near: Option<super::NearSummary>,
}

/// The input as the outputs describe it: the lights (for the EXR headers) and the report's
/// input section.
pub(crate) struct Described<'a> {
    /// One light per image.
    pub lights: &'a crate::capture::lights::Lights,
    /// The report's `inputs`.
    pub summary: InputSummary,
    /// The report's `streaming` section (how a streamed run used memory).
    pub streaming: Option<serde_json::Value>,
}

impl<'a> Described<'a> {
    pub(super) fn of(capture: &'a Capture) -> Self {
        Described {
            lights: &capture.lights,
            summary: InputSummary::of(capture),
            streaming: None,
        }
    }
}

/// What the report says of a run besides its input, configuration and outputs.
#[derive(Debug, Clone)]
pub(crate) struct RunSummary {
    /// Pixel outcome counts.
    pub pixels: StatusCounts,
    /// How much model the data needed.
    pub model: ModelSummary,
    /// Pixels with albedo above 1.
    pub albedo_above_one: usize,
    /// Model residual over solved pixels.
    pub residual: ResidualSummary,
    /// The integrability check.
    pub integrability: IntegrabilitySummary,
    /// Stage timings.
    pub timings: Timings,
    /// Warnings raised (in the file, as their text).
    pub warnings: Vec<Warning>,
    /// What interreflection compensation did.
    pub interreflections: Option<super::InterreflectionSummary>,
    /// What the near-light solve did.
    pub near: Option<super::NearSummary>,
}

impl RunSummary {
    /// The summary of an in-memory reconstruction.
    pub(super) fn of(recon: &Reconstruction) -> Self {
        let res = crate::stats::summarize(&recon.maps.residual);
        RunSummary {
            pixels: recon.counts,
            model: recon.model.clone(),
            albedo_above_one: recon.albedo_above_one,
            residual: ResidualSummary {
                mean: res.mean,
                median: res.median,
            },
            integrability: recon.integrability,
            timings: recon.timings,
            warnings: recon.warnings.clone(),
            interreflections: recon.interreflections.clone(),
            near: recon.near.clone(),
        }
    }
}

/// Stages `report.json` and moves every staged file into place; returns the report.
pub(crate) fn commit_with_report(
    mut out: OutputDir,
    run: RunSummary,
    integration: Option<&Integration>,
    source: &Described,
    config: &Config,
    evaluation: Option<serde_json::Value>,
) -> Result<Report> {
    let mut outputs: Vec<String> = OUTPUT_FILES
        .iter()
        .filter(|f| integration.is_some() || !f.starts_with("depth."))
        .map(|s| s.to_string())
        .collect();
    if config.mesh && integration.is_some() {
        outputs.push("mesh.ply".into());
    }
    outputs.push("report.html".into());
    let r_integrated = integration.map_or(0, |i| {
        i.depth.data().iter().filter(|v| v.is_finite()).count()
    });
    let integration = integration.zip(config.integration.as_ref()).map(|(i, o)| {
        let r = crate::stats::summarize(&i.residual);
        IntegrationSummary {
            method: i.auto.map_or(o.method, |d| d.chosen).name(),
            auto: i.auto.map(|d| AutoSummary {
                decision: d,
                reason: d.reason(),
            }),
            perspective: o.camera.is_some(),
            solve: i.solve,
            iterations: i.iterations,
            closed_off: i.closed_off,
            mean_residual: r.mean,
            median_residual: r.median,
        }
    });
    let mut run = run;
    if let Some(w) = integration
        .as_ref()
        .and_then(|i| i.solve)
        .and_then(crate::run::Warning::of_solve)
    {
        run.warnings.push(w);
    }
    if let Some(w) = integration
        .as_ref()
        .and_then(|i| i.closed_off.map(|c| (c, r_integrated)))
        .and_then(|(c, n)| crate::run::Warning::of_closed_off(c, n))
    {
        run.warnings.push(w);
    }
    let report = Report {
        version: env!("CARGO_PKG_VERSION"),
        inputs: source.summary.clone(),
        config: *config,
        pixels: run.pixels,
        model: run.model,
        albedo_above_one: run.albedo_above_one,
        residual: run.residual,
        integrability: run.integrability,
        timings_s: run.timings,
        warnings: run.warnings,
        integration,
        outputs,
        evaluation,
        interreflections: run.interreflections,
        streaming: source.streaming.clone(),
        near: run.near,
    };
    let encode_error = |e: serde_json::Error| Error::Encode {
        path: out.path().join("report.json"),
        reason: e.to_string(),
    };
    let mut value = serde_json::to_value(&report).map_err(encode_error)?;
    // A grey stack has no colour solve: `config.color` says so rather than naming the
    // colour solve a 3-channel stack would have had.
    if report.inputs.color == ColorMode::Grey {
        value["config"]["color"] = serde_json::Value::from("grey");
    }
    let json = serde_json::to_vec_pretty(&value).map_err(encode_error)?;
    out.stage_bytes("report.json", &json)?;
    // The page is made from the staged files and is part of the set.
    crate::run::html::stage_report_html(&mut out, &report)?;
    out.commit()?;
    Ok(report)
}
