//! Near lights from two mirror balls: each light's position, where the rays it reflects off the
//! two balls meet.
//!
//! Under a pinhole camera a ball of known radius R is placed in 3-D by its outline (its centre
//! at R / sin α along the cone's axis, [`SphereCone::centre`]); the highlight's centroid lies on
//! the ball at P_k, and the light is somewhere along the reflected ray P_k + t l_k. A near light
//! sends different directions to two balls apart, and the point X nearest both rays is its
//! position. The rays are weighted by their lateral uncertainty at the distance of the light,
//! s_k² = (σ_k t_k)² + σ_P,k², with σ_k the direction's per-axis standard error (its rms
//! uncertainty over √2) and σ_P,k how far the ball's own position may be off across the ray (its
//! distance D times the axis' tilt errors, and D's error D δα / tan α along the axis, projected
//! across the ray); X minimises Σ_k |(I − l_k l_kᵀ)(X − P_k)|² / s_k², solved twice so that t_k
//! is the distance to X, and its covariance is (Σ_k (I − l_k l_kᵀ) / s_k²)⁻¹ (the midpoint method
//! of triangulation, weighted; Hartley and Sturm, "Triangulation", CVIU 1997, for its
//! alternatives). How far the rays pass from each other, against what their uncertainties
//! allow, checks the pair: a ray from a secondary reflection, or balls whose radii differ,
//! makes them miss.
//!
//! Depth along the rays is fixed by the angle between them: the light's distance error grows as
//! (distance)² / baseline, so the balls should be as far apart as the frame allows.

use super::perspective::SphereCone;
use super::{
    ChromeCalibration, ChromeOptions, HighlightResult, SphereSource, calibrate_ball, find_balls_in,
    grey_images,
};
use crate::capture::lights::{Light, Lights};
use crate::capture::stack::ImageStack;
use crate::error::{Error, Result};
use crate::grid::ScalarMap;
use nalgebra::{Matrix3, Vector3};
use serde::Serialize;
use std::path::Path;

/// Options of [`calibrate_two_balls`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NearOptions {
    /// How each ball is calibrated; its camera is required.
    pub chrome: ChromeOptions,
    /// The balls' radius (both alike), in the unit of length the positions are given in.
    pub ball_radius: f64,
    /// A position whose rms uncertainty exceeds this fraction of its distance from the balls'
    /// midpoint is in doubt. Default 0.5%: twice the rms uncertainty, which holds about 95%
    /// of the errors, is then within 1% of the distance.
    pub max_relative_uncertainty: f64,
    /// A pair of rays passing farther apart than this many standard deviations of what their
    /// uncertainties allow is inconsistent, and its position in doubt.
    pub max_miss_sigmas: f64,
}

impl NearOptions {
    /// Options with the defaults for a camera and a ball radius.
    pub fn new(camera: crate::camera::Intrinsics, ball_radius: f64) -> Self {
        NearOptions {
            chrome: ChromeOptions {
                camera: Some(camera),
                ..ChromeOptions::default()
            },
            ball_radius,
            max_relative_uncertainty: 0.005,
            max_miss_sigmas: 4.0,
        }
    }
}

/// A light's position triangulated from its highlights on two balls.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LightPosition {
    /// Position (camera frame, the unit of the balls' radius).
    #[serde(serialize_with = "super::serialize_vector")]
    pub position: Vector3<f64>,
    /// Root-mean-square uncertainty of the position, same unit: √ of the covariance's trace, or
    /// half the re-triangulated bound at twice each error's standard deviation where that is
    /// larger (rays meeting at a small angle, where the distance's error is not linear in the
    /// directions').
    pub uncertainty: f64,
    /// Standard deviation along the principal axes of the covariance, largest first.
    pub principal_std: [f64; 3],
    /// Distance from the midpoint of the balls' centres.
    pub distance: f64,
    /// Unit direction from that midpoint to the light.
    #[serde(serialize_with = "super::serialize_vector")]
    pub direction: Vector3<f64>,
    /// Closest distance between the two reflected rays.
    pub miss: f64,
    /// [`LightPosition::miss`] over its standard deviation.
    pub miss_sigmas: f64,
    /// Whether the position can be used; when false, the warnings say why.
    pub accepted: bool,
    /// What may be wrong with it.
    pub warnings: Vec<String>,
}

/// The result of a two-ball calibration.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TwoBallCalibration {
    /// Each ball's calibration: its outline, cone and highlights (left ball first).
    pub balls: Vec<ChromeCalibration>,
    /// Each ball's centre (camera frame, unit of the radius).
    pub centres: Vec<[f64; 3]>,
    /// Per image, the light's position, or why there is none (written as `{"found": …}` or
    /// `{"missing": {"reason": …}}`, as the highlights are).
    #[serde(serialize_with = "serialize_positions")]
    pub positions: Vec<std::result::Result<LightPosition, String>>,
    /// Warnings about the calibration as a whole.
    pub warnings: Vec<String>,
}

/// Writes positions as found / missing entries (see [`TwoBallCalibration::positions`]).
fn serialize_positions<S: serde::Serializer>(
    positions: &[std::result::Result<LightPosition, String>],
    s: S,
) -> std::result::Result<S::Ok, S::Error> {
    #[derive(Serialize)]
    #[serde(rename_all = "snake_case")]
    enum Entry<'a> {
        Found(&'a LightPosition),
        Missing { reason: &'a str },
    }
    s.collect_seq(positions.iter().map(|p| match p {
        Ok(p) => Entry::Found(p),
        Err(reason) => Entry::Missing { reason },
    }))
}

impl TwoBallCalibration {
    /// The lights, one per image, with positions (and directions from the balls' midpoint),
    /// when every position is accepted.
    ///
    /// # Errors
    /// [`Error::BadImage`] naming the first image without a position or with one in doubt
    /// (the message lists them all, with why).
    pub fn lights(&self) -> Result<Lights> {
        self.collect(true)
    }

    /// As [`TwoBallCalibration::lights`], keeping positions in doubt.
    ///
    /// # Errors
    /// [`Error::BadImage`] naming the first image without a position.
    pub fn all_lights(&self) -> Result<Lights> {
        self.collect(false)
    }

    fn collect(&self, accepted_only: bool) -> Result<Lights> {
        let images: Vec<&Path> = self
            .balls
            .first()
            .map(|b| b.lights.iter().map(|o| o.image.as_path()).collect())
            .unwrap_or_default();
        let bad: Vec<(usize, String)> = self
            .positions
            .iter()
            .enumerate()
            .filter_map(|(k, p)| match p {
                Err(why) => Some((k, why.clone())),
                Ok(p) if accepted_only && !p.accepted => Some((k, p.warnings.join("; "))),
                Ok(_) => None,
            })
            .collect();
        if let Some((first, _)) = bad.first() {
            let all: Vec<String> = bad.iter().map(|(k, w)| format!("image {k}: {w}")).collect();
            return Err(Error::BadImage {
                path: images
                    .get(*first)
                    .map(|p| p.to_path_buf())
                    .unwrap_or_default(),
                index: *first,
                reason: format!(
                    "{} of {} light positions are missing or in doubt ({})",
                    bad.len(),
                    self.positions.len(),
                    all.join(" | ")
                ),
            });
        }
        let lights = self
            .positions
            .iter()
            .filter_map(|p| p.as_ref().ok())
            .map(|p| Light {
                direction: p.direction,
                intensity: [1.0; 3],
                file: None,
                position: Some(p.position),
                anisotropy: None,
            })
            .collect();
        Lights::new(lights)
    }
}

/// The lights file `photostereo calibrate` writes for near lights: the JSON lights format
/// (see [`crate::capture::lights`]) with each light's `position`, its `position_uncertainty`
/// (rms, the unit of the balls' radius) and `accepted`, its `direction` from the balls'
/// midpoint, and a `calibration` section holding the camera, the radius, both balls'
/// calibrations and every position. [`Lights::from_file`] reads it back.
pub fn near_lights_file_json(
    lights: &Lights,
    calibration: &TwoBallCalibration,
    ball_radius: f64,
    intensity: Option<&super::IntensityCalibration>,
) -> String {
    let entries: Vec<serde_json::Value> = lights
        .lights()
        .iter()
        .zip(&calibration.positions)
        .map(|(l, p)| {
            let mut v = serde_json::json!({
                "direction": [l.direction.x, l.direction.y, l.direction.z],
                "intensity": l.intensity,
            });
            if let Some(x) = l.position {
                v["position"] = serde_json::json!([x.x, x.y, x.z]);
            }
            if let Ok(p) = p {
                v["position_uncertainty"] = serde_json::json!(p.uncertainty);
                v["accepted"] = serde_json::json!(p.accepted);
            }
            v
        })
        .collect();
    let camera = calibration
        .balls
        .first()
        .and_then(|b| b.cone)
        .map(|k| k.camera);
    let doc = serde_json::json!({
        "lights": entries,
        "calibration": {
            "camera": {
                "model": "pinhole; each ball placed by its outline's cone of rays, each light where the rays it reflects off the two balls meet",
                "intrinsics": camera,
            },
            "ball_radius": ball_radius,
            "length_unit": "the unit of ball_radius; positions in the camera frame (x right, y up, z towards the camera, the camera at the origin)",
            "two_balls": calibration,
            "intensity": intensity,
        },
    });
    // Serialising numbers, strings and derived structs cannot fail.
    serde_json::to_string_pretty(&doc).unwrap_or_default()
}

/// Calibrates near lights from two mirror balls of radius `options.ball_radius` seen by the
/// camera `options.chrome.camera`: each ball is calibrated as [`super::calibrate_chrome`]
/// does (from `mask`, one part per ball, or detected), and each image's two highlights give
/// the light's position (module doc). Of more than two balls, the two largest are used.
///
/// # Errors
/// [`Error::InvalidParameter`] without a camera or with a radius that is not positive;
/// [`Error::SphereNotFound`] (or [`Error::Mask`]) when fewer than two balls are found; as
/// [`super::calibrate_chrome`] otherwise.
pub fn calibrate_two_balls(
    stack: &ImageStack,
    mask: Option<(&ScalarMap, &Path)>,
    options: &NearOptions,
) -> Result<TwoBallCalibration> {
    let Some(camera) = options.chrome.camera else {
        return Err(Error::param(
            "camera",
            "light positions need the camera's intrinsics: under an orthographic camera the balls' depths are unknown",
        ));
    };
    if !(options.ball_radius > 0.0 && options.ball_radius.is_finite()) {
        return Err(Error::param(
            "ball_radius",
            format!("{}: must be a positive length", options.ball_radius),
        ));
    }
    if stack.count() == 0 {
        return Err(Error::TooFewImages { count: 0 });
    }
    let grey = grey_images(stack);
    let (balls, source) = find_balls_in(
        &grey,
        stack.width(),
        stack.height(),
        mask,
        Some(&camera),
        true,
    )?;
    if balls.len() < 2 {
        let c = balls[0].fit.circle;
        let reason = format!(
            "one sphere (centre ({:.1}, {:.1}), radius {:.1} px) where light positions need two",
            c.cx, c.cy, c.radius
        );
        return Err(match (source, mask) {
            (SphereSource::Mask, Some((_, path))) => Error::Mask {
                path: path.to_path_buf(),
                reason: format!("{reason}: the mask must outline both balls"),
            },
            _ => Error::SphereNotFound { reason },
        });
    }
    let mut warnings = Vec::new();
    for o in &balls[2..] {
        let c = o.fit.circle;
        warnings.push(format!(
            "a third sphere is in the images, centre ({:.1}, {:.1}) radius {:.1} px: the two largest are used",
            c.cx, c.cy, c.radius
        ));
    }
    let mut pair: Vec<&super::Ball> = balls[..2].iter().collect();
    pair.sort_by(|a, b| a.fit.circle.cx.total_cmp(&b.fit.circle.cx));
    let cals: Vec<ChromeCalibration> = pair
        .iter()
        .map(|b| calibrate_ball(stack, &grey, b, source, &options.chrome))
        .collect();
    let r = options.ball_radius;
    let cones: Vec<SphereCone> = cals.iter().filter_map(|c| c.cone).collect();
    if cones.len() < 2 {
        return Err(Error::param("camera", "the balls were not placed in 3-D"));
    }
    let centres: Vec<Vector3<f64>> = cones.iter().map(|k| k.centre(r)).collect();
    let mid = 0.5 * (centres[0] + centres[1]);
    let positions = (0..stack.count())
        .map(|k| {
            let mut rays = Vec::new();
            for (cal, cone) in cals.iter().zip(&cones) {
                match &cal.lights[k].result {
                    HighlightResult::Found(h) => rays.push(Ray::of(h, cone, r)?),
                    HighlightResult::Missing(m) => return Err(m.reason.clone()),
                }
            }
            let accepted = cals.iter().all(|c| match &c.lights[k].result {
                HighlightResult::Found(h) => h.accepted,
                HighlightResult::Missing(_) => false,
            });
            let mut p = triangulate(&rays, &mid).map_err(Triangulation::reason)?;
            if !accepted {
                p.warnings
                    .push("a highlight it comes from is in doubt".to_string());
            }
            if p.miss_sigmas > options.max_miss_sigmas {
                p.warnings.push(format!(
                    "the two reflected rays pass {:.3} apart, {:.1} times what their uncertainties allow: a highlight is wrong, or the balls' radii differ",
                    p.miss, p.miss_sigmas
                ));
            }
            if p.uncertainty.is_nan() || p.uncertainty > options.max_relative_uncertainty * p.distance {
                p.warnings.push(format!(
                    "the position is uncertain: ±{:.3} (rms) at a distance of {:.3}, more than the {:.1}% accepted (the balls are too close together, or too small, for a light this far)",
                    p.uncertainty,
                    p.distance,
                    options.max_relative_uncertainty * 100.0
                ));
            }
            p.accepted = p.warnings.is_empty();
            Ok(p)
        })
        .collect();
    Ok(TwoBallCalibration {
        balls: cals,
        centres: centres.iter().map(|c| [c.x, c.y, c.z]).collect(),
        positions,
        warnings,
    })
}

/// A reflected ray with its lateral uncertainty.
#[derive(Debug, Clone, Copy)]
struct Ray {
    origin: Vector3<f64>,
    direction: Vector3<f64>,
    /// Per-axis standard error of the direction (radians).
    sigma: f64,
    /// Covariance of the origin (the ball's position), camera frame.
    origin_cov: Matrix3<f64>,
}

impl Ray {
    /// The ray of highlight `h` on the ball of `cone`, radius `radius`.
    fn of(
        h: &super::Highlight,
        cone: &SphereCone,
        radius: f64,
    ) -> std::result::Result<Ray, String> {
        let (p, _) = cone
            .surface(h.centroid[0], h.centroid[1])
            .ok_or_else(|| "the highlight's centroid is off the ball".to_string())?;
        let d = radius / cone.half_angle.sin();
        let (e1, e2) = cone.tangents();
        // The whole ball moves with its axis' tilts (across) and its distance (along).
        let along = d * cone.std_err[2] / cone.half_angle.tan();
        let across = [d * cone.std_err[0], d * cone.std_err[1]];
        let origin_cov = e1 * e1.transpose() * across[0].powi(2)
            + e2 * e2.transpose() * across[1].powi(2)
            + cone.axis * cone.axis.transpose() * along.powi(2);
        Ok(Ray {
            origin: p * radius,
            direction: h.direction.normalize(),
            sigma: h.uncertainty_deg.to_radians() / std::f64::consts::SQRT_2,
            origin_cov,
        })
    }

    /// The lateral variance of the ray `t` along it, in the plane across it (as a scalar: the
    /// mean of its two principal values).
    fn lateral_variance(&self, t: f64) -> f64 {
        let across = Matrix3::identity() - self.direction * self.direction.transpose();
        let origin = (across * self.origin_cov * across).trace() / 2.0;
        (self.sigma * t).powi(2) + origin
    }
}

/// Why two rays give no position.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Triangulation {
    Parallel,
    Diverging,
    Uncertain,
}

impl Triangulation {
    fn reason(self) -> String {
        match self {
            Triangulation::Parallel => "the two reflected rays are parallel".into(),
            Triangulation::Diverging => {
                "the two reflected rays diverge (they meet behind the balls): the light is too far for the balls' separation, or a highlight is wrong".into()
            }
            Triangulation::Uncertain => {
                "a highlight's direction has no finite uncertainty".into()
            }
        }
    }
}

/// The weighted point nearest `rays` and its covariance (module doc), or `None` when the rays
/// do not fix it.
fn nearest(rays: &[Ray], weights: &[f64]) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for (r, w) in rays.iter().zip(weights) {
        let m = (Matrix3::identity() - r.direction * r.direction.transpose()) * *w;
        a += m;
        b += m * r.origin;
    }
    let inv = a.try_inverse()?;
    let x = inv * b;
    x.iter().all(|v| v.is_finite()).then_some((x, inv))
}

/// How far the position `x` moves when each error source is set to twice its standard
/// deviation, one at a time and either way, the light re-triangulated each time (with the same
/// `weights`) rather than the move linearised: the larger move of each source, combined in
/// quadrature. For errors that act linearly this is twice the rms uncertainty; where the rays
/// meet at a small angle, the distance along them grows faster than linearly with the angle's
/// error (as one over the angle), and the bound says so. The sources are each ray's direction
/// (two axes across it) and its ball's position (the principal axes of its covariance).
fn two_sigma_bound(rays: &[Ray], weights: &[f64], x: &Vector3<f64>) -> f64 {
    let mut sum = 0.0;
    for (k, r) in rays.iter().enumerate() {
        let d = r.direction;
        let helper = if d.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let e1 = d.cross(&helper).normalize();
        let e2 = d.cross(&e1);
        let eig = r.origin_cov.symmetric_eigen();
        // (true: the direction, false: the origin; the move at twice the standard deviation)
        let mut moves = vec![(true, 2.0 * r.sigma * e1), (true, 2.0 * r.sigma * e2)];
        for (value, axis) in eig.eigenvalues.iter().zip(eig.eigenvectors.column_iter()) {
            moves.push((false, 2.0 * value.max(0.0).sqrt() * axis.into_owned()));
        }
        for (direction, step) in moves {
            let mut worst: f64 = 0.0;
            for s in [1.0, -1.0] {
                let mut moved = rays.to_vec();
                if direction {
                    moved[k].direction = (d + s * step).normalize();
                } else {
                    moved[k].origin = r.origin + s * step;
                }
                let y = nearest(&moved, weights).map_or(f64::INFINITY, |(y, _)| (y - x).norm());
                worst = worst.max(y);
            }
            sum += worst * worst;
        }
    }
    sum.sqrt()
}

/// The weighted point nearest the rays (module doc), with distances and directions measured
/// from `reference`.
fn triangulate(
    rays: &[Ray],
    reference: &Vector3<f64>,
) -> std::result::Result<LightPosition, Triangulation> {
    let solve = |weights: &[f64]| nearest(rays, weights);
    // First with unit lateral errors, then with those at the distance found.
    let (mut x, _) = solve(&vec![1.0; rays.len()]).ok_or(Triangulation::Parallel)?;
    let mut cov = Matrix3::zeros();
    let mut w = Vec::with_capacity(rays.len());
    for _ in 0..3 {
        w.clear();
        for r in rays {
            let t = r.direction.dot(&(x - r.origin));
            // The point nearest the rays must lie ahead of both balls: diverging rays (a
            // light too far for the baseline, or noise) meet behind them.
            if t.is_nan() || t <= 0.0 {
                return Err(Triangulation::Diverging);
            }
            let v = r.lateral_variance(t);
            if !(v.is_finite() && v > 0.0) {
                return Err(Triangulation::Uncertain);
            }
            w.push(1.0 / v);
        }
        (x, cov) = solve(&w).ok_or(Triangulation::Parallel)?;
    }
    // The rays' closest approach, against its standard deviation.
    let (miss, miss_sd) = match rays {
        [a, b] => {
            let n = a.direction.cross(&b.direction);
            let nn = n.norm();
            if nn < 1e-12 {
                return Err(Triangulation::Parallel);
            }
            let n = n / nn;
            let miss = (b.origin - a.origin).dot(&n).abs();
            let var: f64 = [a, b]
                .iter()
                .map(|r| r.lateral_variance(r.direction.dot(&(x - r.origin)).max(0.0)))
                .sum();
            (miss, var.sqrt())
        }
        _ => (0.0, 1.0),
    };
    let bound = two_sigma_bound(rays, &w, &x);
    let eig = cov.symmetric_eigen();
    let mut sd: Vec<f64> = eig.eigenvalues.iter().map(|v| v.max(0.0).sqrt()).collect();
    sd.sort_by(|a, b| b.total_cmp(a));
    let to = x - reference;
    Ok(LightPosition {
        position: x,
        uncertainty: cov.trace().max(0.0).sqrt().max(bound / 2.0),
        principal_std: [sd[0], sd[1], sd[2]],
        distance: to.norm(),
        direction: to.normalize(),
        miss,
        miss_sigmas: miss / miss_sd.max(f64::MIN_POSITIVE),
        accepted: true,
        warnings: Vec::new(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_exact_rays_meet_at_the_light_with_the_closed_form_covariance() {
        // Balls at (±b, 0, 0), the light at (0, 0, L): each ray's lateral error is σ t,
        // t = √(b² + L²), so var_x = σ² t⁴ / (2 L²) (across the bisector), var_y = σ² t² / 2,
        // var_z = σ² t⁴ / (2 b²) (along it: depth from the rays' angle).
        let (b, l, sigma) = (40.0, 300.0, 1e-3);
        let light = Vector3::new(0.0, 0.0, l);
        let ray = |o: Vector3<f64>| Ray {
            origin: o,
            direction: (light - o).normalize(),
            sigma,
            origin_cov: Matrix3::zeros(),
        };
        let (a, c) = (Vector3::new(-b, 0.0, 0.0), Vector3::new(b, 0.0, 0.0));
        let p = triangulate(&[ray(a), ray(c)], &Vector3::zeros()).unwrap();
        assert!((p.position - light).norm() < 1e-9, "{p:?}");
        assert!(p.miss < 1e-9);
        let t2 = b * b + l * l;
        let expected = [
            sigma * t2 / (b * 2f64.sqrt()),
            sigma * t2 / (l * 2f64.sqrt()),
            sigma * t2.sqrt() / 2f64.sqrt(),
        ];
        for (got, want) in p.principal_std.iter().zip(expected) {
            assert!((got / want - 1.0).abs() < 1e-9, "{p:?} vs {expected:?}");
        }
        // Errors this small act linearly: the re-triangulated bound is twice the rms.
        let rms = expected.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!(
            (p.uncertainty / rms - 1.0).abs() < 0.02,
            "{} vs {rms}",
            p.uncertainty
        );
        // Twenty times larger (2σ = 2.3° against rays 15° apart), the distance's error is no
        // longer linear in the angle's: an angle smaller by 2σ lengthens the rays by more than
        // a larger one shortens them, and the stated uncertainty grows beyond the linear one.
        let wide = |o: Vector3<f64>| Ray {
            sigma: 20.0 * sigma,
            ..ray(o)
        };
        let q = triangulate(&[wide(a), wide(c)], &Vector3::zeros()).unwrap();
        let linear = 20.0 * rms;
        assert!(
            q.uncertainty > 1.05 * linear && q.uncertainty < 2.0 * linear,
            "{} vs linear {linear}",
            q.uncertainty
        );
        // Parallel rays fix no position.
        let par = Ray {
            direction: Vector3::z(),
            ..ray(a)
        };
        assert_eq!(
            triangulate(&[par, Ray { origin: c, ..par }], &Vector3::zeros()).unwrap_err(),
            Triangulation::Parallel
        );
        // Rays that diverge meet behind the balls: no position.
        let away = |o: Vector3<f64>| Ray {
            direction: (o - light).normalize(),
            ..ray(o)
        };
        assert_eq!(
            triangulate(&[away(a), away(c)], &Vector3::zeros()).unwrap_err(),
            Triangulation::Diverging
        );
    }
}
