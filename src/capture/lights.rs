//! Distant light sources: directions, per-channel intensities and the files that describe them.
//!
//! Camera frame: x to the right, y up, z towards the camera; a light direction points from the
//! surface towards the light. Directions are normalised on construction.
//!
//! Two file formats are read:
//! - JSON: `{"lights": [{"file": "img_000.exr", "direction": [x, y, z], "intensity": 1.0}, ...]}`
//!   where `intensity` (a scalar or `[r, g, b]`, default 1) and `file` are optional;
//! - plain text: one `x y z` line per light, `#` comments and blank lines ignored, with an
//!   optional first line holding only the number of lights (the layout of the classic `lights.txt`).

use crate::error::{Error, Result};
use crate::linalg::condition_from_gram;
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Condition number of the light matrix above which a light set is rejected as degenerate.
pub const MAX_LIGHT_CONDITION: f64 = 1e4;

/// One distant light.
#[derive(Debug, Clone, PartialEq)]
pub struct Light {
    /// Unit vector from the surface towards the light, camera frame.
    pub direction: Vector3<f64>,
    /// Relative irradiance per colour channel (R, G, B); grey data uses the BT.601 mix.
    pub intensity: [f64; 3],
    /// Image file this light belongs to, when the lights file names one.
    pub file: Option<String>,
    /// The light's position (camera frame), when it is a near light measured as one (e.g. by
    /// two mirror balls, [`crate::calibrate::near`]); `direction` is then the direction to it
    /// from a point of the scene (from two balls: their midpoint, where the object should be).
    /// The distant-light solvers use `direction` (the distant approximation); the near-light
    /// solver ([`crate::ps::near`]) uses the position, the inverse-square fall-off and
    /// [`Light::anisotropy`].
    pub position: Option<Vector3<f64>>,
    /// The angular profile of a positioned light (an LED), `None` for an isotropic one.
    pub anisotropy: Option<Anisotropy>,
}

/// The angular profile of a near light (Quéau, Durix, Wu, Cremers, Lauze and Durou,
/// "LED-based photometric stereo: modeling, calibration and numerical solution", JMIV 2018):
/// the light's radiant intensity towards a point X is Φ·cos^μ θ, θ the angle between its
/// principal direction D and X − P. μ = 0 is an isotropic point source; a Lambertian LED has
/// μ = 1.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Anisotropy {
    /// Unit principal direction D (camera frame), the direction the LED points at.
    pub principal: Vector3<f64>,
    /// Exponent μ ≥ 0 of the cosine profile.
    pub mu: f64,
}

/// An ordered set of distant lights, one per image.
#[derive(Debug, Clone, PartialEq)]
pub struct Lights {
    pub(crate) lights: Vec<Light>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonFile {
    lights: Vec<JsonLight>,
    /// Written by `photostereo calibrate`: how the lights were measured (informational).
    #[serde(default, rename = "calibration")]
    _calibration: Option<serde::de::IgnoredAny>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonLight {
    #[serde(default)]
    file: Option<String>,
    direction: [f64; 3],
    #[serde(default)]
    intensity: Option<JsonIntensity>,
    #[serde(default)]
    position: Option<[f64; 3]>,
    /// The principal direction of an anisotropic near light ([`Anisotropy`]).
    #[serde(default)]
    principal: Option<[f64; 3]>,
    /// The exponent of an anisotropic near light's cosine profile ([`Anisotropy`]).
    #[serde(default)]
    mu: Option<f64>,
    /// Written by `photostereo calibrate` (informational).
    #[serde(default, rename = "position_uncertainty")]
    _position_uncertainty: Option<f64>,
    /// Written by `photostereo calibrate` (informational).
    #[serde(default, rename = "confidence")]
    _confidence: Option<f64>,
    /// Written by `photostereo calibrate` (informational).
    #[serde(default, rename = "uncertainty_deg")]
    _uncertainty_deg: Option<f64>,
    /// Written by `photostereo calibrate` (informational).
    #[serde(default, rename = "accepted")]
    _accepted: Option<bool>,
}

#[derive(Deserialize, Serialize, Clone, Copy)]
#[serde(untagged)]
enum JsonIntensity {
    Scalar(f64),
    Rgb([f64; 3]),
}

#[derive(Serialize)]
struct JsonOut<'a> {
    lights: Vec<JsonLightOut<'a>>,
}

#[derive(Serialize)]
struct JsonLightOut<'a> {
    #[serde(skip_serializing_if = "Option::is_none")]
    file: Option<&'a str>,
    direction: [f64; 3],
    intensity: JsonIntensity,
    #[serde(skip_serializing_if = "Option::is_none")]
    position: Option<[f64; 3]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    principal: Option<[f64; 3]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    mu: Option<f64>,
}

impl Light {
    /// A light of unit intensity in direction `direction` (normalised by [`Lights::new`]).
    pub fn new(direction: Vector3<f64>) -> Self {
        Light {
            direction,
            intensity: [1.0; 3],
            file: None,
            position: None,
            anisotropy: None,
        }
    }

    /// A near light at `position` (camera frame) of unit intensity, isotropic; its `direction`
    /// is the direction to it from `target` (where the object is), for the distant
    /// approximation.
    pub fn near(position: Vector3<f64>, target: Vector3<f64>) -> Self {
        Light {
            direction: position - target,
            intensity: [1.0; 3],
            file: None,
            position: Some(position),
            anisotropy: None,
        }
    }

    /// The intensity seen by a grey (BT.601-mixed) image.
    pub fn grey_intensity(&self) -> f64 {
        crate::capture::stack::GREY_WEIGHTS
            .iter()
            .zip(&self.intensity)
            .map(|(w, i)| f64::from(*w) * i)
            .sum()
    }
}

/// Smallest light intensity accepted: images are divided by intensities in 32-bit floats,
/// whose range (about 1e-38 to 3e38) must hold a pixel's value over it with room to spare.
pub const MIN_INTENSITY: f64 = 1e-30;
/// Largest light intensity accepted (see [`MIN_INTENSITY`]).
pub const MAX_INTENSITY: f64 = 1e30;

/// "0, 3 and 5": light indices for messages, the first 8.
pub(crate) fn index_list(indices: &[usize]) -> String {
    let shown: Vec<String> = indices.iter().take(8).map(|i| i.to_string()).collect();
    let mut text = match shown.len() {
        0 => String::new(),
        1 => shown[0].clone(),
        n => format!("{} and {}", shown[..n - 1].join(", "), shown[n - 1]),
    };
    if indices.len() > 8 {
        text = format!("{}, … ({} in all)", shown.join(", "), indices.len());
    }
    text
}

impl Lights {
    /// Validates and normalises a light set.
    ///
    /// # Errors
    /// [`Error::InvalidLight`] for a zero or non-finite direction or a non-positive,
    /// non-finite or out-of-range ([`MIN_INTENSITY`], [`MAX_INTENSITY`]) intensity.
    pub fn new(mut lights: Vec<Light>) -> Result<Self> {
        for (index, light) in lights.iter_mut().enumerate() {
            let d = light.direction;
            if !d.iter().all(|v| v.is_finite()) {
                return Err(Error::InvalidLight {
                    index,
                    reason: format!("direction {:?} is not finite", d.as_slice()),
                });
            }
            // Huge or tiny components would overflow or underflow the norm: those directions
            // are scaled by their largest component first.
            let largest = d.amax();
            if largest < 1e-12 {
                return Err(Error::InvalidLight {
                    index,
                    reason: "direction is the zero vector".into(),
                });
            }
            let norm = d.norm();
            light.direction = if norm.is_finite() && norm > 1e-150 {
                d / norm
            } else {
                let scaled = d / largest;
                scaled / scaled.norm()
            };
            if let Some(p) = light.position
                && !p.iter().all(|v| v.is_finite())
            {
                return Err(Error::InvalidLight {
                    index,
                    reason: format!("position {:?} is not finite", p.as_slice()),
                });
            }
            if let Some(a) = &mut light.anisotropy {
                if light.position.is_none() {
                    return Err(Error::InvalidLight {
                        index,
                        reason: "an angular profile (principal direction and mu) needs a position"
                            .into(),
                    });
                }
                let norm = a.principal.norm();
                if !(norm.is_finite() && norm > 1e-12) {
                    return Err(Error::InvalidLight {
                        index,
                        reason: format!(
                            "principal direction {:?} is zero or not finite",
                            a.principal.as_slice()
                        ),
                    });
                }
                a.principal /= norm;
                if !(a.mu.is_finite() && (0.0..=1000.0).contains(&a.mu)) {
                    return Err(Error::InvalidLight {
                        index,
                        reason: format!("mu {} must be in 0..=1000", a.mu),
                    });
                }
            }
            if let Some(bad) = light
                .intensity
                .iter()
                .find(|i| !i.is_finite() || **i <= 0.0)
            {
                return Err(Error::InvalidLight {
                    index,
                    reason: format!("intensity {bad} must be finite and positive"),
                });
            }
            if let Some(bad) = light
                .intensity
                .iter()
                .find(|i| !(MIN_INTENSITY..=MAX_INTENSITY).contains(*i))
            {
                return Err(Error::InvalidLight {
                    index,
                    reason: format!(
                        "intensity {bad:e} is outside {MIN_INTENSITY:e}..{MAX_INTENSITY:e}: images are divided by it in 32-bit floats, where it would underflow or overflow; give the intensities relative to each other (scaled so that the brightest is 1, say)"
                    ),
                });
            }
        }
        Ok(Lights { lights })
    }

    /// How many lights have a position ([`Light::position`]).
    pub fn positioned(&self) -> usize {
        self.lights.iter().filter(|l| l.position.is_some()).count()
    }

    /// Lights of unit intensity from directions.
    ///
    /// # Errors
    /// As [`Lights::new`].
    pub fn from_directions(directions: &[Vector3<f64>]) -> Result<Self> {
        Lights::new(directions.iter().map(|d| Light::new(*d)).collect())
    }

    /// Reads a lights file, JSON or plain text (decided by content: JSON starts with `{`).
    ///
    /// # Errors
    /// [`Error::Io`] when unreadable, [`Error::LightsFile`] when malformed, and the errors of
    /// [`Lights::new`].
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = crate::io::input::read_text(path)?;
        if text.trim_start().starts_with('{') {
            Lights::from_json_str(&text, path)
        } else {
            Lights::from_text_str(&text, path)
        }
    }

    /// Parses the JSON format; `source` names the file in errors.
    ///
    /// # Errors
    /// [`Error::LightsFile`] when malformed; the errors of [`Lights::new`].
    pub fn from_json_str(text: &str, source: &Path) -> Result<Self> {
        let parsed: JsonFile = serde_json::from_str(text).map_err(|e| Error::LightsFile {
            path: source.to_path_buf(),
            line: Some(e.line()),
            reason: format!(
                "{e}; expected {{\"lights\": [{{\"file\": \"img.exr\", \"direction\": [x, y, z], \"intensity\": 1.0}}, ...]}}"
            ),
        })?;
        let mut lights = Vec::with_capacity(parsed.lights.len());
        for (index, l) in parsed.lights.into_iter().enumerate() {
            let anisotropy = match (l.principal, l.mu) {
                (None, None) => None,
                (Some(d), Some(mu)) => Some(Anisotropy {
                    principal: Vector3::from(d),
                    mu,
                }),
                (Some(_), None) | (None, Some(_)) => {
                    return Err(Error::InvalidLight {
                        index,
                        reason: format!(
                            "{}: `principal` and `mu` describe the light's angular profile together; give both or neither",
                            source.display()
                        ),
                    });
                }
            };
            lights.push(Light {
                direction: Vector3::from(l.direction),
                intensity: match l.intensity {
                    None => [1.0; 3],
                    Some(JsonIntensity::Scalar(s)) => [s; 3],
                    Some(JsonIntensity::Rgb(rgb)) => rgb,
                },
                file: l.file,
                position: l.position.map(Vector3::from),
                anisotropy,
            });
        }
        Lights::new(lights)
    }

    /// Parses `x y z` lines (optionally preceded by a line holding the count).
    ///
    /// # Errors
    /// [`Error::LightsFile`] naming the line when malformed; the errors of [`Lights::new`].
    pub fn from_text_str(text: &str, source: &Path) -> Result<Self> {
        let rows = parse_number_rows(text, source)?;
        let rows = strip_count_line(rows);
        let mut directions = Vec::with_capacity(rows.len());
        for (line, values) in rows {
            if values.len() != 3 {
                return Err(Error::LightsFile {
                    path: source.to_path_buf(),
                    line: Some(line),
                    reason: format!("expected 3 numbers `x y z`, found {}", values.len()),
                });
            }
            directions.push(Vector3::new(values[0], values[1], values[2]));
        }
        if directions.is_empty() {
            return Err(Error::LightsFile {
                path: source.to_path_buf(),
                line: None,
                reason: "no light directions found".into(),
            });
        }
        Lights::from_directions(&directions)
    }

    /// Replaces the intensities by those of a text file of `r g b` (or single-value) lines,
    /// as DiLiGenT's `light_intensities.txt`.
    ///
    /// # Errors
    /// [`Error::LightsFile`] when malformed or when the number of lines differs from the
    /// number of lights; [`Error::InvalidLight`] for a non-positive intensity.
    pub fn with_intensities_file(mut self, path: &Path) -> Result<Self> {
        let text = crate::io::input::read_text(path)?;
        let rows = strip_count_line(parse_number_rows(&text, path)?);
        if rows.len() != self.lights.len() {
            return Err(Error::LightsFile {
                path: path.to_path_buf(),
                line: None,
                reason: format!(
                    "{} intensity lines for {} lights",
                    rows.len(),
                    self.lights.len()
                ),
            });
        }
        for (light, (line, values)) in self.lights.iter_mut().zip(rows) {
            light.intensity = match values.as_slice() {
                [s] => [*s; 3],
                [r, g, b] => [*r, *g, *b],
                _ => {
                    return Err(Error::LightsFile {
                        path: path.to_path_buf(),
                        line: Some(line),
                        reason: format!("expected `r g b` or one value, found {}", values.len()),
                    });
                }
            };
        }
        Lights::new(self.lights)
    }

    /// Number of lights.
    pub fn len(&self) -> usize {
        self.lights.len()
    }

    /// True when there are no lights.
    pub fn is_empty(&self) -> bool {
        self.lights.is_empty()
    }

    /// The lights in order.
    pub fn lights(&self) -> &[Light] {
        &self.lights
    }

    /// Light `index`.
    pub fn get(&self, index: usize) -> Option<&Light> {
        self.lights.get(index)
    }

    /// Indices of `count` well-spread lights, by greedy farthest-point selection: first the
    /// light nearest the mean direction, then each time the light whose smallest angle to
    /// those chosen is largest (ties to the lower index). The indices are returned sorted.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] (`count`) when it is 0 or more than there are lights.
    ///
    /// # Example
    /// ```
    /// use photostereo::capture::lights::Lights;
    /// let lights = Lights::fibonacci(40, 20.0)?;
    /// let pick = lights.spread(4)?;
    /// assert_eq!(pick.len(), 4);
    /// // Four spread lights are far better conditioned than four neighbours.
    /// let near = Lights::new(lights.lights()[..4].to_vec())?;
    /// let spread = Lights::new(pick.iter().map(|&k| lights.lights()[k].clone()).collect())?;
    /// assert!(spread.condition_number() < near.condition_number());
    /// # Ok::<(), photostereo::Error>(())
    /// ```
    pub fn spread(&self, count: usize) -> Result<Vec<usize>> {
        let n = self.lights.len();
        if count == 0 || count > n {
            return Err(Error::param(
                "count",
                format!("{count} lights asked of {n}"),
            ));
        }
        let dirs: Vec<Vector3<f64>> = self
            .lights
            .iter()
            .map(|l| l.direction.normalize())
            .collect();
        let mean = dirs.iter().sum::<Vector3<f64>>();
        let first = (0..n)
            .max_by(|&a, &b| {
                dirs[a]
                    .dot(&mean)
                    .total_cmp(&dirs[b].dot(&mean))
                    .then(b.cmp(&a))
            })
            .unwrap_or(0);
        let mut chosen = vec![first];
        // Cosine of the nearest chosen light, per light (larger is nearer).
        let mut nearest: Vec<f64> = dirs.iter().map(|d| d.dot(&dirs[first])).collect();
        while chosen.len() < count {
            let next = (0..n)
                .filter(|k| !chosen.contains(k))
                .min_by(|&a, &b| nearest[a].total_cmp(&nearest[b]).then(a.cmp(&b)))
                .unwrap_or(0);
            chosen.push(next);
            for (c, d) in nearest.iter_mut().zip(&dirs) {
                *c = c.max(d.dot(&dirs[next]));
            }
        }
        chosen.sort_unstable();
        Ok(chosen)
    }

    /// Unit directions in order.
    pub fn directions(&self) -> Vec<Vector3<f64>> {
        self.lights.iter().map(|l| l.direction).collect()
    }

    /// Condition number σ_max/σ_min of the m×3 light matrix L (rows = directions).
    /// Least-squares error in g grows with it; coplanar lights give infinity.
    pub fn condition_number(&self) -> f64 {
        let gram = self.lights.iter().fold(Matrix3::zeros(), |acc, l| {
            acc + l.direction * l.direction.transpose()
        });
        condition_from_gram(&gram)
    }

    /// Checks that the set can determine g = ρN: at least 3 lights, no more than half of them
    /// behind the surface ([`Lights::behind`]: a sign convention other than this tool's), and
    /// a condition number below `max_condition`.
    ///
    /// # Errors
    /// [`Error::TooFewImages`], [`Error::InvalidLight`] naming the first light behind, or
    /// [`Error::DegenerateLights`].
    pub fn check_usable(&self, max_condition: f64) -> Result<()> {
        if self.lights.len() < 3 {
            return Err(Error::TooFewImages {
                count: self.lights.len(),
            });
        }
        let behind = self.behind();
        if 2 * behind.len() > self.lights.len() {
            let d = self.lights[behind[0]].direction;
            return Err(Error::InvalidLight {
                index: behind[0],
                reason: format!(
                    "direction ({:.3}, {:.3}, {:.3}) points behind the surface, as do {} of the {} lights ({}): in this tool's frame z points from the object towards the camera, and lights behind the object give normals facing away from it; if the lights file uses the opposite convention, flip the sign of z",
                    d.x,
                    d.y,
                    d.z,
                    behind.len(),
                    self.lights.len(),
                    index_list(&behind)
                ),
            });
        }
        let condition = self.condition_number();
        if condition.is_nan() || condition > max_condition {
            return Err(Error::DegenerateLights {
                condition,
                limit: max_condition,
            });
        }
        Ok(())
    }

    /// Indices of the lights behind the surface as the camera sees it (z < 0, z pointing from
    /// the object towards the camera): they light only surfaces turned more than 90° from
    /// the camera's view of their direction's horizon, which the camera barely sees.
    pub fn behind(&self) -> Vec<usize> {
        self.lights
            .iter()
            .enumerate()
            .filter(|(_, l)| l.direction.z < 0.0)
            .map(|(i, _)| i)
            .collect()
    }

    /// Returns the lights reordered to follow `images`.
    ///
    /// When every light names a `file`, each image is matched to the light whose `file` equals
    /// the image path as given, or else its file name. When no light names a file, the order
    /// is kept and the counts must agree.
    ///
    /// # Errors
    /// [`Error::LightsMismatch`] when counts differ, a file is unmatched or matched twice, or
    /// only some lights name files.
    pub fn matched_to(&self, images: &[PathBuf]) -> Result<Lights> {
        let named = self.lights.iter().filter(|l| l.file.is_some()).count();
        if named == 0 {
            if self.lights.len() != images.len() {
                return Err(Error::LightsMismatch {
                    reason: format!(
                        "{} lights for {} images; give one light per image, in the order of the images",
                        self.lights.len(),
                        images.len()
                    ),
                });
            }
            return Ok(self.clone());
        }
        if named != self.lights.len() {
            return Err(Error::LightsMismatch {
                reason: format!(
                    "{named} of {} lights name a `file`; name a file for every light or for none",
                    self.lights.len()
                ),
            });
        }
        let mut used = vec![false; self.lights.len()];
        let mut out = Vec::with_capacity(images.len());
        for (index, image) in images.iter().enumerate() {
            let full = image.to_string_lossy();
            let base = image
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let found = self
                .lights
                .iter()
                .position(|l| l.file.as_deref() == Some(full.as_ref()))
                .or_else(|| {
                    self.lights.iter().position(|l| {
                        l.file
                            .as_deref()
                            .map(|f| Path::new(f).file_name().map(|n| n.to_string_lossy()))
                            == Some(Some(base.as_str().into()))
                    })
                });
            let Some(k) = found else {
                return Err(Error::LightsMismatch {
                    reason: format!(
                        "image {index} ({}) has no light in the lights file (a frame taken with every lamp off is not one of the images: give it as the ambient image)",
                        image.display()
                    ),
                });
            };
            if used[k] {
                return Err(Error::LightsMismatch {
                    reason: format!(
                        "image {index} ({}) matches light {k}, which another image already uses",
                        image.display()
                    ),
                });
            }
            used[k] = true;
            out.push(self.lights[k].clone());
        }
        if let Some(k) = used.iter().position(|u| !u) {
            return Err(Error::LightsMismatch {
                reason: format!(
                    "light {k} (file {:?}) matches no image given",
                    self.lights[k].file.as_deref().unwrap_or("")
                ),
            });
        }
        Lights::new(out)
    }

    /// Serialises to the JSON lights format (intensity written as `[r, g, b]`, or a scalar when
    /// the three are equal).
    pub fn to_json(&self) -> String {
        let out = JsonOut {
            lights: self
                .lights
                .iter()
                .map(|l| JsonLightOut {
                    file: l.file.as_deref(),
                    direction: [l.direction.x, l.direction.y, l.direction.z],
                    intensity: if l.intensity[0] == l.intensity[1]
                        && l.intensity[1] == l.intensity[2]
                    {
                        JsonIntensity::Scalar(l.intensity[0])
                    } else {
                        JsonIntensity::Rgb(l.intensity)
                    },
                    position: l.position.map(|p| [p.x, p.y, p.z]),
                    principal: l
                        .anisotropy
                        .map(|a| [a.principal.x, a.principal.y, a.principal.z]),
                    mu: l.anisotropy.map(|a| a.mu),
                })
                .collect(),
        };
        // Serialising plain numbers and strings cannot fail.
        serde_json::to_string_pretty(&out).unwrap_or_default()
    }

    /// Sets the `file` of every light (for writing a lights file beside rendered images).
    ///
    /// # Errors
    /// [`Error::LightsMismatch`] when the counts differ.
    pub fn with_files(mut self, files: &[String]) -> Result<Self> {
        if files.len() != self.lights.len() {
            return Err(Error::LightsMismatch {
                reason: format!(
                    "{} file names for {} lights",
                    files.len(),
                    self.lights.len()
                ),
            });
        }
        for (l, f) in self.lights.iter_mut().zip(files) {
            l.file = Some(f.clone());
        }
        Ok(self)
    }
}

/// Parses whitespace-separated numbers per line, skipping blanks and `#` comments; keeps the
/// 1-based line number of each row.
fn parse_number_rows(text: &str, source: &Path) -> Result<Vec<(usize, Vec<f64>)>> {
    let mut rows = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let values = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|t| !t.is_empty())
            .map(|t| {
                t.parse::<f64>().map_err(|_| Error::LightsFile {
                    path: source.to_path_buf(),
                    line: Some(i + 1),
                    reason: format!("`{t}` is not a number"),
                })
            })
            .collect::<Result<Vec<_>>>()?;
        rows.push((i + 1, values));
    }
    Ok(rows)
}

/// Drops a leading line that holds only the count of the following lines.
fn strip_count_line(mut rows: Vec<(usize, Vec<f64>)>) -> Vec<(usize, Vec<f64>)> {
    let is_count = rows.len() > 1
        && rows[0].1.len() == 1
        && rows[0].1[0] == (rows.len() - 1) as f64
        && rows[1].1.len() != 1;
    if is_count {
        rows.remove(0);
    }
    rows
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// Found by the `lights` fuzz target: a direction with a component near 1e200 once
    /// overflowed the norm and normalised to the zero vector. It must normalise exactly.
    #[test]
    fn huge_and_tiny_components_normalise() {
        let text = format!("0 4{} 66\n1e-9 0 1e-9\n0 1 1\n", "4".repeat(199));
        let lights = Lights::from_text_str(&text, Path::new("fuzz")).unwrap();
        let d = lights.directions();
        assert!(
            (d[0] - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12,
            "{:?}",
            d[0]
        );
        let s = std::f64::consts::FRAC_1_SQRT_2;
        assert!(
            (d[1] - Vector3::new(s, 0.0, s)).norm() < 1e-12,
            "{:?}",
            d[1]
        );
        for l in &d {
            assert!((l.norm() - 1.0).abs() < 1e-12);
        }
        assert!(Lights::from_json_str(&lights.to_json(), Path::new("fuzz")).is_ok());
    }

    #[test]
    fn json_with_files_intensities_and_normalisation() {
        let text = r#"{"lights": [
            {"file": "a.exr", "direction": [0, 0, 2]},
            {"file": "b.exr", "direction": [1, 0, 1], "intensity": 2.0},
            {"file": "c.exr", "direction": [0, 1, 1], "intensity": [1, 2, 3]}]}"#;
        let l = Lights::from_json_str(text, Path::new("l.json")).unwrap();
        assert_eq!(l.len(), 3);
        assert_relative_eq!(l.lights()[0].direction.z, 1.0);
        assert_relative_eq!(l.lights()[1].direction.x, 0.5f64.sqrt(), epsilon = 1e-12);
        assert_eq!(l.lights()[1].intensity, [2.0; 3]);
        assert_eq!(l.lights()[2].intensity, [1.0, 2.0, 3.0]);
        // Reordering by file name, with directories on the command line.
        let imgs: Vec<PathBuf> = ["x/c.exr", "x/a.exr", "x/b.exr"]
            .iter()
            .map(PathBuf::from)
            .collect();
        let m = l.matched_to(&imgs).unwrap();
        assert_eq!(m.lights()[0].file.as_deref(), Some("c.exr"));
        assert_eq!(m.lights()[2].file.as_deref(), Some("b.exr"));
        // Round trip through to_json.
        let back = Lights::from_json_str(&l.to_json(), Path::new("x")).unwrap();
        for (a, b) in back.lights().iter().zip(l.lights()) {
            assert!((a.direction - b.direction).norm() < 1e-15);
            assert_eq!((a.intensity, &a.file), (b.intensity, &b.file));
        }
    }

    #[test]
    fn near_lights_keep_their_positions() {
        let text = r#"{"lights": [
            {"direction": [0, 0, 1], "position": [10, 20, 300], "position_uncertainty": 0.5},
            {"direction": [1, 0, 1]}]}"#;
        let l = Lights::from_json_str(text, Path::new("l.json")).unwrap();
        assert_eq!(l.positioned(), 1);
        assert_eq!(
            l.lights()[0].position,
            Some(Vector3::new(10.0, 20.0, 300.0))
        );
        let back = Lights::from_json_str(&l.to_json(), Path::new("x")).unwrap();
        assert_eq!(back.lights()[0].position, l.lights()[0].position);
        assert_eq!(back.lights()[1].position, None);
        let bad = r#"{"lights": [{"direction": [0, 0, 1], "position": [1e400, 0, 0]}]}"#;
        assert!(Lights::from_json_str(bad, Path::new("l.json")).is_err());
    }

    /// An LED's angular profile is read, normalised, checked and written back; it needs a
    /// position, both keys, and a sensible exponent.
    #[test]
    fn led_profiles_round_trip() {
        let text = r#"{"lights": [
            {"direction": [0, 0, 1], "position": [0, 0, 50], "principal": [0, 0, -2], "mu": 1.5},
            {"direction": [0, 0.6, 0.8], "position": [0, 40, 50]}
        ]}"#;
        let l = Lights::from_json_str(text, Path::new("l.json")).unwrap();
        let a = l.lights()[0].anisotropy.unwrap();
        assert_eq!(a.principal, Vector3::new(0.0, 0.0, -1.0));
        assert_eq!(a.mu, 1.5);
        assert_eq!(l.lights()[1].anisotropy, None);
        let back = Lights::from_json_str(&l.to_json(), Path::new("back.json")).unwrap();
        assert_eq!(back, l);
        for (bad, says) in [
            (
                r#"{"lights": [{"direction": [0, 0, 1], "position": [0, 0, 5], "mu": 1}]}"#,
                "both",
            ),
            (
                r#"{"lights": [{"direction": [0, 0, 1], "principal": [0, 0, -1], "mu": 1}]}"#,
                "position",
            ),
            (
                r#"{"lights": [{"direction": [0, 0, 1], "position": [0, 0, 5], "principal": [0, 0, 0], "mu": 1}]}"#,
                "zero",
            ),
            (
                r#"{"lights": [{"direction": [0, 0, 1], "position": [0, 0, 5], "principal": [0, 0, -1], "mu": -1}]}"#,
                "mu",
            ),
        ] {
            let e = Lights::from_json_str(bad, Path::new("l.json")).unwrap_err();
            assert!(e.to_string().contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn text_with_count_line_and_comments() {
        let text = "3\n# a comment\n0 0 1\n1 0 1\n0 1 1\n";
        let l = Lights::from_text_str(text, Path::new("l.txt")).unwrap();
        assert_eq!(l.len(), 3);
        let no_count = Lights::from_text_str("0 0 1\n1 0 1\n0 1 1", Path::new("l.txt")).unwrap();
        assert_eq!(l, no_count);
    }

    #[test]
    fn errors_name_the_problem() {
        let e = Lights::from_text_str("0 0 1\n1 0\n", Path::new("l.txt")).unwrap_err();
        assert!(e.to_string().contains("line 2"), "{e}");
        let e = Lights::from_json_str(r#"{"lights":[{"direction":[0,0,0]}]}"#, Path::new("j"))
            .unwrap_err();
        assert!(
            e.to_string().contains("light 0") && e.to_string().contains("zero"),
            "{e}"
        );
        let e = Lights::from_json_str(
            r#"{"lights":[{"direction":[0,0,1],"intensity":-1}]}"#,
            Path::new("j"),
        )
        .unwrap_err();
        assert!(e.to_string().contains("intensity"), "{e}");
        let l = Lights::ring(3, 45.0, 0.0).unwrap();
        let e = l.matched_to(&[PathBuf::from("a.png")]).unwrap_err();
        assert!(e.to_string().contains("3 lights for 1 images"), "{e}");
    }

    #[test]
    fn conditioning_detects_coplanar_sets() {
        let ring = Lights::ring(8, 45.0, 0.0).unwrap();
        // Ring: LᵀL = diag(n/2 cos²e, n/2 cos²e, n sin²e) → condition √2 at 45°.
        assert_relative_eq!(ring.condition_number(), 2f64.sqrt(), epsilon = 1e-9);
        let flat = Lights::from_directions(&[
            Vector3::new(1.0, 0.0, 1.0),
            Vector3::new(-1.0, 0.0, 1.0),
            Vector3::new(0.0, 0.0, 1.0),
        ])
        .unwrap();
        assert!(flat.check_usable(MAX_LIGHT_CONDITION).is_err());
        assert!(ring.check_usable(MAX_LIGHT_CONDITION).is_ok());
    }

    #[test]
    fn generated_sets_have_their_geometry() {
        let axis = Vector3::new(0.3, -0.2, 1.0).normalize();
        let cone = Lights::random_cone(200, axis, 20.0, 5).unwrap();
        let angles: Vec<f64> = cone
            .directions()
            .iter()
            .map(|d| d.dot(&axis).acos().to_degrees())
            .collect();
        assert!(angles.iter().all(|a| *a <= 20.0 + 1e-9));
        assert!(angles.iter().any(|a| *a > 15.0), "cone not filled");
        assert_eq!(cone, Lights::random_cone(200, axis, 20.0, 5).unwrap());
        let grid = Lights::diligent_grid();
        assert_eq!(grid.len(), 96);
        let min_elev = grid
            .directions()
            .iter()
            .map(|d| d.z.asin().to_degrees())
            .fold(90.0, f64::min);
        assert!((min_elev - 47.1).abs() < 1.0, "{min_elev}");
        // Exactly coplanar: rank 2, infinite condition; tilted: finite but large.
        assert!(Lights::coplanar(8, 0.0).unwrap().condition_number() > 1e8);
        let c = Lights::coplanar(8, 2.0).unwrap().condition_number();
        assert!(c > 10.0 && c < 1e3, "{c}");
        let cl = Lights::clustered(10, 60.0, 5.0, 1).unwrap();
        assert!(cl.condition_number() > 10.0);
    }

    #[test]
    fn fibonacci_respects_elevation() {
        let l = Lights::fibonacci(50, 30.0).unwrap();
        assert_eq!(l.len(), 50);
        for d in l.directions() {
            assert!(d.z >= 30f64.to_radians().sin() - 1e-12);
            assert_relative_eq!(d.norm(), 1.0, epsilon = 1e-12);
        }
    }
}
