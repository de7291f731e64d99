//! The capture-wide checks of a solve, in a form that adds up over the parts of a capture.
//!
//! Two checks of a solve are judged over the whole capture, not pixel by pixel: the light left
//! in the attached shadows ([`crate::ps::ambient`]) and each light against the others
//! ([`crate::ps::light_agreement`]). Both rest on counts and sums that add up over any split of
//! the pixels, which is how a streamed run judges its row bands as one. A capture solved in
//! parts elsewhere — spatial tiles on the workers of a cluster (the Python package's
//! `photostereo.dask`) — needs the same: each part's [`CaptureChecks`] is written as text
//! ([`CaptureChecks::to_json`]), carried to one place, read back ([`CaptureChecks::from_json`])
//! and added ([`CaptureChecks::add`]); the total then says what the whole capture's solve would
//! ([`CaptureChecks::warnings`]).
//!
//! The other warnings of a run go with them ([`PartCounts`]): the counts of saturated and
//! non-finite samples and of the pixels left without a normal add up over the parts too, and
//! the warnings about the capture as a whole (the images' encoding, lights behind the surface,
//! corrected intensities), which every part gives alike, are carried as their sentences and said
//! once ([`CaptureChecks::sentences`]). Not carried: the integrability check (its median |curl|
//! needs the assembled map's neighbours across the parts), and saturated samples outside every
//! part's mask (each part reads the bounding box of its own mask, the whole run that of the whole
//! mask).
//!
//! The sums are integers (counts, and fixed-point totals of each row's floating-point sums), so
//! the order in which the parts are added does not change the result. Row bands add up to the
//! whole bit for bit; tiles split rows, and then each part of a row is rounded to the fixed
//! point on its own: the directions agree with the whole's to about 10⁻¹². The lights' check
//! reads every fourth column of a part, so tiles read the pixels the whole reads only where
//! their left edges lie on multiples of four (a tile side that is a multiple of four); other
//! tiles read other pixels of the same capture, and the check agrees with the whole's to what
//! such a sampling moves it (reading a quarter of the pixels instead of all moved DiLiGenT's
//! disagreements by at most 0.06–0.36°).

use crate::error::{Error, Result};
use crate::ps::ambient::{ShadowLight, ShadowLightCounts};
use crate::ps::light_agreement::{LightAgreement, LightAgreementSums};
use crate::run::pipeline::{ModelSummary, Reconstruction};
use crate::run::warnings::{SampleCounts, Warning, of_checks, of_counts};
use serde::{Deserialize, Serialize};

/// The capture-wide checks of a solve or of a part of one, one measurement per solved channel.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CaptureChecks {
    /// The light in the attached shadows, per channel.
    pub shadow_light: Vec<ShadowLight>,
    /// Each light checked against the others, per channel.
    pub light_agreement: Vec<LightAgreement>,
    /// What the part adds to the run's other warnings.
    pub counts: PartCounts,
}

/// What a part of a run adds to the run's warnings besides its checks: the counts that add up
/// over the parts, and the warnings about the capture as a whole, which every part gives alike,
/// as sentences (in the report's order: before the counts', after them, and after the checks').
///
/// Parts of a near-light run are not added up alike: their lights' check (of positions, fitted
/// over the whole image) is not carried, and a part that stops at its iteration cap says so
/// with its own numbers, one sentence a part. Photometric stereo in parts is distant-light
/// only (`photostereo.dask` takes directions).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PartCounts {
    /// Sample and pixel counts.
    pub samples: SampleCounts,
    /// Pixels with an albedo above 1 (counted where the albedo is normalised, 0 elsewhere).
    pub albedo_above_one: usize,
    /// Warnings about the images and the lights: their encoding, lights behind the surface,
    /// positioned lights.
    pub inputs: Vec<String>,
    /// Warnings about the capture-wide model: the light intensities.
    pub model: Vec<String>,
    /// Warnings of the later stages (interreflections, near lights, integration).
    pub later: Vec<String>,
}

impl PartCounts {
    /// The counts of a finished run (of the whole capture or of a part), and its warnings about
    /// the capture as a whole.
    pub fn of(run: &Reconstruction) -> Self {
        let mut c = PartCounts {
            samples: SampleCounts {
                pixels: run.counts,
                ..SampleCounts::default()
            },
            ..PartCounts::default()
        };
        for w in &run.warnings {
            match w {
                Warning::Saturated { samples, used } => {
                    c.samples.saturated += samples;
                    c.samples.saturated_used |= used;
                }
                Warning::NonFinite { samples } => c.samples.non_finite += samples,
                Warning::Unsolved { no_mask, .. } => c.samples.no_mask |= no_mask,
                Warning::AlbedoAboveOne { pixels } => c.albedo_above_one += pixels,
                // From the pixel counts, the checks' sums, or (the integrability check) not
                // carried.
                Warning::Filled { .. }
                | Warning::ShadowLight { .. }
                | Warning::LightsDisagree { .. }
                | Warning::PoorIntegrability { .. } => {}
                Warning::SrgbDecoded { .. }
                | Warning::LightsBehind { .. }
                | Warning::NearLights { .. }
                | Warning::Lossy { .. } => c.inputs.push(w.to_string()),
                Warning::IntensitiesCorrected { .. } | Warning::IntensitiesNotApplied { .. } => {
                    c.model.push(w.to_string())
                }
                Warning::NearNotConverged { .. }
                | Warning::InterreflectionScaleAtLimit
                | Warning::IntegrationNotConverged { .. }
                | Warning::WithoutNormal { .. }
                | Warning::DepthOffsetsGuessed { .. } => c.later.push(w.to_string()),
            }
        }
        c
    }

    /// Adds another part's counts, and its sentences that this one does not hold yet; `None`
    /// (and `self` unchanged) when a count overflows.
    fn try_add(&mut self, other: &PartCounts) -> Option<()> {
        let mut samples = self.samples;
        samples.try_add(&other.samples)?;
        let albedo_above_one = self.albedo_above_one.checked_add(other.albedo_above_one)?;
        self.samples = samples;
        self.albedo_above_one = albedo_above_one;
        for (mine, theirs) in [
            (&mut self.inputs, &other.inputs),
            (&mut self.model, &other.model),
            (&mut self.later, &other.later),
        ] {
            for text in theirs {
                if !mine.contains(text) {
                    mine.push(text.clone());
                }
            }
        }
        Some(())
    }

    /// Whether the pixel counts add up (each pixel of the mask has one outcome).
    fn consistent(&self) -> bool {
        let p = &self.samples.pixels;
        [p.too_few_samples, p.ill_conditioned, p.dark, p.filled]
            .iter()
            .try_fold(p.solved, |sum, &n| sum.checked_add(n))
            == Some(p.masked)
            && self.albedo_above_one <= p.masked
    }
}

/// The text form: the counts and sums themselves.
#[derive(Serialize, Deserialize)]
struct Parts {
    shadow_light: Vec<ShadowLightCounts>,
    light_agreement: Vec<LightAgreementSums>,
    counts: PartCounts,
}

impl CaptureChecks {
    /// The checks of a finished solve (of the whole capture or of a part), without its counts
    /// ([`CaptureChecks::of_run`] has them). The lights' check of a near-light solve is of the
    /// whole image only (it holds positions fitted in several passes, not sums) and is left
    /// out.
    pub fn of(model: &ModelSummary) -> Self {
        CaptureChecks {
            shadow_light: model.shadow_light.clone(),
            light_agreement: model
                .light_agreement
                .iter()
                .filter(|a| !a.is_near())
                .cloned()
                .collect(),
            counts: PartCounts::default(),
        }
    }

    /// The checks of a finished run (of the whole capture or of a part) and its counts
    /// ([`PartCounts::of`]).
    pub fn of_run(run: &Reconstruction) -> Self {
        CaptureChecks {
            counts: PartCounts::of(run),
            ..CaptureChecks::of(&run.model)
        }
    }

    /// The counts and sums as JSON text, to be carried to where the parts are added.
    pub fn to_json(&self) -> String {
        let parts = Parts {
            shadow_light: self.shadow_light.iter().map(|s| s.counts()).collect(),
            light_agreement: self.light_agreement.iter().map(|a| a.sums()).collect(),
            counts: self.counts.clone(),
        };
        // Plain data (integers, floats, vectors): serialising it cannot fail.
        serde_json::to_string(&parts).unwrap_or_default()
    }

    /// Reads what [`CaptureChecks::to_json`] wrote; `checks` names the text in the error.
    pub fn from_json(text: &str) -> Result<Self> {
        let bad = |why: String| {
            Error::param(
                "checks",
                format!("not the checks of a photostereo solve of this version: {why}"),
            )
        };
        let parts: Parts = serde_json::from_str(text).map_err(|e| bad(e.to_string()))?;
        let shadow_light = parts
            .shadow_light
            .into_iter()
            .map(ShadowLight::from_counts)
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| bad("a shadow-light histogram of another size".into()))?;
        let light_agreement = parts
            .light_agreement
            .into_iter()
            .map(LightAgreement::from_sums)
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| bad("light sums that do not match the lights".into()))?;
        if !parts.counts.consistent() {
            return Err(bad("pixel counts that do not add up to the mask's".into()));
        }
        Ok(CaptureChecks {
            shadow_light,
            light_agreement,
            counts: parts.counts,
        })
    }

    /// Adds the checks and counts of another part of the same capture (solved with the same
    /// lights and colour channels). A part with no checks at all (no solved pixel, nothing
    /// measured) adds its counts only.
    pub fn add(&mut self, other: &CaptureChecks) -> Result<()> {
        let overflow = || {
            Error::param(
                "checks",
                "the parts' counts overflow: more parts than one capture can have",
            )
        };
        let mut counts = self.counts.clone();
        counts.try_add(&other.counts).ok_or_else(overflow)?;
        if other.shadow_light.is_empty() && other.light_agreement.is_empty() {
            self.counts = counts;
            return Ok(());
        }
        if self.shadow_light.is_empty() && self.light_agreement.is_empty() {
            self.shadow_light.clone_from(&other.shadow_light);
            self.light_agreement.clone_from(&other.light_agreement);
            self.counts = counts;
            return Ok(());
        }
        if self.shadow_light.len() != other.shadow_light.len()
            || self.light_agreement.len() != other.light_agreement.len()
        {
            return Err(Error::param(
                "checks",
                format!(
                    "a part with {} and {} checked channels added to one with {} and {}: parts of different solves",
                    other.shadow_light.len(),
                    other.light_agreement.len(),
                    self.shadow_light.len(),
                    self.light_agreement.len()
                ),
            ));
        }
        for (c, (a, b)) in self
            .light_agreement
            .iter()
            .zip(&other.light_agreement)
            .enumerate()
        {
            let (a, b) = (a.given(), b.given());
            if a.len() != b.len() {
                return Err(Error::param(
                    "checks",
                    format!(
                        "channel {}: a part checked against {} lights added to one of {}: parts of different solves",
                        c + 1,
                        b.len(),
                        a.len()
                    ),
                ));
            }
            if let Some(k) = a.iter().zip(b).position(|(x, y)| x != y) {
                return Err(Error::param(
                    "checks",
                    format!(
                        "channel {}: a part checked against other lights (light {} differs): parts of different solves",
                        c + 1,
                        k + 1
                    ),
                ));
            }
        }
        // Into a copy, so that a failed addition leaves the total as it was.
        let mut sum = self.clone();
        for (a, b) in sum.shadow_light.iter_mut().zip(&other.shadow_light) {
            a.try_add(b).ok_or_else(overflow)?;
        }
        for (a, b) in sum.light_agreement.iter_mut().zip(&other.light_agreement) {
            a.try_add(b).ok_or_else(overflow)?;
        }
        sum.counts = counts;
        *self = sum;
        Ok(())
    }

    /// What the checks warn of, as a whole run's report would say it; `ambient_subtracted`: the
    /// frame taken with every lamp off was subtracted from the images.
    pub fn warnings(&self, ambient_subtracted: bool) -> Vec<Warning> {
        of_checks(
            self.shadow_light.iter(),
            self.light_agreement.iter(),
            ambient_subtracted,
        )
    }

    /// Every warning the parts give the whole run, as its report says them and in its order:
    /// those about the images and lights, the sample and pixel counts', the intensities',
    /// the checks' ([`CaptureChecks::warnings`]), albedo above 1, and the later stages'.
    pub fn sentences(&self, ambient_subtracted: bool) -> Vec<String> {
        let c = &self.counts;
        let mut out = c.inputs.clone();
        out.extend(of_counts(&c.samples).iter().map(|w| w.to_string()));
        out.extend(c.model.iter().cloned());
        out.extend(
            self.warnings(ambient_subtracted)
                .iter()
                .map(|w| w.to_string()),
        );
        if c.albedo_above_one > 0 {
            out.push(
                Warning::AlbedoAboveOne {
                    pixels: c.albedo_above_one,
                }
                .to_string(),
            );
        }
        out.extend(c.later.iter().cloned());
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::lights::{Light, Lights};
    use crate::ps::test_support::{band, rendered_and_solved};
    use crate::synth::reflectance::Material;
    use crate::synth::render::RenderOptions;
    use crate::synth::scene::{Albedo, SceneKind};
    use nalgebra::Vector3;

    /// A capture whose first six images are 15% dimmer than their lights say, with a row of
    /// saturated samples in another, pixels lit by two lights only and a light behind the
    /// surface, solved whole and in 16² tiles (parts of the arrays, under
    /// the whole's models, as `photostereo.dask` solves them): the tiles' checks and counts,
    /// written as text, read back and added, give the whole run's warnings sentence for
    /// sentence (all but the integrability check's, which is not carried), and its pixel
    /// counts; a tile whose text says more pixels have an outcome than its mask holds is
    /// refused.
    #[test]
    fn tiles_added_give_the_whole_runs_warnings() {
        use crate::capture::Capture;
        use crate::capture::stack::LoadOptions;
        use crate::progress::Silent;
        use crate::run::pipeline::{Config, estimate_models, reconstruct_normals_with_models};
        use ndarray::{Array3, Axis, s};
        let n = 48;
        let scene = SceneKind::Sphere.build(n, Albedo::Constant(0.6), Material::lambertian());
        let rendered = Lights::fibonacci(16, 35.0).unwrap();
        let options = RenderOptions {
            noise_sigma: 0.003,
            seed: 9,
            ..RenderOptions::default()
        };
        let r = crate::synth::render::render(&scene, &rendered, &options).unwrap();
        // A 17th light behind the surface, lighting the rim that turns towards it: a warning
        // about the capture, which every tile gives.
        let behind = Vector3::new(0.3, 0.2, -0.5).normalize();
        let mut all: Vec<Light> = rendered.directions().into_iter().map(Light::new).collect();
        all.push(Light::new(behind));
        let lights = Lights::new(all).unwrap();
        let level = 0.7;
        let mut images = Array3::from_shape_fn((17, n, n), |(k, y, x)| {
            if k == 16 {
                let normal = r.truth.normals.at(x, y).cast::<f64>();
                return if *r.truth.mask.at(x, y) {
                    (0.6 * normal.dot(&behind).max(0.0)) as f32
                } else {
                    0.0
                };
            }
            let v = *r.images[k][0].at(x, y) * if k < 6 { 0.85 } else { 1.0 };
            v.min(level)
        });
        for k in 2..17 {
            for (y, x) in [(20, 20), (21, 20), (30, 12)] {
                images[[k, y, x]] = 0.0;
            }
        }
        for x in 10..40 {
            images[[9, 24, x]] = level;
        }
        let mask = ndarray::Array2::from_shape_fn((n, n), |(y, x)| *r.truth.mask.at(x, y));
        let load = LoadOptions {
            saturation: Some(level),
            ..LoadOptions::default()
        };
        let mut config = Config {
            integration: None,
            ..Config::default()
        };
        config.solve.fill = false;
        let whole =
            Capture::from_arrays(images.view(), lights.clone(), Some(mask.view()), &load).unwrap();
        let models = estimate_models(&whole, &config).unwrap();
        let run = reconstruct_normals_with_models(&whole, &config, Some(&models), &Silent).unwrap();
        let said: Vec<String> = run
            .warnings
            .iter()
            .filter(|w| !matches!(w, Warning::PoorIntegrability { .. }))
            .map(|w| w.to_string())
            .collect();
        for kind in [
            "behind",
            " saturated samples",
            "pixels have no normal",
            "intensit",
        ] {
            assert!(said.iter().any(|w| w.contains(kind)), "{kind}: {said:?}");
        }
        let mut total = CaptureChecks::default();
        let mut parts = 0;
        for y0 in (0..n).step_by(16) {
            for x0 in (0..n).step_by(16) {
                let m = mask.slice(s![y0..y0 + 16, x0..x0 + 16]);
                if !m.iter().any(|&b| b) {
                    continue;
                }
                let tile = images.slice(s![.., y0..y0 + 16, x0..x0 + 16]);
                let part = Capture::from_arrays_part(
                    tile.insert_axis(Axis(3)),
                    lights.clone(),
                    Some(m),
                    &load,
                )
                .unwrap();
                let run = reconstruct_normals_with_models(&part, &config, Some(&models), &Silent)
                    .unwrap();
                let text = CaptureChecks::of_run(&run).to_json();
                total
                    .add(&CaptureChecks::from_json(&text).unwrap())
                    .unwrap();
                parts += 1;
            }
        }
        assert_eq!(parts, 9);
        assert_eq!(total.counts.samples.pixels, run.counts);
        assert_eq!(total.sentences(false), said);
        // Said once however many parts say it: each of the capture's own warnings came from
        // all nine tiles.
        assert_eq!(total.counts.inputs.len(), 1, "{:?}", total.counts.inputs);
        assert_eq!(total.counts.model.len(), 1, "{:?}", total.counts.model);
        let again = total.clone();
        total.add(&again).unwrap();
        assert_eq!(total.counts.inputs, again.counts.inputs);
        assert_eq!(total.counts.model, again.counts.model);
        let mut v: serde_json::Value = serde_json::from_str(&again.to_json()).unwrap();
        v["counts"]["samples"]["pixels"]["solved"] = (run.counts.masked + 1).into();
        let e = CaptureChecks::from_json(&v.to_string())
            .unwrap_err()
            .to_string();
        assert!(e.contains("do not add up"), "{e}");
    }

    /// Room light in the images and one row of the lights turned by 10°: the checks of three
    /// bands of rows, written as text, read back and added in another order, are the whole
    /// solve's (the same counts, sums and warnings, both of them); parts of another solve are
    /// refused, and so is text that is not the checks.
    #[test]
    fn parts_written_read_and_added_are_the_whole() {
        let scene = SceneKind::Relief.build(64, Albedo::Constant(0.7), Material::lambertian());
        let lights = Lights::fibonacci(16, 25.0).unwrap();
        let mut given = lights.directions();
        let l = given[3];
        let axis = nalgebra::Unit::new_normalize(l.cross(&Vector3::z()));
        given[3] = nalgebra::Rotation3::from_axis_angle(&axis, 10f64.to_radians()) * l;
        let used = Lights::new(given.into_iter().map(Light::new).collect()).unwrap();
        let options = RenderOptions {
            noise_sigma: 0.003,
            ambient: 0.08,
            seed: 4,
            ..RenderOptions::default()
        };
        let (r, stack, sol) = rendered_and_solved(&scene, &lights, &used, &options);
        let mask = &r.truth.mask;
        let checks_of = |m: &crate::grid::Mask| CaptureChecks {
            shadow_light: vec![crate::ps::ambient::measure(&stack, 0, &used, m, &sol)],
            light_agreement: vec![crate::ps::light_agreement::measure(
                &stack, 0, &used, m, &sol,
            )],
            counts: PartCounts::default(),
        };
        let whole = checks_of(mask);
        let warned = whole.warnings(false);
        assert!(
            warned
                .iter()
                .any(|w| matches!(w, Warning::ShadowLight { .. }))
                && warned.iter().any(
                    |w| matches!(w, Warning::LightsDisagree { lights, .. } if lights[0].0 == 3)
                ),
            "{warned:?}"
        );
        let mut total = CaptureChecks::default();
        for (y0, y1) in [(40, 64), (0, 17), (17, 40)] {
            let text = checks_of(&band(mask, y0, y1)).to_json();
            total
                .add(&CaptureChecks::from_json(&text).unwrap())
                .unwrap();
        }
        total.add(&CaptureChecks::default()).unwrap();
        assert_eq!(total, whole);
        assert_eq!(total.warnings(false), warned);

        // Another solve's parts: checked against other lights, or with another channel count.
        let mut other = whole.clone();
        other.light_agreement = vec![crate::ps::light_agreement::measure(
            &stack, 0, &lights, mask, &sol,
        )];
        let e = total.add(&other).unwrap_err().to_string();
        assert!(e.contains("other lights"), "{e}");
        other = whole.clone();
        other.shadow_light.push(other.shadow_light[0].clone());
        let e = total.add(&other).unwrap_err().to_string();
        assert!(e.contains("different solves"), "{e}");
        for text in ["", "{}", "[1, 2]"] {
            let e = CaptureChecks::from_json(text).unwrap_err().to_string();
            assert!(e.contains("checks") && e.contains("not the checks"), "{e}");
        }
        // Text that is not what a solve wrote: a histogram of another size, pixels that are
        // not its total, sums for fewer lights than given, a sum out of range.
        let text = whole.to_json();
        let edit = |f: &dyn Fn(&mut serde_json::Value)| {
            let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
            f(&mut v);
            CaptureChecks::from_json(&v.to_string())
        };
        assert!(edit(&|_| {}).is_ok());
        let bad: [&dyn Fn(&mut serde_json::Value); 4] = [
            &|v| {
                v["shadow_light"][0]["histogram"]
                    .as_array_mut()
                    .unwrap()
                    .pop();
            },
            &|v| v["shadow_light"][0]["pixels"] = 56.into(),
            &|v| {
                v["light_agreement"][0]["sums"]
                    .as_array_mut()
                    .unwrap()
                    .pop();
            },
            &|v| v["light_agreement"][0]["sums"][0][0][0] = i64::MAX.into(),
        ];
        for f in bad {
            let e = edit(f).unwrap_err().to_string();
            assert!(e.contains("not the checks"), "{e}");
        }
    }
}
