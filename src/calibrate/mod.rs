//! Light calibration from reference objects photographed under each light: directions from a
//! mirror (chrome) sphere, relative intensities from a matte sphere or a grey card; or, without
//! a reference, from the object itself ([`from_object`], uncalibrated photometric stereo).
//!
//! The chrome sphere's outline comes from its mask ([`sphere::circle_from_mask`], sub-pixel) or
//! is detected in the images ([`sphere::detect_circles`], then verified against them); each
//! image's highlight gives its
//! light by reflecting the view direction about the sphere's normal, l = 2(n·v)n − v with
//! v = (0, 0, 1) ([`highlight::find_highlight`]). [`intensity`] then reads relative intensities
//! off a Lambertian reference. The result is a [`Lights`] set for the main pipeline, and a
//! report with each light's confidence and the warnings.
//!
//! The camera is orthographic by default. Given the camera's intrinsics
//! ([`ChromeOptions::camera`]), the calibration is perspective ([`perspective`]): the outline
//! is fitted as the cone of rays the sphere subtends (its image is an ellipse off the axis) and
//! each pixel reflects its own view ray; calibrating such images as orthographic costs degrees
//! (7.7° on average over the rendered captures of `tests/chrome_captures.rs`, against 0.17°).
//! With two balls of known radius in the images, [`near::calibrate_two_balls`] places each
//! light where the rays it reflects off them meet: a near light's position.
//!
//! ```
//! use photostereo::calibrate::{ChromeOptions, calibrate_chrome};
//! use photostereo::capture::lights::Lights;
//! use photostereo::synth::reflectance::{Diffuse, Material, Mirror, Specular};
//! use photostereo::synth::render::{RenderOptions, render};
//! use photostereo::synth::scene::{Albedo, Object, Primitive, Scene};
//! use photostereo::nalgebra::Vector3;
//!
//! // A chrome ball of radius 60 px under two lamps of 4° radius, rendered with pixels that
//! // integrate over their area; its mask comes from the renderer.
//! let chrome = Material {
//!     diffuse: Diffuse::None,
//!     diffuse_color: [1.0; 3],
//!     specular: Some(Specular::Mirror(Mirror { f0: 0.8 })),
//!     specular_color: [1.0; 3],
//! };
//! let sphere = Primitive::Sphere { cx: 0.0, cy: 0.0, radius: 60.0, base: 0.0 };
//! let scene = Scene { width: 140, height: 140,
//!     objects: vec![Object::new(sphere, Albedo::Constant(1.0)).with_material(chrome)] };
//! let truth = Lights::from_directions(&[Vector3::new(0.3, 0.2, 0.9), Vector3::new(-0.4, 0.1, 0.9)])?;
//! let options = RenderOptions { light_radius_deg: 4.0, pixel_samples: 4, ..RenderOptions::default() };
//! let r = render(&scene, &truth, &options)?;
//! let stack = r.to_stack(&truth, photostereo::capture::stack::ColorMode::Grey)?;
//! let mask = r.truth.mask.map(|m| f32::from(u8::from(*m)));
//!
//! let cal = calibrate_chrome(&stack, Some((&mask, "mask".as_ref())), &ChromeOptions::default())?;
//! let lights = cal.lights()?;
//! for (found, true_l) in lights.directions().iter().zip(truth.directions()) {
//!     assert!(found.angle(&true_l).to_degrees() < 0.3);
//! }
//! # Ok::<(), photostereo::Error>(())
//! ```

pub mod from_object;
pub mod highlight;
pub mod intensity;
pub mod near;
pub mod perspective;
pub mod sphere;

use crate::camera::Intrinsics;
use crate::capture::lights::{Light, Lights};
use crate::capture::stack::{ColorMode, ImageStack, LoadOptions, Transfer, load_stack};
use crate::error::{Error, Result};
use crate::grid::{Grid, ScalarMap};
use crate::io::decode::read_image;
use crate::progress::Progress;
use highlight::{Highlight, HighlightOptions, Missing, find_highlight};
use nalgebra::Vector3;
use perspective::{SphereCone, cone_jackknife, fit_cone, kept_points};
use serde::Serialize;
use sphere::{
    Candidate, CircleFit, circle_from_mask, detect_circles, fit_circle, mask_edge_points,
    outline_points, split_mask,
};
use std::path::{Path, PathBuf};

/// Options of [`calibrate_chrome`].
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct ChromeOptions {
    /// How highlights are found.
    pub highlight: HighlightOptions,
    /// The camera's intrinsics, for a perspective calibration ([`perspective`]): the sphere's
    /// outline is fitted as a cone of rays and each pixel reflects its own view ray. `None`:
    /// orthographic.
    pub camera: Option<Intrinsics>,
}

/// Where the sphere's outline came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SphereSource {
    /// Fitted to the edge of a mask.
    Mask,
    /// Detected in the images.
    Detected,
}

/// One image's outcome.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LightOutcome {
    /// Image index.
    pub index: usize,
    /// The image file.
    pub image: PathBuf,
    /// The highlight and the light it gives, or why there is none.
    #[serde(flatten)]
    pub result: HighlightResult,
}

/// A highlight, or why none was found.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum HighlightResult {
    /// Found.
    Found(Highlight),
    /// Not found.
    Missing(Missing),
}

/// The result of a chrome-sphere calibration.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChromeCalibration {
    /// The sphere's outline (under a pinhole camera, the circle that best matches its
    /// elliptical image).
    pub sphere: CircleFit,
    /// Under a pinhole camera ([`ChromeOptions::camera`]), the sphere's cone of outline rays,
    /// from which the lights are computed.
    pub cone: Option<SphereCone>,
    /// Where it came from.
    pub sphere_source: SphereSource,
    /// One outcome per image, in order.
    pub lights: Vec<LightOutcome>,
    /// Warnings about the calibration as a whole (per-light ones are in their highlights).
    pub warnings: Vec<String>,
}

impl ChromeCalibration {
    /// The light directions, one per image, with unit intensity, when every light is
    /// accepted ([`Highlight::accepted`]).
    ///
    /// # Errors
    /// As [`ChromeCalibration::all_lights`]; and [`Error::BadImage`] naming the first image
    /// whose light is in doubt (the message lists them all, with why).
    pub fn lights(&self) -> Result<Lights> {
        let doubtful: Vec<(&LightOutcome, &Highlight)> = self
            .lights
            .iter()
            .filter_map(|o| match &o.result {
                HighlightResult::Found(h) if !h.accepted => Some((o, h)),
                _ => None,
            })
            .collect();
        if let (Some((first, _)), false) = (doubtful.first(), self.has_missing()) {
            let all: Vec<String> = doubtful
                .iter()
                .map(|(o, h)| format!("image {}: {}", o.index, h.warnings.join("; ")))
                .collect();
            return Err(Error::BadImage {
                path: first.image.clone(),
                index: first.index,
                reason: format!(
                    "{} of {} lights are in doubt ({}); photograph them again, or keep them as they are with their uncertainty",
                    doubtful.len(),
                    self.lights.len(),
                    all.join(" | ")
                ),
            });
        }
        self.all_lights()
    }

    fn has_missing(&self) -> bool {
        self.lights
            .iter()
            .any(|o| matches!(o.result, HighlightResult::Missing(_)))
    }

    /// The light directions, one per image, with unit intensity, whether accepted or in doubt.
    ///
    /// # Errors
    /// [`Error::BadImage`] naming the first image without a highlight (the message lists them
    /// all): a lights file must have one light per image.
    pub fn all_lights(&self) -> Result<Lights> {
        let missing: Vec<&LightOutcome> = self
            .lights
            .iter()
            .filter(|o| matches!(o.result, HighlightResult::Missing(_)))
            .collect();
        if let Some(first) = missing.first() {
            let HighlightResult::Missing(m) = &first.result else {
                unreachable!("filtered to missing outcomes")
            };
            let all: Vec<String> = missing.iter().map(|o| o.index.to_string()).collect();
            return Err(Error::BadImage {
                path: first.image.clone(),
                index: first.index,
                reason: format!(
                    "{} (images without a highlight: {}); remove them and their object images, or fix the exposure",
                    m.reason,
                    all.join(", ")
                ),
            });
        }
        let dirs: Vec<Vector3<f64>> = self
            .lights
            .iter()
            .filter_map(|o| match &o.result {
                HighlightResult::Found(h) => Some(h.direction),
                HighlightResult::Missing(_) => None,
            })
            .collect();
        Lights::from_directions(&dirs)
    }

    /// The found highlights (`None` where missing), in image order.
    pub fn highlights(&self) -> Vec<Option<&Highlight>> {
        self.lights
            .iter()
            .map(|o| match &o.result {
                HighlightResult::Found(h) => Some(h),
                HighlightResult::Missing(_) => None,
            })
            .collect()
    }
}

/// Calibrates one light per image from a mirror sphere: the sphere's circle from `mask` (a
/// grey mask, with its file for errors) or, without one, detected in the images and verified
/// against them (see [`sphere::detect_circles`] and `docs/calibration.md`: something inside it
/// must be lit differently by the lights, and the images must show its outline; of several
/// balls apart, the largest is used and the others are named in the warnings); then each
/// image's highlight (see [`highlight::find_highlight`]) in its excess over the per-pixel
/// median of the images.
///
/// # Errors
/// [`Error::DimensionMismatch`] when the mask's size differs from the images';
/// [`Error::Mask`] when the mask's outline is not a circle; [`Error::SphereNotFound`] when no
/// circle passes the checks, or overlapping ones do and none is clearly the ball (the message
/// lists them); [`Error::TooFewImages`] for an empty stack.
pub fn calibrate_chrome(
    stack: &ImageStack,
    mask: Option<(&ScalarMap, &Path)>,
    options: &ChromeOptions,
) -> Result<ChromeCalibration> {
    if stack.count() == 0 {
        return Err(Error::TooFewImages { count: 0 });
    }
    let grey = grey_images(stack);
    let (w, h) = (stack.width(), stack.height());
    let (balls, source) = find_balls_in(&grey, w, h, mask, options.camera.as_ref(), false)?;
    let mut warnings = Vec::new();
    for o in &balls[1..] {
        let c = o.fit.circle;
        warnings.push(format!(
            "another sphere is in the images, centre ({:.1}, {:.1}) radius {:.1} px: the largest is used (give a mask to choose)",
            c.cx, c.cy, c.radius
        ));
    }
    let mut cal = calibrate_ball(stack, &grey, &balls[0], source, options);
    warnings.append(&mut cal.warnings);
    cal.warnings = warnings;
    Ok(cal)
}

/// A ball found in the images or a mask: its circle and, under a pinhole camera, its cone.
#[derive(Debug, Clone)]
pub(crate) struct Ball {
    fit: CircleFit,
    cone: Option<SphereCone>,
}

/// The highlights of every image on one ball, as [`calibrate_chrome`] finds them.
pub(crate) fn calibrate_ball(
    stack: &ImageStack,
    grey: &[Vec<f32>],
    ball: &Ball,
    source: SphereSource,
    options: &ChromeOptions,
) -> ChromeCalibration {
    let (w, h) = (stack.width(), stack.height());
    let sphere = ball.fit;
    let mut warnings = Vec::new();
    let c = sphere.circle;
    if c.cx - c.radius < 0.0
        || c.cy - c.radius < 0.0
        || c.cx + c.radius > w as f64
        || c.cy + c.radius > h as f64
    {
        warnings.push("the sphere is cut by the image border".to_string());
    }
    // The errors of the outline the lights come from, in pixels (for a cone: its tilts and
    // half-angle times the focal length).
    let errors = match &ball.cone {
        Some(k) => k.std_err.map(|e| e * 0.5 * (k.camera.fx + k.camera.fy)),
        None => sphere.std_err,
    };
    if errors.iter().any(|s| *s > 0.5) {
        warnings.push(format!(
            "the sphere's outline is uncertain (standard errors {:.2}, {:.2}, {:.2} px for its centre and radius, or, seen through the camera, its axis' tilts and half-angle times the focal length)",
            errors[0], errors[1], errors[2]
        ));
    }
    // Each highlight is sought in the image's excess over the per-pixel median, which holds
    // what every image shares (the environment reflected by the ball, the wall) but no
    // highlight, as long as no pixel is lit in half the images (three or more images).
    let median = (grey.len() >= 3).then(|| evidence(grey, w, h, 0.5));
    let noise = disc_noise(grey, w, h, &sphere.circle);
    let lights = grey
        .iter()
        .enumerate()
        .map(|(index, plane)| LightOutcome {
            index,
            image: stack.info()[index].path.clone(),
            result: match find_highlight(
                &excess(plane, median.as_ref()),
                Some(noise[index]),
                &clipped(stack, index, plane),
                w,
                &sphere,
                ball.cone.as_ref(),
                &options.highlight,
            ) {
                Ok(hl) => HighlightResult::Found(hl),
                Err(m) => HighlightResult::Missing(m),
            },
        })
        .collect();
    ChromeCalibration {
        sphere,
        cone: ball.cone,
        sphere_source: source,
        lights,
        warnings,
    }
}

/// The outline of a sphere in `stack`: fitted to `mask` (a grey mask, with its file for
/// errors) or, without one, detected and verified as in [`calibrate_chrome`] (in the
/// per-pixel median, upper quartile and maximum of three or more images).
///
/// # Errors
/// As [`calibrate_chrome`].
pub fn find_sphere(
    stack: &ImageStack,
    mask: Option<(&ScalarMap, &Path)>,
) -> Result<(CircleFit, SphereSource)> {
    let (balls, source) = find_balls_in(
        &grey_images(stack),
        stack.width(),
        stack.height(),
        mask,
        None,
        false,
    )?;
    Ok((balls[0].fit, source))
}

/// The balls in the images, largest first (at least one): from `mask` (one ball, or with
/// `parts` one per separate part of it), or detected and verified; each with its cone of rays
/// under `camera`.
pub(crate) fn find_balls_in(
    grey: &[Vec<f32>],
    w: usize,
    h: usize,
    mask: Option<(&ScalarMap, &Path)>,
    camera: Option<&Intrinsics>,
    parts: bool,
) -> Result<(Vec<Ball>, SphereSource)> {
    if let Some((m, path)) = mask {
        Grid::new(w, h, ()).check_same_size(m, "sphere mask vs images")?;
        if !parts {
            return Ok((vec![ball_from_mask(m, path, camera)?], SphereSource::Mask));
        }
        let balls = split_mask(m)
            .iter()
            .map(|part| ball_from_mask(part, path, camera))
            .collect::<Result<Vec<Ball>>>()?;
        if balls.is_empty() {
            return Err(Error::Mask {
                path: path.to_path_buf(),
                reason: "the mask is empty".into(),
            });
        }
        return Ok((balls, SphereSource::Mask));
    }
    if grey.len() < 3 {
        return Err(Error::SphereNotFound {
            reason: format!(
                "{} image(s): finding the sphere needs three or more, whose median shows it without its highlights",
                grey.len()
            ),
        });
    }
    // The median suits a mirror ball (it drops every highlight), the upper quartile and the
    // maximum a matte one (its rim stays lit). Circles from all three are verified against
    // the images.
    let median = evidence(grey, w, h, 0.5);
    let mut candidates: Vec<Candidate> = Vec::new();
    for c in detect_circles(&median, CANDIDATES, camera)
        .into_iter()
        .chain(detect_circles(
            &evidence(grey, w, h, 0.75),
            CANDIDATES,
            camera,
        ))
        .chain(detect_circles(
            &evidence(grey, w, h, 1.0),
            CANDIDATES,
            camera,
        ))
    {
        // Of two fits of one circle, keep the one with the smaller errors.
        match candidates
            .iter_mut()
            .find(|o| same_circle(&o.fit.circle, &c.fit.circle))
        {
            Some(o) if spread(&c) < spread(o) => *o = c,
            Some(_) => {}
            None => candidates.push(c),
        }
    }
    if candidates.is_empty() {
        return Err(Error::SphereNotFound {
            reason: "no circle of radius ≥ 8 px has edges over half its outline in the images"
                .into(),
        });
    }
    let checks: Vec<(Candidate, Verification)> = candidates
        .into_iter()
        .map(|c| (c, verify(&c, grey, &median, w, h)))
        .collect();
    let mut passed: Vec<&Candidate> = checks
        .iter()
        .filter(|(_, v)| v.passed())
        .map(|(c, _)| c)
        .collect();
    if passed.is_empty() {
        let why: Vec<String> = checks.iter().take(3).map(|(c, v)| v.describe(c)).collect();
        return Err(Error::SphereNotFound {
            reason: format!(
                "no circle in the images passes the checks of a calibration sphere ({})",
                why.join("; ")
            ),
        });
    }
    passed.sort_by(|a, b| b.support.total_cmp(&a.support));
    // Circles that overlap compete for one outline; circles apart are different balls.
    let mut balls: Vec<Candidate> = Vec::new();
    while !passed.is_empty() {
        // The best supported circle and every circle linked to it by a chain of overlaps.
        let mut group: Vec<&Candidate> = vec![passed.remove(0)];
        while let Some(i) = passed
            .iter()
            .position(|c| group.iter().any(|g| overlap(&g.fit.circle, &c.fit.circle)))
        {
            group.push(passed.remove(i));
        }
        group.sort_by(|a, b| b.support.total_cmp(&a.support));
        balls.push(resolve(&group)?);
    }
    balls.sort_by(|a, b| b.fit.circle.radius.total_cmp(&a.fit.circle.radius));
    // The balls used (the largest, or the two largest for positions) need their cone; a
    // failed fit of another is left out of it (it is only named in a warning).
    let used = if parts { 2 } else { 1 };
    let balls = balls
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let cone = camera.map(|k| detected_cone(&median, b, k)).transpose();
            Ok(Ball {
                fit: b.fit,
                cone: if i < used { cone? } else { cone.ok().flatten() },
            })
        })
        .collect::<Result<Vec<Ball>>>()?;
    Ok((balls, SphereSource::Detected))
}

/// A ball from its mask: the circle of its outline, and under `camera` its cone of rays. With a
/// camera the outline must fit the cone (an off-axis ball's image is an ellipse), without one
/// a circle ([`circle_from_mask`]).
fn ball_from_mask(m: &ScalarMap, path: &Path, camera: Option<&Intrinsics>) -> Result<Ball> {
    let Some(k) = camera else {
        return Ok(Ball {
            fit: circle_from_mask(m, path)?,
            cone: None,
        });
    };
    let bad = |reason: String| Error::Mask {
        path: path.to_path_buf(),
        reason,
    };
    let points = mask_edge_points(m);
    let mut fit = fit_circle(&points).map_err(|e| bad(format!("no sphere's outline: {e}")))?;
    if fit.coverage < sphere::MIN_COVERAGE {
        return Err(bad(format!(
            "the outline covers {:.0}% of a sphere's (at least {:.0}% is needed): is this a sphere's mask?",
            fit.coverage * 100.0,
            sphere::MIN_COVERAGE * 100.0
        )));
    }
    let cone = fit_cone(&points, k).map_err(|e| bad(format!("no sphere's outline: {e}")))?;
    let limit = sphere::MAX_MASK_RMS_PX + 0.01 * fit.circle.radius;
    if cone.rms_px > limit || cone.outliers > cone.points {
        return Err(bad(format!(
            "its outline is not a sphere's as the camera sees it: the best cone of rays leaves {} of {} edge points out and the rest {:.2} px from it on average (at most {limit:.2} px)",
            cone.outliers,
            cone.points + cone.outliers,
            cone.rms_px
        )));
    }
    fit.circle = cone.image_circle();
    Ok(Ball {
        fit,
        cone: Some(cone),
    })
}

/// The cone of rays of a detected ball: fitted to the median's edge points near its circle
/// (within the support tolerance plus the ellipse's departure from it, about R(1/cos θ − 1) at
/// θ off-axis), with standard errors allowing for correlated edge points and a deformed
/// outline as the circle's are ([`detect_circles`]).
fn detected_cone(median: &ScalarMap, ball: &Candidate, camera: &Intrinsics) -> Result<SphereCone> {
    let c = ball.fit.circle;
    let band = 1.5 + sphere::ellipse_excess(&c, Some(camera));
    let points = outline_points(median, &c, band);
    let mut cone = fit_cone(&points, camera).map_err(|e| Error::SphereNotFound {
        reason: format!(
            "the outline of the sphere at ({:.1}, {:.1}), radius {:.1} px, fits no sphere seen by the camera given ({e}); check its intrinsics",
            c.cx, c.cy, c.radius
        ),
    })?;
    let kept = kept_points(&points, &cone);
    let jack = cone_jackknife(&kept, &cone, sphere::JACKKNIFE_SECTORS);
    let focal = 0.5 * (camera.fx + camera.fy);
    for (se, j) in cone.std_err.iter_mut().zip(jack) {
        *se = (sphere::EDGE_CORRELATION_PX.sqrt() * *se)
            .max(j)
            .hypot(sphere::OUTLINE_FLOOR_PX / focal);
    }
    Ok(cone)
}

/// The circle among `group` (overlapping circles that passed the checks, best supported
/// first): the leader when every other is a worse fit of its outline (within a few pixels of
/// it) or holds clearly less of an outline; of the fits of that outline, the one with the
/// smallest errors, i.e. the evidence in which it is most nearly a circle (the median for a
/// mirror ball; the upper quartile for a matte one, whose unlit side the median darkens).
fn resolve(group: &[&Candidate]) -> Result<Candidate> {
    let (&lead, rest) = group.split_first().ok_or_else(|| Error::SphereNotFound {
        reason: "no candidate".into(),
    })?;
    let clear = rest.iter().all(|c| {
        near(&lead.fit.circle, &c.fit.circle) || lead.support >= c.support + CLEAR_SUPPORT
    });
    if !clear {
        let listed: Vec<String> = group
            .iter()
            .take(4)
            .map(|c| {
                let k = c.fit.circle;
                format!(
                    "centre ({:.1}, {:.1}) radius {:.1} px with edges over {:.0}% of it",
                    k.cx,
                    k.cy,
                    k.radius,
                    c.support * 100.0
                )
            })
            .collect();
        return Err(Error::SphereNotFound {
            reason: format!(
                "{} overlapping circles pass the checks of a calibration sphere and none holds clearly more of its outline: {}",
                group.len(),
                listed.join("; ")
            ),
        });
    }
    Ok(*std::iter::once(lead)
        .chain(
            rest.iter()
                .copied()
                .filter(|c| near(&lead.fit.circle, &c.fit.circle)),
        )
        .min_by(|x, y| spread(x).total_cmp(&spread(y)))
        .unwrap_or(lead))
}

/// The sum of a candidate's squared standard errors: of two fits of one outline, the smaller
/// is the better.
fn spread(c: &Candidate) -> f64 {
    c.fit.std_err.iter().map(|e| e * e).sum()
}

/// How much more of its outline (fraction of the in-frame circumference) a circle must hold
/// than one overlapping it to be taken instead of it.
const CLEAR_SUPPORT: f64 = 0.15;

/// Whether two circles are within a few pixels of each other everywhere (4 px or 5% of the
/// radius, whichever is more).
fn near(a: &sphere::Circle, b: &sphere::Circle) -> bool {
    (a.cx - b.cx).hypot(a.cy - b.cy) + (a.radius - b.radius).abs() <= (0.05 * a.radius).max(4.0)
}

/// Whether two circles overlap.
fn overlap(a: &sphere::Circle, b: &sphere::Circle) -> bool {
    (a.cx - b.cx).hypot(a.cy - b.cy) < a.radius + b.radius
}

/// Circles sought in each evidence image.
const CANDIDATES: usize = 6;

/// Whether two detected circles are the same one (within 2 px in centre and radius).
fn same_circle(a: &sphere::Circle, b: &sphere::Circle) -> bool {
    (a.cx - b.cx).hypot(a.cy - b.cy) < 2.0 && (a.radius - b.radius).abs() < 2.0
}

/// Each image's noise standard deviation inside `circle` (Immerkær 1996, on the pixels of the
/// disc; see [`crate::ps::noise::image_noise`]): the sphere's own noise, which a dark or
/// clipped background would understate. A millionth of full scale where it cannot be told.
fn disc_noise(grey: &[Vec<f32>], w: usize, h: usize, circle: &sphere::Circle) -> Vec<f64> {
    let disc = Grid::from_fn(w, h, |x, y| {
        (x as f64 - circle.cx).hypot(y as f64 - circle.cy) < 0.97 * circle.radius
    });
    grey.iter()
        .map(|img| {
            let s = f64::from(crate::ps::noise::image_noise(img, w, &disc).sigma);
            if s.is_finite() { s.max(1e-6) } else { 1e-6 }
        })
        .collect()
}

/// What the images say of a candidate circle.
#[derive(Debug, Clone, Copy)]
struct Verification {
    /// Images whose excess over the median peaks inside the circle at ≥ `LIT_SIGMAS` σ
    /// (a highlight on a mirror ball, the lit side of a matte one).
    lit: usize,
    /// Images whose own edge across the circle is significant, with the sign of the median's.
    edged: usize,
    /// Images.
    images: usize,
}

/// An image's excess over the median must reach this many noise σ inside a circle for the
/// image to count as lighting what is in it.
const LIT_SIGMAS: f64 = 10.0;
/// An image's mean step across the outline must reach this many standard errors.
const EDGE_SIGMAS: f64 = 3.0;

impl Verification {
    fn passed(&self) -> bool {
        // Most images light the sphere (some lights may be behind it), and nearly every image
        // shows its outline. A lamp that lights the wall more or less than the others can
        // reverse the ball's contrast in its image, and such captures are refused (the classic
        // 12-light chrome ball, whose outline is one 8-bit code deep, shows it in 10 of 12);
        // relaxing this needs an outline error that allows for quantisation (docs).
        2 * self.lit >= self.images && 10 * self.edged >= 9 * self.images
    }

    fn describe(&self, c: &Candidate) -> String {
        let k = c.fit.circle;
        format!(
            "centre ({:.1}, {:.1}) radius {:.1} px: edges over {:.0}% of its outline in the frame, lit in {} of {} images, outline seen in {}",
            k.cx,
            k.cy,
            k.radius,
            c.support * 100.0,
            self.lit,
            self.images,
            self.edged
        )
    }
}

/// Checks a candidate against every image: is something inside it lit differently by each
/// light (a highlight, shading), and does each image show its outline?
fn verify(
    c: &Candidate,
    grey: &[Vec<f32>],
    median: &ScalarMap,
    w: usize,
    h: usize,
) -> Verification {
    let noise = disc_noise(grey, w, h, &c.fit.circle);
    let k = c.fit.circle;
    let inner = k.radius * 0.97;
    let x0 = (k.cx - inner).floor().max(0.0) as usize;
    let x1 = ((k.cx + inner).ceil().max(0.0) as usize).min(w.saturating_sub(1));
    let y0 = (k.cy - inner).floor().max(0.0) as usize;
    let y1 = ((k.cy + inner).ceil().max(0.0) as usize).min(h.saturating_sub(1));
    // Points just inside and outside the outline, in the frame.
    let samples = (2.0 * std::f64::consts::PI * k.radius).ceil().max(16.0) as usize;
    let pairs: Vec<(usize, usize)> = (0..samples)
        .filter_map(|i| {
            let a = i as f64 / samples as f64 * std::f64::consts::TAU;
            let at = |r: f64| {
                let (x, y) = ((k.cx + r * a.cos()).round(), (k.cy + r * a.sin()).round());
                (x >= 0.0 && y >= 0.0 && x < w as f64 && y < h as f64)
                    .then(|| y as usize * w + x as usize)
            };
            Some((at(k.radius - 2.5)?, at(k.radius + 2.5)?))
        })
        .collect();
    let step = |img: &[f32]| {
        let d: Vec<f64> = pairs
            .iter()
            .map(|&(i, o)| f64::from(img[o]) - f64::from(img[i]))
            .filter(|v| v.is_finite())
            .collect();
        d.iter().sum::<f64>() / d.len().max(1) as f64
    };
    let reference = step(median.data());
    let mut lit = 0;
    let mut edged = 0;
    for (img, sigma) in grey.iter().zip(&noise) {
        let mut peak = f64::MIN;
        for y in y0..=y1 {
            for x in x0..=x1 {
                if (x as f64 - k.cx).hypot(y as f64 - k.cy) < inner {
                    let i = y * w + x;
                    let d = f64::from(img[i] - median.data()[i]);
                    if d > peak {
                        peak = d;
                    }
                }
            }
        }
        if peak >= LIT_SIGMAS * sigma {
            lit += 1;
        }
        // The step's standard error: two noisy samples a pair, independent pairs.
        let se = sigma * (2.0 / pairs.len().max(1) as f64).sqrt();
        let s = step(img);
        if s.abs() >= EDGE_SIGMAS * se && s * reference > 0.0 {
            edged += 1;
        }
    }
    Verification {
        lit,
        edged,
        images: grey.len(),
    }
}

/// How the intensities were measured, for the calibration report.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "reference", rename_all = "kebab-case")]
pub enum IntensityCalibration {
    /// From a matte sphere ([`intensity::intensities_from_sphere`]).
    MatteSphere {
        /// Its outline.
        sphere: CircleFit,
        /// Where the outline came from.
        sphere_source: SphereSource,
        /// Per light: intensity, the direction the shading gives, fit quality.
        fits: Vec<intensity::MatteLight>,
    },
    /// From a grey card ([`intensity::intensities_from_card`]).
    GreyCard {
        /// Card pixels.
        pixels: usize,
        /// The card's normal.
        normal: [f64; 3],
    },
}

/// The lights file `photostereo calibrate` writes: the JSON lights format (see
/// [`crate::capture::lights`]) with each light's `confidence` and `uncertainty_deg` from its highlight,
/// and a `calibration` section holding the sphere, every highlight and the intensity
/// measurement. [`Lights::from_file`] reads it back (the extra fields are informational).
pub fn lights_file_json(
    lights: &Lights,
    chrome: &ChromeCalibration,
    intensity: Option<&IntensityCalibration>,
) -> String {
    let highlights = chrome.highlights();
    let entries: Vec<serde_json::Value> = lights
        .lights()
        .iter()
        .zip(&highlights)
        .map(|(l, h)| {
            let mut v = serde_json::json!({
                "direction": [l.direction.x, l.direction.y, l.direction.z],
                "intensity": l.intensity,
            });
            if let Some(h) = h {
                v["confidence"] = serde_json::json!(h.confidence);
                v["uncertainty_deg"] = serde_json::json!(h.uncertainty_deg);
                v["accepted"] = serde_json::json!(h.accepted);
            }
            v
        })
        .collect();
    let camera = match &chrome.cone {
        None => serde_json::json!(
            "orthographic, view direction (0, 0, 1); l = 2(n·v)n − v at the highlight"
        ),
        Some(k) => serde_json::json!({
            "model": "pinhole; l = 2(n·e)n − e with e the pixel's ray towards the camera",
            "intrinsics": k.camera,
        }),
    };
    let doc = serde_json::json!({
        "lights": entries,
        "calibration": {
            "camera": camera,
            "chrome": chrome,
            "intensity": intensity,
        },
    });
    // Serialising numbers, strings and derived structs cannot fail.
    serde_json::to_string_pretty(&doc).unwrap_or_default()
}

/// The saturated pixels of image `index` (its grey `plane`): those the stack flags when it
/// knows a saturation level (integer files, or a level given); otherwise (float data), where
/// two or more pixels share the image's maximum, those at it (clipped at a level of its own).
fn clipped(stack: &ImageStack, index: usize, plane: &[f32]) -> Vec<bool> {
    let top = plane
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(f32::MIN, f32::max);
    let at_top = plane.iter().filter(|v| **v >= top).count();
    plane
        .iter()
        .enumerate()
        .map(|(p, v)| match stack.saturation_bits(index) {
            Some(_) => stack.is_saturated(index, p),
            None => at_top >= 2 && *v >= top,
        })
        .collect()
}

/// `plane` minus `median` (the plane itself without one).
fn excess(plane: &[f32], median: Option<&ScalarMap>) -> Vec<f32> {
    match median {
        Some(m) => plane.iter().zip(m.data()).map(|(v, m)| v - m).collect(),
        None => plane.to_vec(),
    }
}

/// Full-image grey planes of a stack ([`ImageStack::grey_mix`]; NaN outside its window).
fn grey_images(stack: &ImageStack) -> Vec<Vec<f32>> {
    let grey = stack.grey_mix();
    let (w, h) = (grey.width(), grey.height());
    let win = grey.window();
    (0..grey.count())
        .map(|k| {
            let plane = grey.plane(k, 0);
            let mut out = vec![f32::NAN; w * h];
            for (y, row) in (win.y0..win.y1).zip(plane.chunks_exact(win.width().max(1))) {
                out[y * w + win.x0..y * w + win.x1].copy_from_slice(row);
            }
            out
        })
        .collect()
}

/// An image in which the sphere's outline is sought: the per-pixel `q`-quantile of the images.
/// A highlight lights a pixel in one image or two, so a median or upper quartile drops it (a
/// mean would keep it as an edge of its own) and keeps what most images share: the ball's
/// reflection of its surroundings, ambient light, the background. A matte ball's rim, which
/// about half the lights reach, stays lit in the upper quartile.
fn evidence(grey: &[Vec<f32>], w: usize, h: usize, q: f64) -> ScalarMap {
    let mut column = Vec::with_capacity(grey.len());
    let quartile: Vec<f32> = (0..w * h)
        .map(|p| {
            column.clear();
            column.extend(grey.iter().map(|img| img[p]).filter(|v| v.is_finite()));
            if column.is_empty() {
                return 0.0;
            }
            let k = ((column.len() - 1) as f64 * q).round() as usize;
            let (_, q, _) = column.select_nth_unstable_by(k, f32::total_cmp);
            *q
        })
        .collect();
    Grid::from_vec(w, h, quartile).unwrap_or_else(|_| Grid::new(w, h, 0.0))
}

/// Reads reference images as they are stored (no intensity division), grey or RGB as the
/// files are, with the given transfer function and saturation level (see
/// [`LoadOptions::saturation`]).
///
/// # Errors
/// As [`load_stack`].
pub fn load_reference_images(
    paths: &[PathBuf],
    transfer: Transfer,
    saturation: Option<f32>,
    progress: &dyn Progress,
) -> Result<ImageStack> {
    let Some(first) = paths.first() else {
        return Err(Error::TooFewImages { count: 0 });
    };
    let color = if read_image(first)?.channels == 3 {
        ColorMode::PerChannel
    } else {
        ColorMode::Grey
    };
    let unit = Lights::new(vec![Light::new(Vector3::z()); paths.len()])?;
    load_stack(
        paths,
        &unit,
        &LoadOptions {
            color,
            transfer,
            saturation,
            window: None,
        },
        progress,
    )
}

/// Reads a mask image as grey values in [0, 1] (its first channel), for sub-pixel outlines.
///
/// # Errors
/// As [`read_image`].
pub fn read_grey_mask(path: &Path) -> Result<ScalarMap> {
    let img = read_image(path)?;
    let data = img
        .data
        .chunks_exact(img.channels)
        .map(|px| px[0])
        .collect();
    Grid::from_vec(img.width, img.height, data)
}

/// Writes a vector as a JSON array `[x, y, z]`.
fn serialize_vector<S: serde::Serializer>(
    v: &Vector3<f64>,
    s: S,
) -> std::result::Result<S::Ok, S::Error> {
    serde::Serialize::serialize(&[v.x, v.y, v.z], s)
}
