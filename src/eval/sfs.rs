//! Shape from shading, every method on the same rendered shapes: error against time
//! (`photostereo bench sfs`, the README's table).
//!
//! Each shape is rendered twice per light: once for the distant-light methods (orthographic,
//! a distant light at `slant` from the view and `azimuth`, 40° by default) and once for the
//! perspective method
//! (a pinhole camera two scene widths away, a point light in the camera's plane seen from the
//! scene's centre at the same `slant`; slant 0 is a light at the camera centre). Lambertian,
//! albedo 0.8, cast shadows, no noise. Errors: mean normal angle over the mask, depth RMSE
//! after removing the mean offset as a fraction of the true depth range; the perspective
//! method's absolute depth RMSE too.

use crate::capture::lights::{Light, Lights};
use crate::error::{Error, Result};
use crate::eval::metrics::{angular_errors, depth_errors};
use crate::nalgebra::Vector3;
use crate::sfs::perspective::{PerspectiveOptions, PointLight, RefineOptions};
use crate::sfs::reflectance_map::ReflectanceMap;
use crate::sfs::{SfsMethod, SfsOptions, SfsResult, shape_from_shading};
use crate::synth::near::{NearPlacement, render_near};
use crate::synth::reflectance::Material;
use crate::synth::render::{RenderOptions, render};
use crate::synth::scene::{Albedo, HeightField, SceneKind};
use serde::Serialize;

/// Shapes swept: the sphere as the control, then the four non-spherical shapes.
pub const SFS_SCENES: [SceneKind; 5] = [
    SceneKind::Sphere,
    SceneKind::Vase,
    SceneKind::Peaks,
    SceneKind::Relief,
    SceneKind::Bust,
];
/// Light slants (degrees from the view) swept by default: frontal and oblique.
pub const DEFAULT_SLANTS: [f64; 2] = [0.0, 30.0];
/// Albedo of the rendered shapes.
const ALBEDO: f64 = 0.8;
/// Azimuth of the oblique lights swept by default (degrees, x right, y up).
pub const DEFAULT_AZIMUTHS: [f64; 1] = [40.0];
/// Azimuths closer than this (degrees, after taking them modulo 360°) are one light.
const AZIMUTH_SAME: f64 = 1e-9;

/// What to sweep.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SfsSweepOptions {
    /// Image size (square).
    pub size: usize,
    /// Light slants, degrees.
    pub slants: Vec<f64>,
    /// Azimuths of the oblique lights, degrees (x right, y up), taken modulo 360° and each
    /// once (the rows and the report's options carry them in [0°, 360°)); a frontal light is
    /// run once.
    pub azimuths: Vec<f64>,
    /// Methods.
    pub methods: Vec<SfsMethod>,
}

impl Default for SfsSweepOptions {
    fn default() -> Self {
        SfsSweepOptions {
            size: 128,
            slants: DEFAULT_SLANTS.to_vec(),
            azimuths: DEFAULT_AZIMUTHS.to_vec(),
            methods: vec![
                SfsMethod::Horn,
                SfsMethod::TsaiShah,
                SfsMethod::FastMarching,
                SfsMethod::Perspective,
            ],
        }
    }
}

/// One shape, light and method.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SfsRow {
    /// Scene name.
    pub scene: &'static str,
    /// Light slant, degrees.
    pub slant_deg: f64,
    /// Light azimuth, degrees (x right, y up; 0 for a frontal light).
    pub azimuth_deg: f64,
    /// Method.
    pub method: SfsMethod,
    /// Why the method does not apply at this light, when it does not.
    pub refused: Option<String>,
    /// Mean normal error over the mask, degrees.
    pub normals_deg: Option<f64>,
    /// Depth RMSE after removing the mean offset, over the true depth range.
    pub depth: Option<f64>,
    /// Depth RMSE before removing the mean offset (absolute depth: perspective only).
    pub depth_absolute: Option<f64>,
    /// Iterations (sweeps for the perspective method).
    pub iterations: usize,
    /// Whether the method met its tolerance (and, refined, the refinement too).
    pub converged: bool,
    /// Perspective: whether the swept solution was refined (and in how many steps at full
    /// resolution); `None` for the other methods.
    pub refined: Option<usize>,
    /// The steps taken at lower resolutions to make the start: the refinement's (perspective,
    /// refined) or the method's own iterations (Horn's coarse to fine); 0 otherwise.
    pub refined_coarse: usize,
    /// Solve time, seconds.
    pub seconds: f64,
    /// What the method said was wrong with its result (the report's warnings): a wrong result
    /// without one is a confident wrong answer.
    pub warnings: Vec<String>,
    /// Perspective, refined: whether the refinement was discarded (it moved the whole
    /// surface), so that the result is its start.
    pub discarded: bool,
}

impl SfsRow {
    /// The method's name, with "swept only" for the perspective method's unrefined solution.
    pub fn label(&self) -> String {
        match (self.method, self.refined) {
            (SfsMethod::Perspective, None) => "perspective, swept only".to_string(),
            (m, _) => m.name().to_string(),
        }
    }
}

/// The sweep's rows.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SfsSweepReport {
    /// What was swept.
    pub options: SfsSweepOptions,
    /// One row per shape, light and method.
    pub rows: Vec<SfsRow>,
}

/// A distant light at `slant_deg` from the view and `azimuth_deg`.
fn distant(slant_deg: f64, azimuth_deg: f64) -> Vector3<f64> {
    crate::synth::light_sets::slanted(slant_deg, azimuth_deg)
}

fn scores(r: &SfsResult, truth: &HeightField) -> Result<(f64, f64)> {
    Ok((
        angular_errors(&r.normals, &truth.normals, &truth.mask)?.mean_deg,
        depth_errors(&r.depth, &truth.depth, &truth.mask)?.rmse_over_range,
    ))
}

/// Runs the sweep.
///
/// # Errors
/// [`Error::InvalidParameter`] for a size under 16, a slant outside [0, 60], an azimuth that
/// is not finite, or an oblique slant with no azimuth; the renderer's errors.
pub fn sweep(options: &SfsSweepOptions) -> Result<SfsSweepReport> {
    if options.size < 16 {
        return Err(Error::param(
            "size",
            format!("{} is under 16", options.size),
        ));
    }
    if let Some(s) = options.slants.iter().find(|s| !(0.0..=60.0).contains(*s)) {
        return Err(Error::param("slant", format!("{s}° is outside [0°, 60°]")));
    }
    if let Some(a) = options.azimuths.iter().find(|a| !a.is_finite()) {
        return Err(Error::param(
            "azimuth",
            format!("{a}° is not a finite angle"),
        ));
    }
    if options.azimuths.is_empty() && options.slants.iter().any(|&s| s > 0.0) {
        return Err(Error::param("azimuth", "none given for the oblique slants"));
    }
    // Azimuths in [0°, 360°), each once (400° and 40° are one light; −0° and a rounding just
    // under 360° are 0°).
    let mut azimuths: Vec<f64> = Vec::with_capacity(options.azimuths.len());
    for a in options.azimuths.iter().map(|a| a.rem_euclid(360.0)) {
        let a = if a == 0.0 || a >= 360.0 - AZIMUTH_SAME {
            0.0
        } else {
            a
        };
        if !azimuths.iter().any(|b| (a - b).abs() < AZIMUTH_SAME) {
            azimuths.push(a);
        }
    }
    // A frontal light has no azimuth: it is run once.
    let lights: Vec<(f64, f64)> = options
        .slants
        .iter()
        .flat_map(|&slant| {
            if slant == 0.0 {
                vec![(slant, 0.0)]
            } else {
                azimuths.iter().map(|&a| (slant, a)).collect()
            }
        })
        .collect();
    let mut rows = Vec::new();
    for kind in SFS_SCENES {
        let scene = kind.build(
            options.size,
            Albedo::Constant(ALBEDO as f32),
            Material::lambertian(),
        );
        for &(slant, azimuth) in &lights {
            let l = distant(slant, azimuth);
            let ortho = render(
                &scene,
                &Lights::new(vec![Light::new(l)])?,
                &RenderOptions::default(),
            )?;
            let placement = NearPlacement {
                distance: 2.0 * options.size as f64,
                scale: 1.0,
            };
            let camera = placement.camera(&scene);
            let d = placement.distance;
            let az = azimuth.to_radians();
            let at = Vector3::new(az.cos(), az.sin(), 0.0) * (d * slant.to_radians().tan());
            let mut point = Light::near(at, Vector3::new(0.0, 0.0, -d));
            point.intensity = [d * d; 3];
            let near = render_near(
                &scene,
                &Lights::new(vec![point])?,
                &camera,
                &placement,
                &RenderOptions::default(),
            )?;
            let runs: Vec<(SfsMethod, bool)> = options
                .methods
                .iter()
                .flat_map(|&m| {
                    if m == SfsMethod::Perspective {
                        vec![(m, false), (m, true)]
                    } else {
                        vec![(m, false)]
                    }
                })
                .collect();
            for (method, refine) in runs {
                let row = |refused: Option<String>| SfsRow {
                    scene: kind.name(),
                    slant_deg: slant,
                    azimuth_deg: azimuth,
                    method,
                    refused,
                    normals_deg: None,
                    depth: None,
                    depth_absolute: None,
                    iterations: 0,
                    converged: false,
                    refined: None,
                    refined_coarse: 0,
                    seconds: 0.0,
                    warnings: Vec::new(),
                    discarded: false,
                };
                let (result, truth) = if method == SfsMethod::Perspective {
                    let r = crate::sfs::perspective::solve(
                        &near.images[0][0],
                        &near.truth.mask,
                        &camera,
                        &PointLight {
                            position: at,
                            intensity: d * d,
                        },
                        &PerspectiveOptions {
                            albedo: ALBEDO,
                            refine: refine.then(RefineOptions::default),
                            ..PerspectiveOptions::default()
                        },
                    )?;
                    (r, &near.truth)
                } else {
                    let rmap = ReflectanceMap::lambertian(l)?;
                    if let Err(why) = method.applicable(&rmap) {
                        rows.push(row(Some(why)));
                        continue;
                    }
                    let r = shape_from_shading(
                        &ortho.images[0][0],
                        &ortho.truth.mask,
                        &rmap,
                        ALBEDO,
                        &SfsOptions {
                            method,
                            ..SfsOptions::default()
                        },
                    )?;
                    (r, &ortho.truth)
                };
                let (normals, depth) = scores(&result, truth)?;
                let depth_absolute = (method == SfsMethod::Perspective)
                    .then(|| absolute_rmse(&result, truth))
                    .flatten();
                rows.push(SfsRow {
                    normals_deg: Some(normals),
                    depth: Some(depth),
                    depth_absolute,
                    iterations: result.report.iterations,
                    converged: result.report.converged
                        && result
                            .report
                            .refinement
                            .as_ref()
                            .is_none_or(|r| r.converged),
                    discarded: result
                        .report
                        .refinement
                        .as_ref()
                        .is_some_and(|r| r.discarded),
                    refined: result.report.refinement.as_ref().map(|r| r.iterations),
                    refined_coarse: result
                        .report
                        .refinement
                        .as_ref()
                        .map_or(result.report.coarse_iterations, |r| r.coarse_iterations),
                    seconds: result.report.seconds,
                    warnings: result.report.warnings.clone(),
                    ..row(None)
                });
            }
        }
    }
    Ok(SfsSweepReport {
        options: SfsSweepOptions {
            azimuths,
            ..options.clone()
        },
        rows,
    })
}

/// Depth RMSE without alignment, over the true range.
fn absolute_rmse(r: &SfsResult, truth: &HeightField) -> Option<f64> {
    let (mut se, mut n, mut lo, mut hi) = (0.0, 0.0, f64::INFINITY, f64::NEG_INFINITY);
    for i in 0..truth.mask.len() {
        let (e, t) = (
            f64::from(r.depth.data()[i]),
            f64::from(truth.depth.data()[i]),
        );
        if truth.mask.data()[i] && e.is_finite() && t.is_finite() {
            se += (e - t).powi(2);
            n += 1.0;
            lo = lo.min(t);
            hi = hi.max(t);
        }
    }
    (n > 0.0 && hi > lo).then(|| (se / n).sqrt() / (hi - lo))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small sweep runs every method (the perspective one swept only and refined), refuses
    /// the inapplicable ones, and the perspective method at the camera centre is the best on
    /// the bust.
    #[test]
    fn small_sweep() {
        let report = sweep(&SfsSweepOptions {
            size: 48,
            slants: vec![0.0, 30.0],
            azimuths: DEFAULT_AZIMUTHS.to_vec(),
            methods: vec![
                SfsMethod::TsaiShah,
                SfsMethod::FastMarching,
                SfsMethod::Perspective,
            ],
        })
        .unwrap();
        assert_eq!(report.rows.len(), SFS_SCENES.len() * 2 * 4);
        assert_eq!(
            report.rows.iter().filter(|r| r.refined.is_some()).count(),
            SFS_SCENES.len() * 2
        );
        // Tsai–Shah refuses the frontal light, fast marching the oblique one.
        for r in &report.rows {
            let refused = r.refused.is_some();
            match r.method {
                SfsMethod::TsaiShah => assert_eq!(refused, r.slant_deg == 0.0),
                SfsMethod::FastMarching => assert_eq!(refused, r.slant_deg > 0.0),
                _ => assert!(!refused),
            }
        }
        let bust = |m: SfsMethod| {
            report
                .rows
                .iter()
                .find(|r| {
                    r.scene == "bust"
                        && r.slant_deg == 0.0
                        && r.method == m
                        && (m != SfsMethod::Perspective || r.refined.is_some())
                })
                .and_then(|r| r.normals_deg)
                .unwrap()
        };
        assert!(
            bust(SfsMethod::Perspective) < bust(SfsMethod::FastMarching),
            "{} {}",
            bust(SfsMethod::Perspective),
            bust(SfsMethod::FastMarching)
        );
    }

    /// Each oblique slant is run at every azimuth, the frontal light once; the light moves with
    /// the azimuth (the results differ), and the method's warnings are carried into the rows.
    #[test]
    fn oblique_lights_are_swept_over_the_azimuths() {
        // 400° is 40°, and −140° is 220°: each is run once, named in [0°, 360°).
        let report = sweep(&SfsSweepOptions {
            size: 32,
            slants: vec![0.0, 30.0],
            azimuths: vec![40.0, -140.0, 400.0],
            methods: vec![SfsMethod::TsaiShah],
        })
        .unwrap();
        assert_eq!(report.rows.len(), SFS_SCENES.len() * 3);
        for scene in SFS_SCENES {
            let rows: Vec<&SfsRow> = report
                .rows
                .iter()
                .filter(|r| r.scene == scene.name())
                .collect();
            let lights: Vec<(f64, f64)> =
                rows.iter().map(|r| (r.slant_deg, r.azimuth_deg)).collect();
            assert_eq!(lights, [(0.0, 0.0), (30.0, 40.0), (30.0, 220.0)]);
            assert_eq!(report.options.azimuths, [40.0, 220.0]);
            assert!(rows[0].refused.is_some());
            let (a, b) = (rows[1].normals_deg.unwrap(), rows[2].normals_deg.unwrap());
            assert!(a.is_finite() && b.is_finite() && a != b, "{}", scene.name());
        }
        assert!(
            report
                .rows
                .iter()
                .filter(|r| r.refused.is_none())
                .any(|r| !r.warnings.is_empty())
        );
        // Only frontal: no azimuth is needed.
        let frontal = sweep(&SfsSweepOptions {
            size: 32,
            slants: vec![0.0],
            azimuths: vec![],
            methods: vec![SfsMethod::FastMarching],
        })
        .unwrap();
        assert_eq!(frontal.rows.len(), SFS_SCENES.len());
        for azimuths in [vec![], vec![f64::NAN]] {
            let err = sweep(&SfsSweepOptions {
                size: 32,
                azimuths,
                ..SfsSweepOptions::default()
            })
            .unwrap_err();
            assert!(err.to_string().contains("azimuth"), "{err}");
        }
    }
}
