//! Light calibration from reference objects photographed under each light: directions from a
//! mirror (chrome) sphere, relative intensities from a matte sphere or a grey card.
//!
//! The chrome sphere's outline comes from its mask ([`sphere::circle_from_mask`], sub-pixel) or
//! is detected in the images ([`sphere::detect_circle`]); each image's highlight gives its
//! light by reflecting the view direction about the sphere's normal, l = 2(n·v)n − v with
//! v = (0, 0, 1) ([`highlight::find_highlight`]). [`intensity`] then reads relative intensities
//! off a Lambertian reference. The result is a [`Lights`] set for the main pipeline, and a
//! report with each light's confidence and the warnings.
//!
//! The camera is orthographic, as everywhere in the crate. With a perspective lens the view
//! direction varies over the sphere by the angle the sphere subtends; the error this makes is
//! of the order of the highlight's offset from the principal point divided by the focal length.
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

pub mod highlight;
pub mod intensity;
pub mod sphere;

use crate::capture::lights::{Light, Lights};
use crate::capture::stack::{ColorMode, ImageStack, LoadOptions, Transfer, load_stack};
use crate::error::{Error, Result};
use crate::grid::{Grid, ScalarMap};
use crate::io::decode::read_image;
use crate::progress::Progress;
use highlight::{Highlight, HighlightOptions, Missing, find_highlight};
use nalgebra::Vector3;
use serde::Serialize;
use sphere::{CircleFit, circle_from_mask, detect_circle};
use std::path::{Path, PathBuf};

/// Options of [`calibrate_chrome`].
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct ChromeOptions {
    /// How highlights are found.
    pub highlight: HighlightOptions,
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
    /// The sphere's outline.
    pub sphere: CircleFit,
    /// Where it came from.
    pub sphere_source: SphereSource,
    /// One outcome per image, in order.
    pub lights: Vec<LightOutcome>,
    /// Warnings about the calibration as a whole (per-light ones are in their highlights).
    pub warnings: Vec<String>,
}

impl ChromeCalibration {
    /// The light directions, one per image, with unit intensity.
    ///
    /// # Errors
    /// [`Error::BadImage`] naming the first image without a highlight (the message lists them
    /// all): a lights file must have one light per image.
    pub fn lights(&self) -> Result<Lights> {
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
/// grey mask, with its file for errors) or, without one, detected in the per-pixel median or
/// upper quartile of the images;
/// then each image's highlight (see [`highlight::find_highlight`]).
///
/// # Errors
/// [`Error::DimensionMismatch`] when the mask's size differs from the images';
/// [`Error::Mask`] when the mask's outline is not a circle; [`Error::SphereNotFound`] when no
/// sphere is detected; [`Error::TooFewImages`] for an empty stack.
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
    let (sphere, source) = find_sphere_in(&grey, w, h, mask)?;
    let mut warnings = Vec::new();
    let c = sphere.circle;
    if c.cx - c.radius < 0.0
        || c.cy - c.radius < 0.0
        || c.cx + c.radius > w as f64
        || c.cy + c.radius > h as f64
    {
        warnings.push("the sphere is cut by the image border".to_string());
    }
    if sphere.std_err.iter().any(|s| *s > 0.5) {
        warnings.push(format!(
            "the sphere's outline is uncertain (standard errors {:.2}, {:.2}, {:.2} px for centre and radius)",
            sphere.std_err[0], sphere.std_err[1], sphere.std_err[2]
        ));
    }
    let lights = grey
        .iter()
        .enumerate()
        .map(|(index, plane)| LightOutcome {
            index,
            image: stack.info()[index].path.clone(),
            result: match find_highlight(plane, w, &sphere, &options.highlight) {
                Ok(hl) => HighlightResult::Found(hl),
                Err(m) => HighlightResult::Missing(m),
            },
        })
        .collect();
    Ok(ChromeCalibration {
        sphere,
        sphere_source: source,
        lights,
        warnings,
    })
}

/// The outline of a sphere in `stack`: fitted to `mask` (a grey mask, with its file for
/// errors) or, without one, detected in the per-pixel median or upper quartile of the images.
///
/// # Errors
/// As [`calibrate_chrome`].
pub fn find_sphere(
    stack: &ImageStack,
    mask: Option<(&ScalarMap, &Path)>,
) -> Result<(CircleFit, SphereSource)> {
    find_sphere_in(&grey_images(stack), stack.width(), stack.height(), mask)
}

fn find_sphere_in(
    grey: &[Vec<f32>],
    w: usize,
    h: usize,
    mask: Option<(&ScalarMap, &Path)>,
) -> Result<(CircleFit, SphereSource)> {
    Ok(match mask {
        Some((m, path)) => {
            Grid::new(w, h, ()).check_same_size(m, "sphere mask vs images")?;
            (circle_from_mask(m, path)?, SphereSource::Mask)
        }
        None => {
            // The median suits a mirror ball (it drops every highlight), the upper quartile a
            // matte one (its rim stays lit); the outline that more of a circle supports wins.
            let fits = [0.5, 0.75].map(|q| detect_circle(&evidence(grey, w, h, q)));
            let best = fits
                .iter()
                .filter_map(|f| f.as_ref().ok())
                .max_by(|a, b| {
                    a.coverage
                        .total_cmp(&b.coverage)
                        .then(b.rms_px.total_cmp(&a.rms_px))
                })
                .copied();
            match (best, fits) {
                (Some(fit), _) => (fit, SphereSource::Detected),
                (None, [Err(e), _]) => return Err(e),
                (None, _) => unreachable!("no fit implies the first failed"),
            }
        }
    })
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
            }
            v
        })
        .collect();
    let doc = serde_json::json!({
        "lights": entries,
        "calibration": {
            "camera": "orthographic, view direction (0, 0, 1); l = 2(n·v)n − v at the highlight",
            "chrome": chrome,
            "intensity": intensity,
        },
    });
    // Serialising numbers, strings and derived structs cannot fail.
    serde_json::to_string_pretty(&doc).unwrap_or_default()
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
/// files are, with the given transfer function.
///
/// # Errors
/// As [`load_stack`].
pub fn load_reference_images(
    paths: &[PathBuf],
    transfer: Transfer,
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
            saturation: None,
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
