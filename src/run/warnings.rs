//! The warnings of a run: what the user should know about a result that was still computed
//! (input conversions, saturation, unsolved pixels, intensity corrections, integrability,
//! albedo above 1), as data.
//!
//! Each [`Warning`] carries its numbers and displays as a sentence in the library's own terms;
//! `report.json` holds that sentence. A front end adds what its user can do about it: the
//! command-line tool names the flag (`--linear`, `--mask`, …), a notebook would name the
//! argument.

use crate::ps::ambient::ShadowLight;
use crate::ps::light_agreement::LightAgreement;
use crate::ps::normals::IntegrabilitySummary;
use crate::ps::solve::Method;
use crate::ps::solve::StatusCounts;
use crate::run::pipeline::{ChannelModel, Config, GAIN_WARNING, InputFacts, POOR_CURL, Tallies};
use serde::{Deserialize, Serialize, Serializer};
use std::fmt;

/// Something the user should know about a run whose result was still computed.
#[derive(Debug, Clone, PartialEq)]
pub enum Warning {
    /// 8-bit images were decoded as sRGB-encoded data (they may hold linear radiance).
    SrgbDecoded {
        /// Images decoded so.
        images: usize,
    },
    /// Lights behind the surface (z < 0; fewer than half of them, else the run is refused).
    LightsBehind {
        /// Their indices.
        lights: Vec<usize>,
        /// Lights in all.
        count: usize,
    },
    /// Lights given with positions (near lights), used by their directions.
    NearLights {
        /// Lights with a position.
        positioned: usize,
        /// Lights in all.
        count: usize,
    },
    /// The near-light solve stopped at its iteration cap.
    NearNotConverged {
        /// Alternations made.
        iterations: usize,
        /// The last alternation's RMS depth change over the depth range.
        change: f64,
    },
    /// JPEG images: lossy, 8-bit, sRGB-encoded.
    Lossy {
        /// JPEG images among the inputs.
        images: usize,
    },
    /// Samples at or above the saturation level.
    Saturated {
        /// Saturated samples over all images.
        samples: usize,
        /// Whether the estimator used them (plain least squares) instead of excluding them.
        used: bool,
    },
    /// NaN or infinite samples, excluded from the solve.
    NonFinite {
        /// Such samples over all images.
        samples: usize,
    },
    /// Pixels of the mask left without a normal.
    Unsolved {
        /// Pixels without a normal.
        unsolved: usize,
        /// Pixels in the mask.
        masked: usize,
        /// With fewer than three usable samples.
        too_few_samples: usize,
        /// With ill-conditioned lights.
        ill_conditioned: usize,
        /// Dark in every image.
        dark: usize,
        /// No mask was given, so the background counts as object.
        no_mask: bool,
    },
    /// Pixels of the mask too poorly determined to be solved alone, filled in from their few
    /// samples and their solved neighbours.
    Filled {
        /// Pixels filled.
        filled: usize,
        /// Pixels in the mask.
        masked: usize,
    },
    /// The images' brightness disagrees with the stated light intensities; the estimated
    /// corrections were applied.
    IntensitiesCorrected {
        /// The images (numbered from 0) whose gain is further than [`GAIN_WARNING`] from 1.
        images: Vec<usize>,
        /// The gain furthest from 1.
        worst: f32,
    },
    /// Intensities estimated from the images differ from the stated ones but were not applied:
    /// the estimate did not converge, or the robust fits explain the samples they keep as well
    /// under the stated ones, or (the rest of the estimate applied or not) the fits set the
    /// image aside whole and it was measured afterwards ([`crate::ps::intensities`]).
    IntensitiesNotApplied {
        /// The images (numbered from 0) whose estimated gain differs from the gain applied
        /// (1 where nothing was) by a factor further than [`GAIN_WARNING`] from 1.
        images: Vec<usize>,
        /// That factor furthest from 1.
        worst: f32,
    },
    /// The samples in attached shadow hold light — ambient light, a black level,
    /// interreflections — enough to turn the normals by [`SHADOW_LIGHT_WARN_DEG`] or more on
    /// average ([`crate::ps::ambient`]).
    ShadowLight {
        /// The level, a fraction of a lit surface's brightness (negative: below zero).
        level: f64,
        /// Pixels it was measured over.
        pixels: usize,
        /// The mean angle (degrees) such an offset turns the normals by.
        bias_deg: f64,
        /// An ambient image was subtracted already.
        ambient_subtracted: bool,
    },
    /// Images whose brightness the other images' normals explain by a light direction far
    /// from the given one, beyond what chance gives the other lights
    /// ([`crate::ps::light_agreement`]).
    LightsDisagree {
        /// Per light (numbered from 0): its disagreement (degrees) and the unit direction that
        /// explains its image best — for near lights, the position.
        lights: Vec<(usize, f64, [f64; 3])>,
        /// The lights are near ones, checked by their positions (the disagreement is an angle
        /// seen from the object's centre).
        positions: bool,
        /// The median disagreement over the lights, degrees.
        median_deg: f64,
        /// The disagreement beyond which a light is named, degrees.
        threshold_deg: f64,
        /// The colour channel (from 0) and the channels solved, when each channel was solved on
        /// its own and more than one is: the channel with the most lights named.
        channel: Option<(usize, usize)>,
    },
    /// The median |curl| of the gradient field is above [`POOR_CURL`].
    PoorIntegrability {
        /// Median |curl| per pixel.
        median_abs_curl: f64,
    },
    /// Pixels with albedo above 1 although the intensities were declared normalised.
    AlbedoAboveOne {
        /// Such pixels.
        pixels: usize,
    },
    /// The interreflection compensation's reflectance scale was estimated at the top of its
    /// search, the brightest pixel's reflectance 1 ([`crate::ps::interreflection`]): the data
    /// asked for at least that much, so the residual may be answering to more than
    /// interreflections and the compensation may be too strong.
    InterreflectionScaleAtLimit,
    /// The depth's linear solve stopped before it converged (conjugate gradients at their
    /// iteration limit or broken down): the depth is the last iterate's.
    IntegrationNotConverged {
        /// The integrator's solver (its name).
        solver: &'static str,
        /// Iterations made.
        iterations: usize,
        /// Why it stopped.
        convergence: crate::integrate::Convergence,
    },
    /// Pixels of the mask given to the integration without a normal (NaN, or the zero vector
    /// that normal maps store for none): left without depth.
    WithoutNormal {
        /// Such pixels.
        pixels: usize,
        /// Pixels in the mask.
        masked: usize,
    },
    /// The discontinuity-preserving integrator's cuts close regions off all around
    /// ([`crate::integrate::ClosedOff`]): their depth offset relative to the rest is not in the
    /// normals, and the depth differences across those cuts are a guess (the least jump).
    DepthOffsetsGuessed {
        /// Regions closed off.
        regions: usize,
        /// Their pixels.
        pixels: usize,
        /// Pixels of the largest.
        largest: usize,
        /// Pixels integrated in all.
        integrated: usize,
    },
}

impl Warning {
    /// The warning an integration with closed-off regions calls for
    /// ([`Warning::DepthOffsetsGuessed`]), `integrated` the pixels with a depth: when the
    /// regions closed off hold at least [`GUESSED_SHARE`] of them (below that they are a few
    /// grazing rim pixels each, which the counts in the report still list).
    pub fn of_closed_off(
        closed: crate::integrate::ClosedOff,
        integrated: usize,
    ) -> Option<Warning> {
        let share = closed.pixels as f64 / integrated.max(1) as f64;
        (closed.regions > 0 && share >= GUESSED_SHARE).then_some(Warning::DepthOffsetsGuessed {
            regions: closed.regions,
            pixels: closed.pixels,
            largest: closed.largest,
            integrated,
        })
    }

    /// The warning integrating `normals` over `mask` calls for: [`Warning::WithoutNormal`]
    /// when some pixels of the mask have no normal ([`crate::integrate::usable_normal`]), else
    /// none.
    pub fn of_normals(
        normals: &crate::grid::NormalMap,
        mask: &crate::grid::Mask,
    ) -> Option<Warning> {
        let (mut masked, mut pixels) = (0, 0);
        for (n, &m) in normals.data().iter().zip(mask.data()) {
            if m {
                masked += 1;
                pixels += usize::from(!crate::integrate::usable_normal(n));
            }
        }
        (pixels > 0).then_some(Warning::WithoutNormal { pixels, masked })
    }

    /// The warnings that integrating `normals` over `mask` into `result` calls for, in this
    /// order: pixels of the mask without a normal ([`Warning::of_normals`]), a linear solve
    /// that stopped before converging ([`Warning::of_solve`]), regions whose depth offset is a
    /// guess ([`Warning::of_closed_off`]).
    pub fn of_integration(
        normals: &crate::grid::NormalMap,
        mask: &crate::grid::Mask,
        result: &crate::integrate::Integration,
    ) -> Vec<Warning> {
        let integrated = result.depth.data().iter().filter(|v| v.is_finite()).count();
        [
            Warning::of_normals(normals, mask),
            result.solve.and_then(Warning::of_solve),
            result
                .closed_off
                .and_then(|c| Warning::of_closed_off(c, integrated)),
        ]
        .into_iter()
        .flatten()
        .collect()
    }

    /// The warning a linear solve of the depth calls for: [`Warning::IntegrationNotConverged`]
    /// when it stopped before converging, else none.
    pub fn of_solve(solve: crate::integrate::SolveInfo) -> Option<Warning> {
        (!solve.convergence.converged()).then_some(Warning::IntegrationNotConverged {
            solver: solve.method.name(),
            iterations: solve.iterations,
            convergence: solve.convergence,
        })
    }
}

/// Mean angle (degrees) by which the light measured in attached shadows would turn the
/// normals, at the level's end nearer zero of its two-standard-error interval
/// ([`crate::ps::ambient::ShadowLight::confident_bias_deg`]), from which a run warns.
/// A degree: on rendered scenes (0.5% noise, 8–48 lights) the error without any offset is
/// 0.2–0.45°, an ambient term of 2% of a lamp's light adds about 0.3–0.8° and one of 5% adds
/// 0.9–2.4°; DiLiGenT cat, bear and reading, whose shadows hold 1.3–2.5% (interreflections
/// and subsurface light, which subtracting would not remove), predict 0.5–1.0° (reading 0.94°
/// at the confident end).
pub const SHADOW_LIGHT_WARN_DEG: f64 = 1.0;

/// Least share of the integrated pixels in regions closed off by depth jumps for which
/// [`Warning::of_closed_off`] warns.
pub const GUESSED_SHARE: f64 = 0.01;

/// Image numbers listed in a warning at most.
const LISTED_IMAGES: usize = 12;

/// The first [`LISTED_IMAGES`] of `images` (numbered from 0) numbered from 1, then an
/// ellipsis if there are more.
fn listed(images: &[usize]) -> String {
    let list: Vec<String> = images
        .iter()
        .take(LISTED_IMAGES)
        .map(|k| (k + 1).to_string())
        .collect();
    let more = if images.len() > LISTED_IMAGES {
        ", …"
    } else {
        ""
    };
    format!("{}{more}", list.join(", "))
}

impl fmt::Display for Warning {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Warning::SrgbDecoded { images } => write!(
                f,
                "{images} 8-bit image(s) were decoded as sRGB-encoded (gamma) data; if they hold linear radiance, declare them linear"
            ),
            Warning::LightsBehind { lights, count } => write!(
                f,
                "light(s) {} of {count} point behind the surface (z < 0; z points from the object towards the camera): they light only surfaces the camera sees at grazing angles; check their sign",
                crate::capture::lights::index_list(lights)
            ),
            Warning::NearLights { positioned, count } => write!(
                f,
                "{positioned} of {count} lights have a position (near lights), but they were solved as distant ones: each was used with its given direction (from two balls: from their midpoint), which is off at a pixel by about the angle the pixel's offset from that point subtends at the light; the near-light model needs every light's position and the camera's intrinsics"
            ),
            Warning::NearNotConverged { iterations, change } => write!(
                f,
                "the near-light solve stopped after {iterations} alternations of normals and depth without converging (the depth still moved by {:.3}% of its range); the normals and depth are those of the last alternation",
                100.0 * change
            ),
            Warning::Lossy { images } => write!(
                f,
                "{images} image(s) are JPEG: 8-bit, sRGB-encoded and lossily compressed; they were decoded and linearised, but their compression artefacts and coarse steps add error to the normals (RAW, 16-bit TIFF/PNG or EXR keep the measurement)"
            ),
            Warning::Saturated { samples, used } => write!(
                f,
                "{samples} saturated samples{}",
                if *used {
                    " (used by plain least squares, which biases normals there)"
                } else {
                    " were excluded from the solve"
                }
            ),
            Warning::NonFinite { samples } => {
                write!(f, "{samples} NaN or infinite samples were excluded")
            }
            Warning::Unsolved {
                unsolved,
                masked,
                too_few_samples,
                ill_conditioned,
                dark,
                no_mask,
            } => write!(
                f,
                "{unsolved} of {masked} pixels have no normal: {too_few_samples} with fewer than 3 usable samples, {ill_conditioned} with ill-conditioned lights, {dark} dark{}",
                if *no_mask {
                    " (no mask was given, so the background counts too)"
                } else {
                    ""
                }
            ),
            Warning::IntegrationNotConverged {
                solver,
                iterations,
                convergence,
            } => write!(
                f,
                "the depth's linear solve ({solver}) stopped after {iterations} iterations {}: the depth is that of its last iterate and may be off by more than the data's noise",
                convergence.describe()
            ),
            Warning::WithoutNormal { pixels, masked } => write!(
                f,
                "{pixels} of the {masked} pixels of the mask have no normal (NaN, or the zero vector that normal maps store for none): they are left without depth"
            ),
            Warning::DepthOffsetsGuessed {
                regions,
                pixels,
                largest,
                integrated,
            } => write!(
                f,
                "depth jumps close {regions} region{} off all around ({pixels} of {integrated} integrated pixels, {:.1}%; the largest {largest}): the normals do not say how far in front of or behind the rest such a region lies, and the depth places it at the least jump across its cut, a guess",
                if *regions == 1 { "" } else { "s" },
                100.0 * *pixels as f64 / (*integrated).max(1) as f64,
            ),
            Warning::InterreflectionScaleAtLimit => write!(
                f,
                "the interreflection compensation's reflectance scale was estimated at its physical limit (the brightest pixel's reflectance 1): the residual may be answering to more than interreflections, so the compensation may be too strong; compare with a run without it, or give the scale"
            ),
            Warning::Filled { filled, masked } => write!(
                f,
                "{filled} of {masked} pixels had too few usable samples or ill-conditioned lights to be solved alone: their normals were filled in from their neighbours and are less reliable (marked in residual.exr, channel filled)"
            ),
            Warning::IntensitiesCorrected { images, worst } => {
                write!(
                    f,
                    "the images' brightness disagrees with the light intensities for {} image(s) (numbered from 1: {}); corrected from the data by factors up to {worst:.2} — check the intensity file",
                    images.len(),
                    listed(images),
                )
            }
            Warning::IntensitiesNotApplied { images, worst } => write!(
                f,
                "the light intensities estimated from the images differ from the stated ones for {} image(s) (numbered from 1: {}) by factors up to {worst:.2}, but that estimate was not applied: it did not converge, or the robust fits explain the samples they keep as well without it, or they set the image aside whole (as they do an image that is off as a whole; strong highlights or interreflections can also cause this); check the intensity file (estimate in report.json → model.estimated_gains)",
                images.len(),
                listed(images),
            ),
            Warning::ShadowLight {
                level,
                pixels,
                bias_deg,
                ambient_subtracted,
            } if *level >= 0.0 => write!(
                f,
                "the samples in attached shadow (whose lamp the surface faces away from) hold {:.1}% of a lit surface's brightness (median over {pixels} pixels){}: light no lamp sends there — ambient light, the camera's black level or interreflections; an offset that every image shares turns the normals towards the lights' mean direction, here by about {bias_deg:.1}° on average{}",
                100.0 * level,
                if *ambient_subtracted {
                    ", after the ambient image was subtracted"
                } else {
                    ""
                },
                if *ambient_subtracted {
                    "; interreflections do this where the surface sees itself, or the ambient image was taken under less light than the images"
                } else {
                    "; if the room was lit or the camera adds an offset, subtract an image taken with every lamp off"
                }
            ),
            Warning::ShadowLight {
                level,
                pixels,
                bias_deg,
                ambient_subtracted,
            } => write!(
                f,
                "the samples in attached shadow (whose lamp the surface faces away from) sit {:.1}% of a lit surface's brightness below zero (median over {pixels} pixels){}: an offset the images did not hold was taken off them, which turns the normals away from the lights' mean direction, here by about {bias_deg:.1}° on average",
                -100.0 * level,
                if *ambient_subtracted {
                    ", after the ambient image was subtracted: was it taken under more light than the images?"
                } else {
                    ""
                }
            ),
            Warning::LightsDisagree {
                lights,
                positions,
                median_deg,
                threshold_deg,
                channel,
            } => {
                let list: Vec<String> = lights
                    .iter()
                    .take(LISTED_IMAGES)
                    .map(|(k, deg, d)| {
                        // A position in the lights' units gets a digit more than a unit vector.
                        let (label, digits) = if *positions {
                            ("position ", 4)
                        } else {
                            ("", 3)
                        };
                        format!(
                            "{} ({deg:.1}° off: {label}({:.*}, {:.*}, {:.*}))",
                            k + 1,
                            digits,
                            d[0],
                            digits,
                            d[1],
                            digits,
                            d[2]
                        )
                    })
                    .collect();
                let (what, seen) = if *positions {
                    ("position", ", seen from the object's centre")
                } else {
                    ("direction", "")
                };
                write!(
                    f,
                    "the brightness of {} image(s){} (numbered from 1, with the light {what} that explains each best given the normals of the other images: {}{}) disagrees with the light given for it: the median light disagrees by {median_deg:.1}°{seen}, and beyond {threshold_deg:.1}° is more than chance; that light's {what} may be wrong (a typo, two rows swapped, a lamp moved after the calibration) or the image may not belong to this capture",
                    lights.len(),
                    match channel {
                        Some((c, n)) => format!(" in colour channel {} of {n}", c + 1),
                        None => String::new(),
                    },
                    list.join(", "),
                    if lights.len() > LISTED_IMAGES {
                        ", …"
                    } else {
                        ""
                    }
                )
            }
            Warning::PoorIntegrability { median_abs_curl } => write!(
                f,
                "poor integrability: median |curl| {median_abs_curl:.3} per pixel (above {POOR_CURL}): the normals are noisy or the surface has discontinuities, so depth from them will be distorted; more or better-spread lights help, and bilateral integration keeps discontinuities"
            ),
            Warning::AlbedoAboveOne { pixels } => write!(
                f,
                "{pixels} pixels have albedo > 1 although intensities were declared normalised: check the light intensities or exposure"
            ),
        }
    }
}

/// Written as its sentence (the `warnings` of `report.json` are strings).
impl Serialize for Warning {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_str(self)
    }
}

/// The warnings of a run, from what loading found, the whole-image tallies, each channel's
/// model and the integrability check.
pub(crate) fn warnings(
    facts: &InputFacts,
    tallies: &Tallies,
    models: &[ChannelModel],
    integrability: &IntegrabilitySummary,
    config: &Config,
) -> Vec<Warning> {
    let counts = &tallies.counts;
    let recalibrated = config.solve.recalibrates(facts.count);
    let mut warnings = Vec::new();
    let linearised = facts.info.iter().filter(|i| i.linearised).count();
    if linearised > 0 {
        warnings.push(Warning::SrgbDecoded { images: linearised });
    }
    if !facts.behind.is_empty() {
        warnings.push(Warning::LightsBehind {
            lights: facts.behind.clone(),
            count: facts.count,
        });
    }
    if facts.positioned > 0 {
        warnings.push(Warning::NearLights {
            positioned: facts.positioned,
            count: facts.count,
        });
    }
    let lossy = facts
        .info
        .iter()
        .filter(|i| crate::io::decode::is_jpeg(&i.path))
        .count();
    if lossy > 0 {
        warnings.push(Warning::Lossy { images: lossy });
    }
    warnings.extend(of_counts(&SampleCounts {
        pixels: *counts,
        saturated: facts.info.iter().map(|i| i.saturated).sum(),
        saturated_used: config.solve.method == Method::LeastSquares,
        non_finite: facts.info.iter().map(|i| i.non_finite).sum(),
        no_mask: facts.unmasked_files,
    }));
    if recalibrated {
        // The gains applied (all 1 where an estimate was not), then the estimates not applied:
        // all of an estimate that was not, and of one that was, the images the robust fits
        // set aside whole (measured, never applied: where the estimate differs from the gain).
        if let Some((images, worst)) = gains_off(models.iter().map(|s| &s.gains.gains)) {
            warnings.push(Warning::IntensitiesCorrected { images, worst });
        }
        if let Some((images, worst)) = gains_off(models.iter().map(|s| not_applied(&s.gains))) {
            warnings.push(Warning::IntensitiesNotApplied { images, worst });
        }
    }
    warnings.extend(of_checks(
        models.iter().filter_map(|m| m.shadow_light.as_ref()),
        models.iter().filter_map(|m| m.light_agreement.as_ref()),
        facts.ambient_subtracted,
    ));
    if integrability.pixels > 0 && integrability.median_abs_curl > POOR_CURL {
        warnings.push(Warning::PoorIntegrability {
            median_abs_curl: integrability.median_abs_curl,
        });
    }
    if config.albedo_normalised && tallies.albedo_above_one > 0 {
        warnings.push(Warning::AlbedoAboveOne {
            pixels: tallies.albedo_above_one,
        });
    }
    warnings
}

/// The images whose gain, in any of the channels' `gains`, is further than [`GAIN_WARNING`]
/// from 1 (numbered from 0, in order), and the gain furthest from 1; `None` when there is none.
fn gains_off<G: AsRef<[f32]>>(gains: impl Iterator<Item = G>) -> Option<(Vec<usize>, f32)> {
    // Per image, the gain furthest from 1 over the channels.
    let mut off: Vec<(usize, f32)> = Vec::new();
    for channel in gains {
        for (k, &g) in channel.as_ref().iter().enumerate() {
            if (g - 1.0).abs() <= GAIN_WARNING {
                continue;
            }
            match off.iter_mut().find(|(i, _)| *i == k) {
                Some(e) if (g - 1.0).abs() > (e.1 - 1.0).abs() => e.1 = g,
                Some(_) => {}
                None => off.push((k, g)),
            }
        }
    }
    off.sort_by_key(|e| e.0);
    let worst = off.iter().map(|e| e.1).fold(1.0f32, |a, g| {
        if (g - 1.0).abs() > (a - 1.0).abs() {
            g
        } else {
            a
        }
    });
    (!off.is_empty()).then(|| (off.into_iter().map(|e| e.0).collect(), worst))
}

/// Per image, the factor between the estimated gain and the gain applied (1 where nothing
/// was): where the estimate was not applied, the estimate itself; where it was, 1 but for the
/// images the robust fits set aside whole, measured afterwards and never applied.
fn not_applied(g: &crate::ps::intensities::GainEstimate) -> Vec<f32> {
    g.estimated
        .iter()
        .zip(&g.gains)
        .map(|(&e, &a)| if a > 0.0 { e / a } else { 1.0 })
        .collect()
}

/// The pixel outcomes and sample counts of a run (or of a part of one) that its warnings
/// report.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SampleCounts {
    /// Pixel outcomes.
    pub pixels: StatusCounts,
    /// Saturated samples over all images (in the part of each image that was read: the rows or
    /// the bounding box of the mask).
    pub saturated: usize,
    /// Whether the estimator used the saturated samples (plain least squares).
    pub saturated_used: bool,
    /// NaN or infinite samples over all images.
    pub non_finite: usize,
    /// No mask was given, so the background counts as object.
    pub no_mask: bool,
}

impl SampleCounts {
    /// Adds the counts of another part of the same run; `None` (and `self` unchanged) when a
    /// count overflows.
    pub fn try_add(&mut self, other: &SampleCounts) -> Option<()> {
        let mut pixels = self.pixels;
        pixels.try_add(&other.pixels)?;
        *self = SampleCounts {
            pixels,
            saturated: self.saturated.checked_add(other.saturated)?,
            saturated_used: self.saturated_used || other.saturated_used,
            non_finite: self.non_finite.checked_add(other.non_finite)?,
            no_mask: self.no_mask || other.no_mask,
        };
        Some(())
    }
}

/// The warnings of a run's sample and pixel counts, in the report's order: saturated and
/// non-finite samples, filled pixels, pixels without a normal. Those of a whole run and of the
/// parts of one added up ([`crate::run::checks::CaptureChecks`]).
pub(crate) fn of_counts(c: &SampleCounts) -> Vec<Warning> {
    let p = &c.pixels;
    let mut warnings = Vec::new();
    if c.saturated > 0 {
        warnings.push(Warning::Saturated {
            samples: c.saturated,
            used: c.saturated_used,
        });
    }
    if c.non_finite > 0 {
        warnings.push(Warning::NonFinite {
            samples: c.non_finite,
        });
    }
    if p.filled > 0 {
        warnings.push(Warning::Filled {
            filled: p.filled,
            masked: p.masked,
        });
    }
    let unsolved = p.unsolved();
    if unsolved > 0 {
        warnings.push(Warning::Unsolved {
            unsolved,
            masked: p.masked,
            too_few_samples: p.too_few_samples,
            ill_conditioned: p.ill_conditioned,
            dark: p.dark,
            no_mask: c.no_mask,
        });
    }
    warnings
}

/// The warnings of the capture-wide checks of a solve: the light in attached shadows (the
/// channel whose shadows bend the normals most) and each light against the others (the channel
/// with the most lights named), one measurement a channel; `ambient_subtracted`: the frame
/// taken with every lamp off was subtracted. Those of a whole run and of the parts of one
/// added up ([`crate::run::checks::CaptureChecks`]).
pub(crate) fn of_checks<'a>(
    shadow_light: impl Iterator<Item = &'a ShadowLight>,
    light_agreement: impl Iterator<Item = &'a LightAgreement>,
    ambient_subtracted: bool,
) -> Vec<Warning> {
    let mut warnings = Vec::new();
    // The channel whose attached shadows bend the normals most, judged at the level the data
    // show at least (two standard errors nearer zero).
    let shadow = shadow_light
        .filter_map(|s| {
            Some((
                s.level?,
                s.pixels,
                s.predicted_bias_deg?,
                s.confident_bias_deg()?,
            ))
        })
        .max_by(|a, b| a.3.total_cmp(&b.3));
    if let Some((level, pixels, bias_deg, confident)) = shadow
        && confident >= SHADOW_LIGHT_WARN_DEG
    {
        warnings.push(Warning::ShadowLight {
            level,
            pixels,
            bias_deg,
            ambient_subtracted,
        });
    }
    // The channel with the most disagreeing lights (the first of equals), named when there are
    // several.
    let checked: Vec<&LightAgreement> = light_agreement.collect();
    let mut most: Option<(usize, &LightAgreement)> = None;
    for (c, a) in checked.iter().enumerate() {
        if !a.disagreeing.is_empty()
            && most.is_none_or(|(_, b)| a.disagreeing.len() > b.disagreeing.len())
        {
            most = Some((c, a));
        }
    }
    if let Some((c, a)) = most
        && let (Some(median_deg), Some(threshold_deg)) = (a.median_deg, a.threshold_deg)
    {
        let mut positions = false;
        let mut lights: Vec<(usize, f64, [f64; 3])> = a
            .disagreeing
            .iter()
            .filter_map(|&k| {
                a.lights[k].as_ref().map(|f| {
                    positions |= f.position.is_some();
                    (k, f.disagreement_deg, f.position.unwrap_or(f.direction))
                })
            })
            .collect();
        lights.sort_by(|x, y| y.1.total_cmp(&x.1));
        warnings.push(Warning::LightsDisagree {
            lights,
            positions,
            median_deg,
            threshold_deg,
            channel: (checked.len() > 1).then_some((c, checked.len())),
        });
    }
    warnings
}

/// Each warning's sentence: it carries the warning's numbers (images numbered from 1, at most
/// [`LISTED_IMAGES`] listed), is what `report.json` holds, and names no command-line flag.
#[cfg(test)]
mod tests {
    use super::*;

    /// NaN and the zero vector inside the mask are counted as no normal; outside it, and any
    /// other finite vector (of any length), are not.
    #[test]
    fn pixels_of_the_mask_without_a_normal_are_counted() {
        use nalgebra::Vector3;
        let normals = crate::grid::Grid::from_vec(
            4,
            1,
            vec![
                Vector3::new(f32::NAN, 0.0, 1.0),
                Vector3::zeros(),
                Vector3::new(0.0, 0.0, 0.3),
                Vector3::zeros(),
            ],
        )
        .unwrap();
        let mask = crate::grid::Grid::from_vec(4, 1, vec![true, true, true, false]).unwrap();
        assert_eq!(
            Warning::of_normals(&normals, &mask),
            Some(Warning::WithoutNormal {
                pixels: 2,
                masked: 3
            })
        );
        let last = crate::grid::Grid::from_vec(4, 1, vec![false, false, true, false]).unwrap();
        assert_eq!(Warning::of_normals(&normals, &last), None);
    }

    /// The estimate's factors the not-applied warning reads: all of an estimate that was not
    /// applied; of one that was, only the images the fits set aside whole (their estimate
    /// differs from the gain applied), whatever the median normalisation did to the rest.
    #[test]
    fn not_applied_reads_the_set_aside_images_of_an_applied_estimate() {
        let mut g = crate::ps::intensities::GainEstimate::unit(4);
        g.estimated = vec![0.8, 1.0, 1.3, 1.05];
        assert_eq!(not_applied(&g), g.estimated);
        assert_eq!(
            gains_off([not_applied(&g)].into_iter()),
            Some((vec![0, 2], 1.3))
        );
        g.applied = true;
        g.gains = vec![0.8, 1.0, 1.02, 1.05];
        let f = not_applied(&g);
        assert_eq!(
            gains_off([f.clone()].into_iter()).map(|o| o.0),
            Some(vec![2])
        );
        assert!(
            (f[2] - 1.3 / 1.02).abs() < 1e-6 && f[0] == 1.0 && f[3] == 1.0,
            "{f:?}"
        );
    }

    /// One of each variant, with numbers found nowhere else in the sentences, and the texts
    /// each sentence must contain.
    fn cases() -> Vec<(Warning, Vec<&'static str>)> {
        vec![
            (Warning::SrgbDecoded { images: 17 }, vec!["17 8-bit image"]),
            (
                Warning::Saturated {
                    samples: 4321,
                    used: true,
                },
                vec!["4321 saturated", "used by plain least squares"],
            ),
            (
                Warning::Saturated {
                    samples: 4322,
                    used: false,
                },
                vec!["4322 saturated", "excluded"],
            ),
            (Warning::NonFinite { samples: 913 }, vec!["913 NaN"]),
            (
                Warning::Unsolved {
                    unsolved: 611,
                    masked: 9876,
                    too_few_samples: 401,
                    ill_conditioned: 203,
                    dark: 7,
                    no_mask: true,
                },
                vec![
                    "611 of 9876",
                    "401 with fewer",
                    "203 with ill",
                    "7 dark",
                    "no mask",
                ],
            ),
            (
                Warning::IntensitiesCorrected {
                    images: vec![0, 4, 13],
                    worst: 1.3704,
                },
                vec!["3 image(s)", "1, 5, 14)", "1.37"],
            ),
            (
                Warning::IntensitiesNotApplied {
                    images: vec![2, 5, 6, 7, 8, 9, 10, 11, 12],
                    worst: 0.8695,
                },
                vec![
                    "9 image(s)",
                    "3, 6, 7, 8, 9, 10, 11, 12, 13)",
                    "0.87",
                    "estimated_gains",
                ],
            ),
            (
                Warning::LightsDisagree {
                    lights: vec![
                        (40, 8.912, [0.1234, -0.5, 0.857]),
                        (7, 3.04, [0.0, 0.0, 1.0]),
                    ],
                    positions: false,
                    median_deg: 0.634,
                    threshold_deg: 2.546,
                    channel: None,
                },
                vec![
                    "2 image(s) (numbered",
                    "41 (8.9° off: (0.123, -0.500, 0.857))",
                    "8 (3.0° off",
                    "median light disagrees by 0.6°",
                    "beyond 2.5°",
                    "two rows swapped",
                ],
            ),
            (
                Warning::LightsDisagree {
                    lights: vec![(3, 5.54, [0.0, 0.6, 0.8])],
                    positions: false,
                    median_deg: 1.2,
                    threshold_deg: 4.0,
                    channel: Some((2, 3)),
                },
                vec!["1 image(s) in colour channel 3 of 3", "4 (5.5° off"],
            ),
            (
                Warning::LightsDisagree {
                    lights: vec![(5, 10.447, [12.5, -3.25, 40.125])],
                    positions: true,
                    median_deg: 0.21,
                    threshold_deg: 2.0,
                    channel: None,
                },
                vec![
                    "light position that explains",
                    "6 (10.4° off: position (12.5000, -3.2500, 40.1250))",
                    "0.2°, seen from the object's centre",
                    "light's position may be wrong",
                ],
            ),
            (
                Warning::PoorIntegrability {
                    median_abs_curl: 0.0734,
                },
                vec!["0.073"],
            ),
            (
                Warning::AlbedoAboveOne { pixels: 2929 },
                vec!["2929 pixels"],
            ),
            (
                Warning::ShadowLight {
                    level: 0.0763,
                    pixels: 742,
                    bias_deg: 1.386,
                    ambient_subtracted: false,
                },
                vec!["7.6%", "742 pixels", "1.4°", "every lamp off"],
            ),
            (
                Warning::ShadowLight {
                    level: 0.0521,
                    pixels: 743,
                    bias_deg: 2.04,
                    ambient_subtracted: true,
                },
                vec![
                    "5.2%",
                    "743 pixels",
                    "2.0°",
                    "after the ambient image",
                    "interreflections",
                ],
            ),
            (
                Warning::ShadowLight {
                    level: -0.0481,
                    pixels: 744,
                    bias_deg: 1.88,
                    ambient_subtracted: true,
                },
                vec![
                    "4.8%",
                    "below zero",
                    "744 pixels",
                    "1.9°",
                    "more light than the images",
                ],
            ),
            (
                Warning::IntegrationNotConverged {
                    solver: "grid-multigrid-cg",
                    iterations: 2017,
                    convergence: crate::integrate::Convergence::IterationLimit,
                },
                vec!["grid-multigrid-cg", "2017 iterations", "not converged"],
            ),
            (
                Warning::WithoutNormal {
                    pixels: 64,
                    masked: 5021,
                },
                vec!["64 of the 5021", "no normal", "without depth"],
            ),
            (
                Warning::DepthOffsetsGuessed {
                    regions: 21,
                    pixels: 8795,
                    largest: 8725,
                    integrated: 24706,
                },
                vec![
                    "21 regions",
                    "8795 of 24706",
                    "35.6%",
                    "largest 8725",
                    "a guess",
                ],
            ),
        ]
    }

    /// Every variant's sentence holds its numbers (and the curl limit), serialises as itself
    /// and names no flag; the unsolved warning mentions the mask only when none was given.
    #[test]
    fn sentences_carry_their_numbers_and_name_no_flag() {
        for (w, texts) in cases() {
            let s = w.to_string();
            for t in texts {
                assert!(s.contains(t), "{w:?}: {s:?} lacks {t:?}");
            }
            if let Warning::PoorIntegrability { .. } = w {
                assert!(s.contains(&format!("above {POOR_CURL}")), "{s}");
            }
            assert!(!s.contains("--"), "{w:?} names a flag: {s}");
            assert_eq!(
                serde_json::to_value(&w).unwrap(),
                serde_json::Value::String(s),
                "{w:?}"
            );
        }
        let unmasked = Warning::Unsolved {
            unsolved: 1,
            masked: 2,
            too_few_samples: 1,
            ill_conditioned: 0,
            dark: 0,
            no_mask: false,
        };
        assert!(!unmasked.to_string().contains("mask"), "{unmasked}");
    }

    /// A depth solve warns only when it stopped before converging.
    #[test]
    fn only_an_unconverged_solve_warns() {
        use crate::integrate::{Convergence, SolveInfo, SolveMethod};
        let solve = |convergence| SolveInfo {
            unknowns: 10,
            method: SolveMethod::GridMultigridCg,
            iterations: 7,
            convergence,
        };
        for c in [
            Convergence::Exact,
            Convergence::Residual,
            Convergence::DataNoise,
        ] {
            assert_eq!(Warning::of_solve(solve(c)), None, "{c:?}");
        }
        for c in [Convergence::IterationLimit, Convergence::Breakdown] {
            let w = Warning::of_solve(solve(c)).expect("a warning");
            assert!(w.to_string().contains("7 iterations"), "{w}");
        }
    }

    /// More images than are listed: the first [`LISTED_IMAGES`] (from 1), then an ellipsis.
    #[test]
    fn a_long_image_list_is_cut() {
        let w = Warning::IntensitiesCorrected {
            images: (0..LISTED_IMAGES + 3).collect(),
            worst: 0.5,
        };
        let s = w.to_string();
        let listed: Vec<String> = (1..=LISTED_IMAGES).map(|k| k.to_string()).collect();
        assert!(
            s.contains(&format!("{} image(s)", LISTED_IMAGES + 3)),
            "{s}"
        );
        assert!(s.contains(&format!(": {}, …)", listed.join(", "))), "{s}");
        assert!(!s.contains(&format!(", {},", LISTED_IMAGES + 1)), "{s}");
        assert!(s.contains("0.50"), "{s}");
    }
}
