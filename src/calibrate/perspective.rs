//! A mirror sphere seen through a pinhole camera: its outline is a cone of rays, each pixel of
//! it reflects its own view ray, and its centre lies at a distance the outline fixes in units
//! of its radius.
//!
//! Camera frame as in [`crate::camera`]: x right, y up, z towards the viewer; the camera at the
//! origin looks down −z, and the ray through pixel (u, v) is
//! d = normalise((u − c_x)/f_x, −(v − c_y)/f_y, −1).
//!
//! **Outline.** The rays that graze a sphere of radius R whose centre is at distance D along the
//! unit axis a make the same angle α with it, sin α = R/D: the outline is the cone d·a = cos α.
//! Its image is an ellipse, not a circle, once the sphere is off the optical axis (axis ratio
//! about 1/cos θ at θ off-axis: 1.5% at 10°, 6% at 20°), so the circle an orthographic
//! calibration fits is off by a fraction of a pixel to several pixels, and the view direction
//! varies over the ball by about 2α. [`fit_cone`] fits a and α to the outline's edge points by
//! least squares on the angles, β_i − α with β_i = acos(d_i·a) (a geometric fit on the sphere of
//! directions, the counterpart of the circle's geometric fit; see e.g. Wong, Schnieders and Li,
//! "Recovering light directions and camera poses from a single sphere", ECCV 2008, for the
//! sphere's cone of rays).
//!
//! **Reflection.** The ray d through a pixel meets the sphere (in units of R, centre
//! C = a / sin α) at P = t d, t the nearer root of |t d − C| = 1; the normal is n = P − C, and a
//! distant light seen there is l = 2(n·e)n − e with e = −d towards the camera. Unlike the
//! orthographic l = 2 n_z n − z, e differs from pixel to pixel. Given R in any unit of length,
//! the centre and P are positions in that unit ([`SphereCone::centre`]), which is what two
//! balls need to place a near light ([`super::near`]).

// The robust rounds and outlier cut are the circle fit's.
use super::sphere::{Circle, OUTLIER_FLOOR_PX, OUTLIER_SIGMAS, ROBUST_ROUNDS, fit_circle};
use crate::camera::Intrinsics;
use crate::error::{Error, Result};
use crate::stats::median_by;
use nalgebra::{Matrix3, Vector3};
use serde::Serialize;

/// Gauss–Newton iterations of the cone fit.
const ITERATIONS: usize = 30;

/// A sphere's cone of outline rays under a pinhole camera, fitted to its outline.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SphereCone {
    /// The camera.
    pub camera: Intrinsics,
    /// Unit direction from the camera to the sphere's centre (camera frame; z < 0).
    #[serde(serialize_with = "super::serialize_vector")]
    pub axis: Vector3<f64>,
    /// Half-angle α of the cone (radians): sin α = R / D for a sphere of radius R whose centre
    /// is at distance D.
    pub half_angle: f64,
    /// Standard errors (radians) of the axis' tilt along its two tangent directions
    /// ([`SphereCone::tangents`]) and of the half-angle.
    pub std_err: [f64; 3],
    /// Root-mean-square angular distance of the kept points from the cone, in pixels (at the
    /// mean focal length).
    pub rms_px: f64,
    /// Edge points kept by the robust fit.
    pub points: usize,
    /// Edge points rejected as outliers.
    pub outliers: usize,
}

impl SphereCone {
    /// The unit ray from the camera through pixel (u, v).
    pub fn ray(&self, u: f64, v: f64) -> Vector3<f64> {
        ray(&self.camera, u, v)
    }

    /// Two unit vectors completing the axis to a right-handed frame: the directions of the
    /// tilts [`SphereCone::std_err`] measures (the first is horizontal, in the x–z plane).
    pub fn tangents(&self) -> (Vector3<f64>, Vector3<f64>) {
        tangents(&self.axis)
    }

    /// The sphere's centre (camera frame) for a sphere of radius `radius`, in the unit of
    /// `radius`: its distance is `radius / sin α`.
    pub fn centre(&self, radius: f64) -> Vector3<f64> {
        self.axis * (radius / self.half_angle.sin())
    }

    /// Where the ray of pixel (u, v) meets the sphere, and the outward normal there, with the
    /// sphere's radius as the unit of length (multiply the point by R for a position); `None`
    /// where the ray misses it.
    pub fn surface(&self, u: f64, v: f64) -> Option<(Vector3<f64>, Vector3<f64>)> {
        let d = self.ray(u, v);
        let c = self.axis / self.half_angle.sin();
        let b = d.dot(&c);
        let disc = b * b - (c.norm_squared() - 1.0);
        if disc.is_nan() || disc < 0.0 {
            return None;
        }
        let p = (b - disc.sqrt()) * d;
        Some((p, (p - c).normalize()))
    }

    /// The direction (towards the light) that pixel (u, v) of the sphere reflects into the
    /// camera: l = 2(n·e)n − e, e = −d (module doc); `None` off the sphere.
    pub fn reflected(&self, u: f64, v: f64) -> Option<Vector3<f64>> {
        let (_, n) = self.surface(u, v)?;
        let e = -self.ray(u, v);
        Some(2.0 * n.dot(&e) * n - e)
    }

    /// The cone moved by `delta` (radians) in parameter `k`: 0 and 1 tilt the axis along its
    /// tangents, 2 widens the half-angle.
    pub fn perturbed(&self, k: usize, delta: f64) -> SphereCone {
        let mut c = *self;
        let (e1, e2) = self.tangents();
        match k {
            0 => c.axis = (self.axis + delta * e1).normalize(),
            1 => c.axis = (self.axis + delta * e2).normalize(),
            _ => c.half_angle += delta,
        }
        c
    }

    /// The circle that best matches the outline's image (fitted to the projection of 64 of
    /// its rays): where the sphere is, for choosing its pixels.
    pub fn image_circle(&self) -> Circle {
        let (e1, e2) = self.tangents();
        let (s, c) = self.half_angle.sin_cos();
        let points: Vec<[f64; 2]> = (0..64)
            .filter_map(|i| {
                let phi = i as f64 / 64.0 * std::f64::consts::TAU;
                let d = c * self.axis + s * (phi.cos() * e1 + phi.sin() * e2);
                project(&self.camera, &d)
            })
            .collect();
        fit_circle(&points).map_or_else(
            |_| {
                let (u, v) = project(&self.camera, &self.axis).map_or((0.0, 0.0), |p| (p[0], p[1]));
                Circle {
                    cx: u,
                    cy: v,
                    radius: self.camera.fx * self.half_angle.tan(),
                }
            },
            |f| f.circle,
        )
    }

    /// Angle (radians) between the ray through the image point (u, v) and the cone: positive
    /// outside it.
    pub fn angular_distance(&self, u: f64, v: f64) -> f64 {
        self.ray(u, v).dot(&self.axis).clamp(-1.0, 1.0).acos() - self.half_angle
    }
}

/// The unit ray through pixel (u, v).
fn ray(k: &Intrinsics, u: f64, v: f64) -> Vector3<f64> {
    Vector3::new((u - k.cx) / k.fx, -(v - k.cy) / k.fy, -1.0).normalize()
}

/// The pixel a direction (in front of the camera) projects to.
fn project(k: &Intrinsics, d: &Vector3<f64>) -> Option<[f64; 2]> {
    (d.z < 0.0).then(|| [k.cx + k.fx * d.x / -d.z, k.cy - k.fy * d.y / -d.z])
}

/// A right-handed frame (e1, e2) orthogonal to the unit vector `a`, e1 horizontal.
fn tangents(a: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let e1 = Vector3::y().cross(a);
    let e1 = if e1.norm() > 1e-9 {
        e1.normalize()
    } else {
        Vector3::x()
    };
    (e1, a.cross(&e1))
}

/// Fits the cone of outline rays to edge points of the sphere's outline (pixels), started from
/// the circle through them: a geometric least-squares fit on the angles (module doc), with
/// points beyond 3 robust σ (and 0.75 px) dropped and the fit repeated, as [`fit_circle`] does.
///
/// # Errors
/// [`Error::InvalidParameter`] (`points`) with fewer than 4 points, non-finite ones, or points
/// that fit no cone in front of the camera.
pub fn fit_cone(points: &[[f64; 2]], camera: &Intrinsics) -> Result<SphereCone> {
    if points.len() < 4 {
        return Err(Error::param(
            "points",
            format!(
                "{} edge points; a sphere's outline needs at least 4",
                points.len()
            ),
        ));
    }
    let start = fit_circle(points)?;
    let rays: Vec<Vector3<f64>> = points.iter().map(|p| ray(camera, p[0], p[1])).collect();
    let c = start.circle;
    let mut axis = ray(camera, c.cx, c.cy);
    let mut alpha = mean_angle(&rays, &axis);
    let focal = 0.5 * (camera.fx + camera.fy);
    let mut kept: Vec<Vector3<f64>> = rays;
    let mut outliers = 0;
    for _ in 0..ROBUST_ROUNDS {
        (axis, alpha) = gauss_newton(&kept, axis, alpha);
        let mut abs: Vec<f64> = kept
            .iter()
            .map(|d| (angle(d, &axis) - alpha).abs())
            .collect();
        let sigma = 1.4826 * median_by(&mut abs, f64::total_cmp).unwrap_or(0.0);
        let cut = (OUTLIER_SIGMAS * sigma).max(OUTLIER_FLOOR_PX / focal);
        let next: Vec<Vector3<f64>> = kept
            .iter()
            .copied()
            .filter(|d| (angle(d, &axis) - alpha).abs() <= cut)
            .collect();
        if next.len() == kept.len() || next.len() < 4 {
            break;
        }
        outliers += kept.len() - next.len();
        kept = next;
    }
    (axis, alpha) = gauss_newton(&kept, axis, alpha);
    if !(alpha > 0.0
        && alpha < std::f64::consts::FRAC_PI_2
        && axis.z < 0.0
        && axis.iter().all(|v| v.is_finite()))
    {
        return Err(Error::param(
            "points",
            "the edge points fit no sphere in front of the camera",
        ));
    }
    let (jtj, ss) = normal_matrix(&kept, &axis, alpha);
    let n = kept.len();
    let var = ss / n.saturating_sub(3).max(1) as f64;
    let cov = jtj
        .try_inverse()
        .unwrap_or_else(|| Matrix3::from_element(f64::INFINITY));
    Ok(SphereCone {
        camera: *camera,
        axis,
        half_angle: alpha,
        std_err: [
            (cov[(0, 0)] * var).sqrt(),
            (cov[(1, 1)] * var).sqrt(),
            (cov[(2, 2)] * var).sqrt(),
        ],
        rms_px: (ss / n as f64).sqrt() * focal,
        points: n,
        outliers,
    })
}

/// Edge points of the outline kept by a [`fit_cone`] (within its outlier cut), for
/// [`cone_jackknife`].
pub(crate) fn kept_points(points: &[[f64; 2]], cone: &SphereCone) -> Vec<[f64; 2]> {
    let focal = 0.5 * (cone.camera.fx + cone.camera.fy);
    let mut abs: Vec<f64> = points
        .iter()
        .map(|p| cone.angular_distance(p[0], p[1]).abs())
        .collect();
    let sigma = 1.4826 * median_by(&mut abs, f64::total_cmp).unwrap_or(0.0);
    let cut = (OUTLIER_SIGMAS * sigma).max(OUTLIER_FLOOR_PX / focal);
    points
        .iter()
        .copied()
        .filter(|p| cone.angular_distance(p[0], p[1]).abs() <= cut)
        .collect()
}

/// Block-jackknife standard errors (radians) of the cone's three parameters over `sectors`
/// angular sectors of the outline about the image circle's centre (as the circles' jackknife
/// in [`super::sphere`]): the fit without each sector in turn.
pub(crate) fn cone_jackknife(points: &[[f64; 2]], cone: &SphereCone, sectors: usize) -> [f64; 3] {
    let c = cone.image_circle();
    let sector = |p: &[f64; 2]| {
        let a = (p[1] - c.cy)
            .atan2(p[0] - c.cx)
            .rem_euclid(std::f64::consts::TAU);
        ((a / std::f64::consts::TAU * sectors as f64) as usize).min(sectors - 1)
    };
    let (e1, e2) = cone.tangents();
    let mut fits: Vec<[f64; 3]> = Vec::new();
    for s in 0..sectors {
        let rest: Vec<Vector3<f64>> = points
            .iter()
            .filter(|p| sector(p) != s)
            .map(|p| cone.ray(p[0], p[1]))
            .collect();
        if rest.len() == points.len() || rest.len() < 4 {
            continue;
        }
        let (a, alpha) = gauss_newton(&rest, cone.axis, cone.half_angle);
        fits.push([a.dot(&e1), a.dot(&e2), alpha]);
    }
    super::sphere::jackknife_spread(&fits)
}

fn angle(d: &Vector3<f64>, axis: &Vector3<f64>) -> f64 {
    d.dot(axis).clamp(-1.0, 1.0).acos()
}

fn mean_angle(rays: &[Vector3<f64>], axis: &Vector3<f64>) -> f64 {
    rays.iter().map(|d| angle(d, axis)).sum::<f64>() / rays.len().max(1) as f64
}

/// JᵀJ and the sum of squared residuals of the angular residuals β_i − α, with respect to
/// (tilt along e1, tilt along e2, α).
fn normal_matrix(rays: &[Vector3<f64>], axis: &Vector3<f64>, alpha: f64) -> (Matrix3<f64>, f64) {
    let (e1, e2) = tangents(axis);
    let mut jtj = Matrix3::zeros();
    let mut ss = 0.0;
    for d in rays {
        let beta = angle(d, axis);
        let s = beta.sin().max(1e-12);
        let j = Vector3::new(-d.dot(&e1) / s, -d.dot(&e2) / s, -1.0);
        jtj += j * j.transpose();
        ss += (beta - alpha).powi(2);
    }
    (jtj, ss)
}

/// Gauss–Newton on the angular residuals from (axis, α).
fn gauss_newton(
    rays: &[Vector3<f64>],
    mut axis: Vector3<f64>,
    mut alpha: f64,
) -> (Vector3<f64>, f64) {
    for _ in 0..ITERATIONS {
        let (e1, e2) = tangents(&axis);
        let mut jtj = Matrix3::<f64>::zeros();
        let mut jtr = Vector3::<f64>::zeros();
        for d in rays {
            let beta = angle(d, &axis);
            let s = beta.sin().max(1e-12);
            let j = Vector3::new(-d.dot(&e1) / s, -d.dot(&e2) / s, -1.0);
            jtj += j * j.transpose();
            jtr += j * (beta - alpha);
        }
        let Some(step) = jtj.lu().solve(&-jtr) else {
            break;
        };
        if !step.iter().all(|v| v.is_finite()) {
            break;
        }
        axis = (axis + step.x * e1 + step.y * e2).normalize();
        alpha += step.z;
        if step.norm() < 1e-13 {
            break;
        }
    }
    (axis, alpha)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> Intrinsics {
        Intrinsics {
            fx: 900.0,
            fy: 900.0,
            cx: 320.0,
            cy: 240.0,
        }
    }

    /// Outline points of a sphere of radius 1 at `centre`, projected exactly.
    fn outline(k: &Intrinsics, centre: Vector3<f64>, n: usize) -> Vec<[f64; 2]> {
        let a = centre.normalize();
        let alpha = (1.0 / centre.norm()).asin();
        let (e1, e2) = tangents(&a);
        (0..n)
            .filter_map(|i| {
                let phi = i as f64 / n as f64 * std::f64::consts::TAU;
                let d = alpha.cos() * a + alpha.sin() * (phi.cos() * e1 + phi.sin() * e2);
                project(k, &d)
            })
            .collect()
    }

    #[test]
    fn the_cone_of_an_off_axis_sphere_is_recovered_where_a_circle_is_not() {
        let k = camera();
        // 17° off the axis: its image is an ellipse of axis ratio ≈ 1.047.
        let centre = Vector3::new(3.0, -1.5, -11.0);
        let pts = outline(&k, centre, 360);
        let cone = fit_cone(&pts, &k).unwrap();
        assert!(cone.axis.angle(&centre.normalize()) < 1e-9, "{cone:?}");
        assert!((cone.centre(1.0) - centre).norm() < 1e-8 * centre.norm());
        assert!(cone.rms_px < 1e-6, "{}", cone.rms_px);
        // The circle through the same points is off by pixels.
        let circle = fit_circle(&pts).unwrap();
        assert!(circle.rms_px > 0.5, "{}", circle.rms_px);
        // Each outline point's ray grazes the sphere: its reflection is the view ray itself.
        let p = pts[10];
        let inside = [
            p[0] + (cone.image_circle().cx - p[0]) * 1e-4,
            p[1] + (cone.image_circle().cy - p[1]) * 1e-4,
        ];
        let r = cone.reflected(inside[0], inside[1]).unwrap();
        assert!(r.angle(&cone.ray(p[0], p[1])) < 0.05, "{r:?}");
    }

    #[test]
    fn reflection_agrees_with_the_orthographic_limit() {
        // Far away on the axis (a long lens), the perspective reflection of the pixel at
        // normal n is the orthographic 2 n_z n − z.
        let k = Intrinsics {
            fx: 1e6,
            fy: 1e6,
            cx: 0.0,
            cy: 0.0,
        };
        let centre = Vector3::new(0.0, 0.0, -1e4);
        let cone = fit_cone(&outline(&k, centre, 90), &k).unwrap();
        let r_img = k.fx * cone.half_angle.tan();
        let (u, v) = (0.4 * r_img, -0.3 * r_img);
        let n = Vector3::new(0.4, 0.3, (1.0f64 - 0.16 - 0.09).sqrt());
        let ortho = 2.0 * n.z * n - Vector3::z();
        let r = cone.reflected(u, v).unwrap();
        assert!(r.angle(&ortho) < 1e-3, "{r:?} vs {ortho:?}");
    }

    #[test]
    fn outliers_are_dropped_and_too_few_points_refused() {
        let k = camera();
        let centre = Vector3::new(-2.0, 1.0, -9.0);
        let mut pts = outline(&k, centre, 200);
        // A stand below the ball: points 15 px off its outline.
        let c = fit_circle(&pts).unwrap().circle;
        for i in 0..20 {
            pts.push([c.cx - 10.0 + i as f64, c.cy + c.radius + 15.0]);
        }
        let cone = fit_cone(&pts, &k).unwrap();
        assert!(cone.outliers >= 20, "{cone:?}");
        assert!(cone.axis.angle(&centre.normalize()) < 1e-6);
        assert!(fit_cone(&pts[..3], &k).is_err());
    }
}
