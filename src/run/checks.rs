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
use crate::run::pipeline::ModelSummary;
use crate::run::warnings::{Warning, of_checks};
use serde::{Deserialize, Serialize};

/// The capture-wide checks of a solve or of a part of one, one measurement per solved channel.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CaptureChecks {
    /// The light in the attached shadows, per channel.
    pub shadow_light: Vec<ShadowLight>,
    /// Each light checked against the others, per channel.
    pub light_agreement: Vec<LightAgreement>,
}

/// The text form: the counts and sums themselves.
#[derive(Serialize, Deserialize)]
struct Parts {
    shadow_light: Vec<ShadowLightCounts>,
    light_agreement: Vec<LightAgreementSums>,
}

impl CaptureChecks {
    /// The checks of a finished solve (of the whole capture or of a part). The lights' check
    /// of a near-light solve is of the whole image only (it holds positions fitted in
    /// several passes, not sums) and is left out.
    pub fn of(model: &ModelSummary) -> Self {
        CaptureChecks {
            shadow_light: model.shadow_light.clone(),
            light_agreement: model
                .light_agreement
                .iter()
                .filter(|a| !a.is_near())
                .cloned()
                .collect(),
        }
    }

    /// The counts and sums as JSON text, to be carried to where the parts are added.
    pub fn to_json(&self) -> String {
        let parts = Parts {
            shadow_light: self.shadow_light.iter().map(|s| s.counts()).collect(),
            light_agreement: self.light_agreement.iter().map(|a| a.sums()).collect(),
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
        Ok(CaptureChecks {
            shadow_light,
            light_agreement,
        })
    }

    /// Adds the checks of another part of the same capture (solved with the same lights and
    /// colour channels). A part with no checks at all (no solved pixel, nothing measured) adds
    /// nothing.
    pub fn add(&mut self, other: &CaptureChecks) -> Result<()> {
        if other.shadow_light.is_empty() && other.light_agreement.is_empty() {
            return Ok(());
        }
        if self.shadow_light.is_empty() && self.light_agreement.is_empty() {
            self.clone_from(other);
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
        let overflow = || {
            Error::param(
                "checks",
                "the parts' counts overflow: more parts than one capture can have",
            )
        };
        let mut sum = self.clone();
        for (a, b) in sum.shadow_light.iter_mut().zip(&other.shadow_light) {
            a.try_add(b).ok_or_else(overflow)?;
        }
        for (a, b) in sum.light_agreement.iter_mut().zip(&other.light_agreement) {
            a.try_add(b).ok_or_else(overflow)?;
        }
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
