//! Perspective shape from shading under a near point light with inverse-square fall-off: the
//! well-posed formulation of Prados & Faugeras ("Shape from shading: a well-posed problem?",
//! CVPR 2005), solved by a monotone upwind scheme.
//!
//! # Model
//! A pinhole camera K sees a surface at depth Z(u, v) along its optical axis; in normalised
//! coordinates (ξ, η) = ((u − c_x)/f_x, (v − c_y)/f_y) the surface point is X = Z·(ξ, η, 1)
//! (internally x right, y down, z forward). With the unknown z = ln Z and its gradient
//! P = (∂z/∂ξ, ∂z/∂η), the (unnormalised) normal facing the camera is
//! n = (P₁, P₂, −(1 + ξP₁ + ηP₂)), of length W(P) = |n|. A point light of intensity Φ at S,
//! at distance d = |S − X|, lights the point with
//!
//! I = Φ·F(cos θ)/d²,  cos θ = n·(S − X)/(W d),
//!
//! F the reflectance's brightness at angle θ (Lambert: F(c) = ρc). Since n·X = −Z,
//! n·(S − X) = Z − S₃ + m·P with m = (S₁ − ξS₃, S₂ − ηS₃), and for a Lambertian surface the
//! image equation becomes the Hamilton–Jacobi equation
//!
//! H(x, z, P) = W(P) − κ m·P − κ(Z − S₃) = 0,  κ = ρΦ/(I d³).
//!
//! For a light at the camera centre (S = 0, a flash) m = 0 and the equation holds for any
//! isotropic reflectance whose brightness grows with cos θ: W(P) = 1/(Q·F⁻¹(I Z² Q²/Φ)),
//! Q = |(ξ, η, 1)|.
//!
//! # Why it is well posed
//! The fall-off makes H strictly increasing in z (a farther point is darker), so the equation
//! has at most one viscosity solution (Prados & Faugeras 2005; the comparison principle needs
//! no boundary condition on the image): unlike the orthographic model under a frontal light,
//! a dent and a bump do not look alike, because the dent is farther from the light. The
//! surface is the solution, with the mask's edge a state constraint (nothing enters from
//! outside the object).
//!
//! # Scheme
//! W is convex in P, W(P) = sup over unit a of a·(P₁, P₂, 1 + ξP₁ + ηP₂), so H is the
//! Hamiltonian of a control problem, H = sup_a [c(a)·P + a₃] − κ(Z − S₃) with velocities
//! c(a) = (a₁ + ξa₃, a₂ + ηa₃) − κm. The scheme replaces each P_i by its upwind one-sided
//! difference (backward where c_i > 0, forward where c_i < 0; Godunov's choice for a convex
//! Hamiltonian, monotone in the sense of Barles & Souganidis 1991) and takes the supremum over
//! a exactly: it is attained inside one of the four sign cones (a = v/|v|), on a face c_i = 0
//! (the disc of the unit ball in that plane), or on the line c = 0, ten closed-form candidates.
//! A missing neighbour removes the controls that would look across it (the state constraint).
//! Each pixel's equation, increasing in its own z and decreasing in its neighbours', is solved
//! by safeguarded regula falsi, in Gauss–Seidel sweeps that alternate the four raster
//! directions (fast sweeping: Zhao, "A fast sweeping method for eikonal equations", Math.
//! Comp. 2005), starting from each pixel's largest depth the brightness allows (cos θ = 1), a
//! supersolution from which the iterates decrease towards the solution. The sweeps stop when
//! no pixel's ln Z moves by more than the tolerance; a run that hits the sweep limit first says
//! so.
//!
//! # Refinement
//! The swept solution is first order and, where the light grazes the surface or cast shadows
//! cut the characteristics, determined only by what flows in from upstream. [`refine`] then
//! fits the whole image from it (least squares over 2×2 cells of lit pixels plus a small
//! curvature penalty, Gauss–Newton with a sparse Cholesky factorisation): on the rendered test
//! shapes with the light 30° off the axis, 5–9° → 1.8–3.3° (see `docs/shape-from-shading.md`).
//! It works coarse to fine: a large mask is swept and refined at half resolution (recursively)
//! and the result upsampled as the start; a start swept at full resolution is first moved by
//! its refinement at half resolution when that level is large enough.
//!
//! # Assumptions and failure modes
//! - The light's position and intensity, the camera and the albedo are known, in consistent
//!   units: the depth comes out absolute, in the units of the light's position. A wrong albedo
//!   scales the depth by about its square root and bends the shape.
//! - Pixels in shadow (darker than the shadow level) carry no equation: their depth is filled
//!   from their neighbours (harmonic interpolation) and they are counted.
//! - Non-Lambertian reflectance is modelled only for a light at the camera centre, where the
//!   brightness depends on θ alone; F must increase with cos θ (checked).
//! - First order: the error shrinks with the pixel size; creases and depth jumps are smoothed.
//! - Interreflections and ambient light are not modelled.

use crate::camera::Intrinsics;
use crate::capture::stack::GREY_WEIGHTS;
use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, ScalarMap};
use crate::integrate::sparse::{NONE, Unknowns};
use crate::sfs::{
    OUTLINE_MISALIGNED_WARN, SfsMethod, SfsReport, SfsResult, occluding, outline_agreement,
    outline_contradicted_warning,
};
use crate::synth::reflectance::{Diffuse, Material};
use nalgebra::Vector3;
use std::time::Instant;

pub mod refine;
pub use refine::{RefineOptions, RefineReport};

/// Default sweep limit of [`solve`].
pub const DEFAULT_MAX_SWEEPS: usize = 400;
/// Default tolerance on the largest change of ln Z in a sweep.
pub const DEFAULT_TOLERANCE: f64 = 1e-7;
/// Samples of the reflectance's brightness over cos θ ∈ [0, 1] (its inverse is interpolated).
const BRIGHTNESS_SAMPLES: usize = 2048;
/// Mean relative residual above which the result is reported as not explaining the image. The
/// residual is taken with the output's central-difference normals, which the first-order
/// scheme matches only to its discretisation: 0.003–0.021 on the rendered test shapes at
/// 128² and 256² (halving with the pixel size), so the limit sits above that.
const POOR_FIT: f64 = 0.05;
/// Times a pixel's drift κm is refreshed at its new depth within one update.
const DRIFT_REFRESHES: usize = 4;
/// A light within this fraction of the scene's distance from the camera centre counts as at it
/// (for non-Lambertian reflectance, which is modelled only there).
const AT_CAMERA: f64 = 0.01;

/// A point light: position in the camera frame (x right, y up, z towards the viewer,
/// [`crate::camera`]; the camera centre is the origin) and intensity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointLight {
    /// Position, in the units the depth is wanted in.
    pub position: Vector3<f64>,
    /// Intensity Φ: the brightness of a white Lambertian surface facing the light at unit
    /// distance.
    pub intensity: f64,
}

/// Options of [`solve`].
#[derive(Debug, Clone)]
pub struct PerspectiveOptions {
    /// The surface's reflectance (its albedo is [`PerspectiveOptions::albedo`]).
    pub material: Material,
    /// Diffuse albedo ρ of the surface.
    pub albedo: f64,
    /// Brightness, as a fraction of the image's 99th percentile in the mask, at or below
    /// which a pixel is in shadow.
    pub shadow_level: f64,
    /// Sweep limit (0: [`DEFAULT_MAX_SWEEPS`]).
    pub max_sweeps: usize,
    /// Largest change of ln Z in a sweep at which the sweeps stop (0: [`DEFAULT_TOLERANCE`]).
    pub tolerance: f64,
    /// A depth map (along the optical axis) to start from instead of the brightness bound: a
    /// warm start, for example the result at a lower resolution. Values above the bound are
    /// lowered to it; NaN pixels start at the bound.
    pub start: Option<ScalarMap>,
    /// The variational refinement of the swept depth ([`refine`]); `None` returns the
    /// viscosity solution as swept.
    pub refine: Option<RefineOptions>,
}

impl Default for PerspectiveOptions {
    fn default() -> Self {
        PerspectiveOptions {
            material: Material::lambertian(),
            albedo: 1.0,
            shadow_level: crate::sfs::DEFAULT_SHADOW_LEVEL,
            max_sweeps: 0,
            tolerance: 0.0,
            start: None,
            refine: Some(RefineOptions::default()),
        }
    }
}

/// The brightness F(cos θ) of the reflectance for a light at the viewer, and its inverse.
#[derive(Clone)]
enum Brightness {
    /// F(c) = ρc.
    Lambert(f64),
    /// F sampled at c = k/(n − 1), increasing.
    Table(Vec<f64>),
}

impl Brightness {
    fn new(material: &Material, albedo: f64) -> Result<Self> {
        if material.specular.is_none() && material.diffuse == Diffuse::Lambertian {
            let grey: f64 = (0..3)
                .map(|c| f64::from(GREY_WEIGHTS[c]) * material.diffuse_color[c])
                .sum();
            return Ok(Brightness::Lambert(albedo * grey));
        }
        let n = BRIGHTNESS_SAMPLES;
        let mut table = Vec::with_capacity(n);
        for k in 0..n {
            let c = k as f64 / (n - 1) as f64;
            let l = Vector3::new((1.0 - c * c).max(0.0).sqrt(), 0.0, c);
            let f = material.eval(albedo, &l, &l);
            let grey: f64 = (0..3).map(|ch| f64::from(GREY_WEIGHTS[ch]) * f[ch]).sum();
            table.push(std::f64::consts::PI * grey * c);
        }
        if let Some(k) = (1..n).find(|&k| table[k] <= table[k - 1]) {
            return Err(Error::param(
                "material",
                format!(
                    "its brightness under a light at the viewer does not grow with cos θ \
                     (it falls near cos θ = {:.3}): the brightness does not determine the \
                     slope",
                    k as f64 / (n - 1) as f64
                ),
            ));
        }
        Ok(Brightness::Table(table))
    }

    /// F(1), the brightest a surface can be.
    fn max(&self) -> f64 {
        match self {
            Brightness::Lambert(r) => *r,
            Brightness::Table(t) => t[t.len() - 1],
        }
    }

    fn eval(&self, c: f64) -> f64 {
        let c = c.clamp(0.0, 1.0);
        match self {
            Brightness::Lambert(r) => r * c,
            Brightness::Table(t) => {
                let x = c * (t.len() - 1) as f64;
                let k = (x as usize).min(t.len() - 2);
                t[k] + (t[k + 1] - t[k]) * (x - k as f64)
            }
        }
    }

    /// F(c) continued linearly beyond [0, 1] (with its slope at each end): smooth, so that a
    /// fit can pull a lit pixel whose current normal faces away from the light back towards
    /// it, where the clamped F would give it no gradient.
    fn eval_extended(&self, c: f64) -> f64 {
        match self {
            Brightness::Lambert(r) => r * c,
            Brightness::Table(t) => {
                let n = (t.len() - 1) as f64;
                if c < 0.0 {
                    t[0] + (t[1] - t[0]) * n * c
                } else if c > 1.0 {
                    t[t.len() - 1] + (t[t.len() - 1] - t[t.len() - 2]) * n * (c - 1.0)
                } else {
                    self.eval(c)
                }
            }
        }
    }

    /// cos θ with F(cos θ) = `f`, clamped to [0, 1].
    fn inverse(&self, f: f64) -> f64 {
        match self {
            Brightness::Lambert(r) => (f / r).clamp(0.0, 1.0),
            Brightness::Table(t) => {
                if f <= t[0] {
                    return 0.0;
                }
                if f >= t[t.len() - 1] {
                    return 1.0;
                }
                let k = t.partition_point(|&v| v <= f).clamp(1, t.len() - 1);
                let (a, b) = (t[k - 1], t[k]);
                ((k - 1) as f64 + (f - a) / (b - a)) / (t.len() - 1) as f64
            }
        }
    }
}

/// One pixel's fixed data.
#[derive(Clone, Copy)]
struct Pixel {
    xi: f64,
    eta: f64,
    /// |(ξ, η, 1)|.
    q: f64,
    /// Brightness.
    i: f64,
}

/// The light in the internal frame (x right, y down, z forward) and the reflectance.
#[derive(Clone)]
struct Model {
    s: Vector3<f64>,
    /// Whether the light is at the camera centre (m = 0, any reflectance).
    at_camera: bool,
    phi: f64,
    brightness: Brightness,
    fx: f64,
    fy: f64,
}

impl Model {
    /// κm (the drift of the light's offset) and the right-hand side r, at ln-depth z.
    fn terms(&self, px: &Pixel, z: f64) -> ([f64; 2], f64) {
        let zz = z.exp();
        if self.at_camera {
            let f = px.i * zz * zz * px.q * px.q / self.phi;
            let c = self.brightness.inverse(f).max(1e-9);
            return ([0.0, 0.0], 1.0 / (px.q * c));
        }
        let x = Vector3::new(px.xi, px.eta, 1.0) * zz;
        let d = (self.s - x).norm();
        let kappa = self.phi * self.brightness.max() / (px.i * d * d * d);
        let s = &self.s;
        (
            [kappa * (s.x - px.xi * s.z), kappa * (s.y - px.eta * s.z)],
            kappa * (zz - s.z),
        )
    }

    /// The smallest ln-depth on the branch where the model's brightness falls with depth: the
    /// depth along the pixel's ray at which κ(Z − S₃) = ρΦ(Z − S₃)/(I d³) peaks (−∞ for a light
    /// at the camera centre, whose brightness falls at every depth). Nearer than that, moving
    /// away from the camera brings the point no farther from an offset light, and the
    /// equation's own monotonicity is lost.
    fn lower(&self, px: &Pixel) -> f64 {
        if self.at_camera {
            return f64::NEG_INFINITY;
        }
        let w = Vector3::new(px.xi, px.eta, 1.0);
        let (q2, ws, s3, ss) = (
            w.norm_squared(),
            w.dot(&self.s),
            self.s.z,
            self.s.norm_squared(),
        );
        // 2Q²Z² − (ω·S + 3S₃Q²)Z + 3S₃ ω·S − |S|² = 0, the larger root.
        let (a, b, c) = (2.0 * q2, -(ws + 3.0 * s3 * q2), 3.0 * s3 * ws - ss);
        let disc = b * b - 4.0 * a * c;
        if disc < 0.0 {
            return f64::NEG_INFINITY;
        }
        let zz = (-b + disc.sqrt()) / (2.0 * a);
        if zz > 0.0 { zz.ln() } else { f64::NEG_INFINITY }
    }

    /// The largest ln-depth the brightness allows (cos θ = 1), and whether the pixel is
    /// brighter than any depth allows.
    fn bound(&self, px: &Pixel) -> (f64, bool) {
        let reach = (self.phi * self.brightness.max() / px.i).sqrt();
        let w = Vector3::new(px.xi, px.eta, 1.0);
        let ww = w.norm_squared();
        let ws = w.dot(&self.s);
        let disc = ws * ws - ww * (self.s.norm_squared() - reach * reach);
        if disc < 0.0 {
            // Closest approach of the ray to the light (none in front of the camera: refused).
            if ws <= 0.0 {
                return (f64::NEG_INFINITY, true);
            }
            return ((ws / ww).ln(), true);
        }
        let zz = (ws + disc.sqrt()) / ww;
        if zz <= 0.0 {
            return (f64::NEG_INFINITY, true);
        }
        (zz.ln(), false)
    }
}

/// Upwind one-sided differences of ln Z along one axis, in normalised units: backward
/// (z − z_prev) and forward (z_next − z).
#[derive(Clone, Copy)]
struct Axis {
    back: Option<f64>,
    fwd: Option<f64>,
}

impl Axis {
    fn pick(&self, positive_velocity: bool) -> Option<f64> {
        if positive_velocity {
            self.back
        } else {
            self.fwd
        }
    }
}

/// The scheme's Hamiltonian sup_a [c(a)·P_upwind + a₃], c(a) = M a − k with rows
/// M₁ = (1, 0, ξ), M₂ = (0, 1, η), over the unit ball; `None` when no control is admissible.
fn upwind_hamiltonian(xi: f64, eta: f64, k: [f64; 2], axes: [Axis; 2]) -> Option<f64> {
    let rows = [Vector3::new(1.0, 0.0, xi), Vector3::new(0.0, 1.0, eta)];
    let ok = |positive: bool, c: f64| if positive { c >= 0.0 } else { c <= 0.0 };
    let mut best = f64::NEG_INFINITY;
    // Inside a sign cone: a = v/|v|, v = Mᵀ P + e₃.
    for s1 in [true, false] {
        let Some(p1) = axes[0].pick(s1) else { continue };
        for s2 in [true, false] {
            let Some(p2) = axes[1].pick(s2) else { continue };
            let v = Vector3::new(p1, p2, 1.0 + xi * p1 + eta * p2);
            let n = v.norm();
            if n == 0.0 {
                continue;
            }
            let a = v / n;
            if ok(s1, rows[0].dot(&a) - k[0]) && ok(s2, rows[1].dot(&a) - k[1]) {
                best = best.max(n - k[0] * p1 - k[1] * p2);
            }
        }
    }
    // On a face c_i = 0: the disc of the ball in the plane M_i·a = k_i.
    for i in 0..2 {
        let j = 1 - i;
        let norm = rows[i].norm();
        let nv = rows[i] / norm;
        let t = k[i] / norm;
        if t.abs() > 1.0 {
            continue;
        }
        let centre = nv * t;
        let radius = (1.0 - t * t).sqrt();
        for sj in [true, false] {
            let Some(pj) = axes[j].pick(sj) else { continue };
            let wv = rows[j] * pj + Vector3::z();
            let perp = wv - nv * wv.dot(&nv);
            let pn = perp.norm();
            let a = if pn > 0.0 {
                centre + perp * (radius / pn)
            } else {
                centre
            };
            if ok(sj, rows[j].dot(&a) - k[j]) {
                best = best.max(a.dot(&wv) - k[j] * pj);
            }
        }
    }
    // On the line c = 0: a = Mᵀ(MMᵀ)⁻¹k + s·(−ξ, −η, 1)/Q, the largest a₃.
    let (g11, g12, g22) = (1.0 + xi * xi, xi * eta, 1.0 + eta * eta);
    let det = g11 * g22 - g12 * g12;
    let y1 = (g22 * k[0] - g12 * k[1]) / det;
    let y2 = (g11 * k[1] - g12 * k[0]) / det;
    let ap = rows[0] * y1 + rows[1] * y2;
    let r2 = ap.norm_squared();
    if r2 <= 1.0 {
        let q = (1.0 + xi * xi + eta * eta).sqrt();
        best = best.max(ap.z + (1.0 - r2).sqrt() / q);
    }
    best.is_finite().then_some(best)
}

/// The scheme's residual at one pixel for ln-depth z, given its neighbours' values and the
/// drift k = κm (taken at the pixel's previous depth: with it frozen the residual grows with z,
/// since the fall-off makes r fall and the upwind differences grow).
fn residual_at(model: &Model, px: &Pixel, z: f64, nb: [Option<f64>; 4], k: [f64; 2]) -> f64 {
    let [left, right, up, down] = nb;
    let axes = [
        Axis {
            back: left.map(|l| model.fx * (z - l)),
            fwd: right.map(|r| model.fx * (r - z)),
        },
        Axis {
            back: up.map(|u| model.fy * (z - u)),
            fwd: down.map(|d| model.fy * (d - z)),
        },
    ];
    let (_, r) = model.terms(px, z);
    match upwind_hamiltonian(px.xi, px.eta, k, axes) {
        Some(hv) => hv - r,
        None => f64::INFINITY,
    }
}

/// Solves one pixel's equation for its ln-depth, from `z0`, not above `upper`, to within
/// `precision`: the drift κm frozen at the current depth, refreshed at the new one until it
/// moves by less than `precision` (at most [`DRIFT_REFRESHES`] times; none for a light at the
/// camera, whose drift is 0).
fn solve_pixel(
    model: &Model,
    px: &Pixel,
    z0: f64,
    (lower, upper): (f64, f64),
    nb: [Option<f64>; 4],
    precision: f64,
) -> Option<f64> {
    let mut z = z0.clamp(lower, upper);
    for refresh in 0..DRIFT_REFRESHES {
        let (k, _) = model.terms(px, z);
        let Some(next) = solve_frozen(model, px, z, (lower, upper), nb, k, precision) else {
            // Rootless from the start, or after a first update (kept).
            return (refresh > 0).then_some(z);
        };
        let moved = (next - z).abs();
        z = next;
        if model.at_camera || moved < precision {
            break;
        }
    }
    Some(z)
}

/// One pixel's equation with the drift `k` frozen: increasing in z, solved by bracketing and
/// regula falsi until the bracket is narrower than `precision`; `None` when it has no root on
/// the physical branch with these neighbours (where the light grazes the surface, the equation
/// may not be solvable until they settle).
fn solve_frozen(
    model: &Model,
    px: &Pixel,
    z0: f64,
    (lower, upper): (f64, f64),
    nb: [Option<f64>; 4],
    k: [f64; 2],
    precision: f64,
) -> Option<f64> {
    let f = |z: f64| residual_at(model, px, z, nb, k);
    let z0 = z0.clamp(lower, upper);
    let f0 = f(z0);
    if f0 == 0.0 {
        return Some(z0);
    }
    // Bracket the root: the residual grows with z.
    let (mut lo, mut hi, mut flo, mut fhi);
    let mut step = 1e-4;
    if f0 > 0.0 {
        (hi, fhi) = (z0, f0);
        loop {
            let z = (hi - step).max(lower);
            let fz = f(z);
            if fz <= 0.0 {
                (lo, flo) = (z, fz);
                break;
            }
            if z <= lower || step > 50.0 {
                return None;
            }
            (hi, fhi) = (z, fz);
            step *= 4.0;
        }
    } else {
        (lo, flo) = (z0, f0);
        loop {
            let z = (lo + step).min(upper);
            let fz = f(z);
            if fz >= 0.0 {
                (hi, fhi) = (z, fz);
                break;
            }
            if z >= upper {
                // The root would put the point beyond the depth at which it faces the light.
                return None;
            }
            (lo, flo) = (z, fz);
            step *= 4.0;
        }
    }
    // Regula falsi, Illinois variant.
    let mut side = 0i8;
    for _ in 0..60 {
        if hi - lo < precision {
            break;
        }
        let z = if flo.is_finite() && fhi.is_finite() {
            let z = (lo * fhi - hi * flo) / (fhi - flo);
            if z > lo && z < hi { z } else { 0.5 * (lo + hi) }
        } else {
            0.5 * (lo + hi)
        };
        let fz = f(z);
        if fz == 0.0 {
            return Some(z);
        }
        if fz > 0.0 {
            (hi, fhi) = (z, fz);
            if side == 1 {
                flo *= 0.5;
            }
            side = 1;
        } else {
            (lo, flo) = (z, fz);
            if side == -1 {
                fhi *= 0.5;
            }
            side = -1;
        }
    }
    Some(if flo.abs() < fhi.abs() { lo } else { hi })
}

/// Perspective shape from shading of `image` (linear brightness) inside `mask`, seen by
/// `camera` under the point `light` (see the module documentation).
///
/// The swept solution is refined by [`refine`] unless [`PerspectiveOptions::refine`] is `None`;
/// with the refinement on, a mask of more than 2¹⁴ pixels is swept at half resolution
/// (recursively), refined there, and upsampled as the start of the refinement.
///
/// Returns depth along the optical axis (positive, in the units of the light's position),
/// unit normals in the camera frame (z towards the viewer), the orthographic gradients of
/// those normals (p = −n_x/n_z, q = −n_y/n_z), the residual (I − I_model)·d²/(Φ F(1)), the
/// pixels whose depth was not fitted to their own brightness (`shadow`, counted in the report's
/// `shadow_pixels`: refined, the pixels that are a corner of no 2×2 block of lit pixels; swept
/// only, those in shadow or lit where the scheme has no solution, while lit pixels of the
/// occluding contour, extrapolated in a straight line from inside, are not among them), and a
/// report whose `light` is the unit direction from the surface's centre to the light and whose
/// `refinement` says what the refinement did.
///
/// # Errors
/// [`Error::InvalidParameter`] when the sizes differ, the mask is empty or holds a non-finite
/// or negative brightness, the light's intensity, the albedo, the shadow level, the tolerance or
/// a refinement option is out of range, the light is not in front of the camera's plane, the
/// material is non-Lambertian and the light is not at the camera centre, or the material's
/// brightness does not grow with cos θ.
pub fn solve(
    image: &ScalarMap,
    mask: &Mask,
    camera: &Intrinsics,
    light: &PointLight,
    options: &PerspectiveOptions,
) -> Result<SfsResult> {
    solve_swept(image, mask, camera, light, options).map(|(r, _)| r)
}

/// [`solve`], and the size of the image the sweeps ran on (smaller than the image's when they
/// ran at half resolution, recursively).
fn solve_swept(
    image: &ScalarMap,
    mask: &Mask,
    camera: &Intrinsics,
    light: &PointLight,
    options: &PerspectiveOptions,
) -> Result<(SfsResult, (usize, usize))> {
    let started = Instant::now();
    image.check_same_size(mask, "mask")?;
    let (w, h) = (image.width(), image.height());
    if !(light.intensity.is_finite() && light.intensity > 0.0) {
        return Err(Error::param(
            "light intensity",
            format!("{} must be finite and > 0", light.intensity),
        ));
    }
    if !light.position.iter().all(|v| v.is_finite()) {
        return Err(Error::param("light position", "must be finite"));
    }
    if !(options.albedo.is_finite() && options.albedo > 0.0) {
        return Err(Error::param(
            "albedo",
            format!("{} must be finite and > 0", options.albedo),
        ));
    }
    crate::sfs::check_shadow_level(options.shadow_level)?;
    if !(options.tolerance.is_finite() && options.tolerance >= 0.0) {
        return Err(Error::param(
            "tolerance",
            format!("{} must be finite and ≥ 0", options.tolerance),
        ));
    }
    if mask.count() == 0 {
        return Err(Error::param("mask", "is empty: no pixel to solve"));
    }
    if let Some(i) = (0..mask.len()).find(|&i| mask.data()[i] && !image.data()[i].is_finite()) {
        return Err(Error::param(
            "image",
            format!(
                "pixel ({}, {}) inside the mask is {}: mask it out or repair the image",
                i % w,
                i / w,
                image.data()[i]
            ),
        ));
    }
    let focal_ok = |f: f64| f.is_finite() && f > 0.0;
    if !(focal_ok(camera.fx)
        && focal_ok(camera.fy)
        && camera.cx.is_finite()
        && camera.cy.is_finite())
    {
        return Err(Error::param(
            "camera",
            format!(
                "fx {} fy {} cx {} cy {}: focal lengths must be finite and > 0, the principal \
                 point finite",
                camera.fx, camera.fy, camera.cx, camera.cy
            ),
        ));
    }
    options.material.validate()?;
    let brightness = Brightness::new(&options.material, options.albedo)?;
    if brightness.max().is_nan() || brightness.max() <= 0.0 {
        return Err(Error::param(
            "material",
            "reflects no light towards a light at the viewer (its diffuse colour or lobe is 0)",
        ));
    }
    let s = Vector3::new(light.position.x, -light.position.y, -light.position.z);
    if s.z > 0.0 {
        return Err(Error::param(
            "light position",
            format!(
                "({:.4}, {:.4}, {:.4}) is in front of the camera's plane; this model needs the \
                 light in or behind it (z ≥ 0, x right, y up, z towards the viewer)",
                light.position.x, light.position.y, light.position.z
            ),
        ));
    }
    let tolerance = if options.tolerance > 0.0 {
        options.tolerance
    } else {
        DEFAULT_TOLERANCE
    };
    let max_sweeps = if options.max_sweeps > 0 {
        options.max_sweeps
    } else {
        DEFAULT_MAX_SWEEPS
    };

    // Shadows: relative to the image's 99th percentile in the mask.
    let mut lit_values: Vec<f32> = (0..mask.len())
        .filter(|&i| mask.data()[i])
        .map(|i| image.data()[i])
        .collect();
    let p99 = crate::stats::quantile_in_place(&mut lit_values, 0.99).map_or(0.0, f64::from);
    if p99 <= 0.0 {
        return Err(Error::param("image", "is black inside the mask"));
    }
    let shadow_at = options.shadow_level * p99;
    // The occluding contour: mask pixels with a 4-neighbour outside the mask inside the image
    // (the image's border is not a contour). There the surface turns away within the pixel,
    // more steeply than a difference across pixels can follow, and the light grazes it too
    // wherever the light is off the axis: no equation; extrapolated from inside.
    let contour = Grid::from_fn(w, h, |c, r| {
        *mask.at(c, r)
            && ((c > 0 && !*mask.at(c - 1, r))
                || (c + 1 < w && !*mask.at(c + 1, r))
                || (r > 0 && !*mask.at(c, r - 1))
                || (r + 1 < h && !*mask.at(c, r + 1)))
    });
    let domain = Grid::from_fn(w, h, |c, r| {
        *mask.at(c, r) && f64::from(*image.at(c, r)) > shadow_at && !*contour.at(c, r)
    });
    let all = Unknowns::new(mask);
    let u = Unknowns::new(&domain);
    let n = u.len();
    if n == 0 {
        return Err(Error::param(
            "image",
            "every pixel of the mask is in shadow",
        ));
    }
    let pixel_of = |pix: usize| {
        let (c, r) = ((pix % w) as f64, (pix / w) as f64);
        let xi = (c - camera.cx) / camera.fx;
        let eta = (r - camera.cy) / camera.fy;
        Pixel {
            xi,
            eta,
            q: (1.0 + xi * xi + eta * eta).sqrt(),
            i: f64::from(image.data()[pix]),
        }
    };
    let pixels: Vec<Pixel> = u.pixel.iter().map(|&p| pixel_of(p as usize)).collect();

    // Where the light is: at the camera centre when within AT_CAMERA of the scene's distance.
    let reach_median = {
        let mut r: Vec<f64> = pixels
            .iter()
            .map(|p| (light.intensity * brightness.max() / p.i).sqrt() / p.q)
            .collect();
        let mid = r.len() / 2;
        *r.select_nth_unstable_by(mid, f64::total_cmp).1
    };
    let at_camera = s.norm() <= AT_CAMERA * reach_median;
    let lambertian = matches!(brightness, Brightness::Lambert(_));
    if !at_camera && !lambertian {
        return Err(Error::param(
            "material",
            format!(
                "non-Lambertian reflectance is modelled only for a light at the camera centre; \
                 this light is {:.3} away, {:.1}% of the scene's distance",
                s.norm(),
                100.0 * s.norm() / reach_median
            ),
        ));
    }
    let model = Model {
        s: if at_camera { Vector3::zeros() } else { s },
        at_camera,
        phi: light.intensity,
        brightness,
        fx: camera.fx,
        fy: camera.fy,
    };

    // The swept solution on the whole mask: at this resolution, or (for a large mask that is
    // to be refined) the refined solution of the half-resolution image, upsampled.
    // The brightness bound of each lit pixel: where cos θ = 1, the largest depth it allows.
    let mut too_bright = 0usize;
    let upper: Vec<f64> = pixels
        .iter()
        .map(|p| {
            let (b, bright) = model.bound(p);
            if bright {
                too_bright += 1;
            }
            b
        })
        .collect();
    if let Some(k) = upper.iter().position(|b| !b.is_finite()) {
        let pix = u.pixel[k] as usize;
        return Err(Error::param(
            "light position",
            format!(
                "pixel ({}, {}) is brighter than the light can make any point on its ray",
                pix % w,
                pix / w
            ),
        ));
    }
    if let Some(r) = &options.refine {
        r.validate()?;
    }
    let sweep = || -> Result<Swept> {
        // Start: the brightness bound (a supersolution), or the warm start below it.
        let lower: Vec<f64> = pixels
            .iter()
            .zip(&upper)
            .map(|(p, &u)| model.lower(p).min(u))
            .collect();
        let mut z = upper.clone();
        if let Some(start) = &options.start {
            start.check_same_size(mask, "start depth")?;
            for (k, &pix) in u.pixel.iter().enumerate() {
                let v = f64::from(start.data()[pix as usize]);
                if v.is_finite() && v > 0.0 {
                    z[k] = v.ln().min(upper[k]);
                }
            }
        }

        // Fast sweeping: Gauss–Seidel in the four raster directions.
        let index = {
            let mut idx = vec![NONE; w * h];
            for (k, &p) in u.pixel.iter().enumerate() {
                idx[p as usize] = k as u32;
            }
            idx
        };
        let nb = |z: &[f64], k: usize| {
            let get = |j: u32| (j != NONE).then(|| z[j as usize]);
            [
                get(u.left[k]),
                get(u.right[k]),
                get(u.up[k]),
                get(u.down[k]),
            ]
        };
        let Some(window) = domain.bounding_box() else {
            return Err(Error::param(
                "image",
                "every pixel of the mask is in shadow",
            ));
        };
        let (c0, c1, r0, r1) = (window.x0, window.x1 - 1, window.y0, window.y1 - 1);
        let mut rootless = vec![false; n];
        // A pixel is revisited only when a neighbour moved since its last update (its own
        // equation was then solved to `precision`): later sweeps touch only the pixels still
        // moving.
        let mut dirty = vec![true; n];
        let settled = 0.01 * tolerance;
        // Each pixel's root to a tenth of the motion that wakes its neighbours: finer roots
        // only move ln Z in digits that neither the sweeps' stopping test nor a neighbour reads
        // (10⁻¹² before; the errors of `bench sfs` are unchanged, docs/shape-from-shading.md).
        let precision = 0.1 * settled;
        let mut sweeps = 0;
        let mut converged = false;
        let mut last_change = f64::INFINITY;
        while sweeps < max_sweeps {
            let (rev_r, rev_c) =
                [(false, false), (true, true), (false, true), (true, false)][sweeps % 4];
            let mut change = 0f64;
            for ri in 0..=(r1 - r0) {
                let r = if rev_r { r1 - ri } else { r0 + ri };
                for ci in 0..=(c1 - c0) {
                    let c = if rev_c { c1 - ci } else { c0 + ci };
                    let k = index[r * w + c];
                    if k == NONE {
                        continue;
                    }
                    let k = k as usize;
                    if !dirty[k] {
                        continue;
                    }
                    dirty[k] = false;
                    // No root with these neighbours: the pixel waits for them to settle.
                    let Some(new) = solve_pixel(
                        &model,
                        &pixels[k],
                        z[k],
                        (lower[k], upper[k]),
                        nb(&z, k),
                        precision,
                    ) else {
                        rootless[k] = true;
                        continue;
                    };
                    rootless[k] = false;
                    let moved = (new - z[k]).abs();
                    change = change.max(moved);
                    z[k] = new;
                    if moved > settled {
                        for j in [u.left[k], u.right[k], u.up[k], u.down[k]] {
                            if j != NONE {
                                dirty[j as usize] = true;
                            }
                        }
                    }
                }
            }
            sweeps += 1;
            last_change = change;
            if change <= tolerance {
                converged = true;
                break;
            }
        }

        // Depth on the whole mask: shadowed pixels filled harmonically from the solved ones.
        let mut lnz = vec![f64::NAN; all.len()];
        let mut known = vec![false; all.len()];
        {
            let mut pos = vec![NONE; w * h];
            for (k, &p) in all.pixel.iter().enumerate() {
                pos[p as usize] = k as u32;
            }
            for (k, &p) in u.pixel.iter().enumerate() {
                if !rootless[k] {
                    let j = pos[p as usize] as usize;
                    lnz[j] = z[k];
                    known[j] = true;
                }
            }
        }
        // Contour pixels: the straight line through the two pixels inside, along each axis that
        // leaves the mask (their mean where two do).
        let mut extrapolated = 0usize;
        let mut line_fill = Vec::new();
        for k in 0..all.len() {
            let pix = all.pixel[k] as usize;
            if known[k] || !contour.data()[pix] || f64::from(image.data()[pix]) <= shadow_at {
                continue;
            }
            let inner = |j: u32, step: fn(&Unknowns, usize) -> u32| -> Option<f64> {
                if j == NONE || !known[j as usize] {
                    return None;
                }
                let j2 = step(&all, j as usize);
                if j2 == NONE || !known[j2 as usize] {
                    return None;
                }
                Some(2.0 * lnz[j as usize] - lnz[j2 as usize])
            };
            let mut candidates = Vec::with_capacity(2);
            if all.left[k] == NONE || all.right[k] == NONE {
                candidates.extend(
                    inner(all.right[k], |u, j| u.right[j])
                        .or_else(|| inner(all.left[k], |u, j| u.left[j])),
                );
            }
            if all.up[k] == NONE || all.down[k] == NONE {
                candidates.extend(
                    inner(all.down[k], |u, j| u.down[j])
                        .or_else(|| inner(all.up[k], |u, j| u.up[j])),
                );
            }
            if !candidates.is_empty() {
                line_fill.push((k, candidates.iter().sum::<f64>() / candidates.len() as f64));
            }
        }
        for (k, v) in line_fill {
            lnz[k] = v;
            known[k] = true;
            extrapolated += 1;
        }
        let unfilled = fill_harmonic(&all, &mut lnz, &known);
        let singular = z
            .iter()
            .zip(&upper)
            .filter(|(a, b)| (*b - *a) < 1e-6)
            .count();
        Ok(Swept {
            lnz,
            known,
            sweeps,
            converged,
            last_change,
            grazing: rootless.iter().filter(|&&b| b).count(),
            extrapolated,
            unfilled,
            singular,
            coarse: None,
            coarse_steps: None,
            coarse_discarded: false,
        })
    };
    let Swept {
        mut lnz,
        mut known,
        sweeps,
        converged,
        last_change,
        grazing,
        extrapolated,
        unfilled,
        singular,
        coarse,
        coarse_steps,
        coarse_discarded,
    } = match coarse_start(image, mask, camera, light, options, &all)? {
        Some(swept) => swept,
        None => sweep()?,
    };

    // The variational refinement, from the swept and filled depth, on every pixel with one.
    // The refinement's report, and whether the depth returned is the one swept at this
    // resolution (not refined, refined on no cell, or its refinement discarded with no lower
    // resolution having moved its start; an upsampled start is never the swept depth).
    let (refinement, swept_depth) = match &options.refine {
        None => (None, true),
        Some(refine_options) => {
            let keep: Vec<usize> = (0..all.len()).filter(|&k| lnz[k].is_finite()).collect();
            let sites: Vec<refine::Site> = keep
                .iter()
                .map(|&k| {
                    let pix = all.pixel[k] as usize;
                    let px = pixel_of(pix);
                    refine::Site {
                        xi: px.xi,
                        eta: px.eta,
                        i: px.i,
                        lit: px.i > shadow_at,
                    }
                })
                .collect();
            let grid: Vec<(usize, usize)> = keep
                .iter()
                .map(|&k| {
                    let pix = all.pixel[k] as usize;
                    (pix / w, pix % w)
                })
                .collect();
            let mut zk: Vec<f64> = keep.iter().map(|&k| lnz[k]).collect();
            let problem = refine::Problem::new(&model, &sites, &grid, w, h);
            // A start swept at this resolution is refined at half resolution first (when that
            // level is large enough and it helps); an upsampled start already was.
            let coarse_iterations = match coarse_steps {
                Some(steps) => steps,
                None => refine::refine_from_half(
                    &problem,
                    (&model, &sites, &grid),
                    (w, h),
                    &mut zk,
                    refine_options,
                ),
            };
            let mut report = refine::refine(&problem, &mut zk, refine_options)?;
            report.coarse_iterations = coarse_iterations;
            let fitted = problem.fitted();
            // A discarded refinement left `zk` at its start, which is returned. The swept depth
            // keeps what its sweeps solved and what they interpolated; any other start (moved by
            // the half-resolution refinement, or upsampled) counts the pixels of lit cells as
            // solved, as a refined result does.
            let swept = coarse_steps.is_none()
                && (report.cells == 0 || (report.discarded && coarse_iterations == 0));
            if report.cells > 0 {
                if !swept {
                    for k in known.iter_mut() {
                        *k = false;
                    }
                    for (t, &k) in keep.iter().enumerate() {
                        known[k] = fitted[t];
                    }
                }
                for (t, &k) in keep.iter().enumerate() {
                    lnz[k] = zk[t];
                }
            }
            (Some(report), swept)
        }
    };
    let depth_v: Vec<f64> = lnz.iter().map(|v| v.exp()).collect();
    let depth = all.to_map(&depth_v);

    // Normals from central differences of ln Z (one-sided at the edge).
    let mut normals = Grid::new(w, h, Vector3::repeat(f32::NAN));
    let mut pmap = Grid::new(w, h, f32::NAN);
    let mut qmap = Grid::new(w, h, f32::NAN);
    let mut residual = Grid::new(w, h, f32::NAN);
    let mut shadow = Grid::new(w, h, false);
    let (mut abs_sum, mut lit, mut centre, mut placed) = (0.0, 0usize, Vector3::zeros(), 0usize);
    let diff = |a: u32, b: u32, k: usize, f: f64| -> f64 {
        let v = |j: u32| (j != NONE && lnz[j as usize].is_finite()).then(|| lnz[j as usize]);
        match (v(a), v(b)) {
            (Some(x), Some(y)) => 0.5 * f * (y - x),
            (None, Some(y)) => f * (y - lnz[k]),
            (Some(x), None) => f * (lnz[k] - x),
            (None, None) => 0.0,
        }
    };
    for k in 0..all.len() {
        if !lnz[k].is_finite() {
            continue;
        }
        let pix = all.pixel[k] as usize;
        let px = pixel_of(pix);
        let p1 = diff(all.left[k], all.right[k], k, camera.fx);
        let p2 = diff(all.up[k], all.down[k], k, camera.fy);
        let ni = Vector3::new(p1, p2, -(1.0 + px.xi * p1 + px.eta * p2)).normalize();
        let nc = Vector3::new(ni.x, -ni.y, -ni.z);
        normals.data_mut()[pix] = nc.cast::<f32>();
        if nc.z > 1e-9 {
            pmap.data_mut()[pix] = (-nc.x / nc.z) as f32;
            qmap.data_mut()[pix] = (-nc.y / nc.z) as f32;
        }
        let x = Vector3::new(px.xi, px.eta, 1.0) * lnz[k].exp();
        centre += x;
        placed += 1;
        let to_light = model.s - x;
        let d = to_light.norm();
        let cos = ni.dot(&to_light) / d;
        let scale = light.intensity * model.brightness.max() / (d * d);
        let predicted = light.intensity * model.brightness.eval(cos) / (d * d);
        let res = (px.i - predicted) / scale;
        residual.data_mut()[pix] = res as f32;
        if known[k] {
            abs_sum += res.abs();
            lit += 1;
        } else {
            shadow.data_mut()[pix] = true;
        }
    }
    let centre = centre / placed.max(1) as f64;
    let to_light = (model.s - centre).normalize();
    let to_camera = (-centre).normalize();
    let slant = to_light
        .dot(&to_camera)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees();
    let light_dir = [to_light.x, -to_light.y, -to_light.z];
    let mean_abs_residual = if lit > 0 { abs_sum / lit as f64 } else { 0.0 };
    let curl = crate::ps::normals::integrability(&pmap, &qmap).summary;
    let mut assumptions = vec![
        "perspective camera, point light with inverse-square fall-off: the unique viscosity \
         solution (Prados & Faugeras 2005), no boundary condition"
            .to_string(),
        format!(
            "albedo {} and light intensity {} known; depth in the light position's units",
            options.albedo, light.intensity
        ),
    ];
    if extrapolated > 0 && swept_depth {
        assumptions.push(format!(
            "{extrapolated} pixels on the occluding contour continue the depth inside in a \
             straight line"
        ));
    }
    if let Some((cw, ch)) = &coarse {
        assumptions.push(format!(
            "swept at {cw}×{ch} (halving the resolution until the mask has at most \
             {SWEEP_AT_MOST} pixels), refined at each resolution from the one below{}",
            if coarse_discarded {
                " (at half resolution the refinement moved the whole surface and was \
                 discarded: that level's start was upsampled)"
            } else {
                ""
            }
        ));
    } else if refinement.as_ref().is_some_and(|r| r.coarse_iterations > 0) {
        assumptions.push(
            "the swept start refined at half resolution first (recursively), its change \
             interpolated back"
                .to_string(),
        );
    }
    if let Some(r) = refinement.as_ref().filter(|r| !r.discarded && r.cells > 0) {
        assumptions.push(format!(
            "refined: the depth of least squared image residual over {} cells of lit pixels \
             plus {} times its squared second differences, from the swept solution (a local \
             minimum near it); shadowed pixels continue the lit surface with least curvature",
            r.cells, r.smoothness
        ));
    }
    if at_camera {
        assumptions.push(format!(
            "light at the camera centre ({:.3} from it, {:.2}% of the scene's distance)",
            s.norm(),
            100.0 * s.norm() / reach_median
        ));
    }
    let mut warnings = Vec::new();
    if !converged {
        let at = coarse.map_or(String::new(), |(cw, ch)| format!(" at {cw}×{ch}"));
        warnings.push(format!(
            "perspective stopped at its limit of {max_sweeps} sweeps{at} without converging \
             (last change of ln Z {last_change:.2e}, tolerance {tolerance:.1e})"
        ));
    }
    if too_bright as f64 > 0.01 * n as f64 {
        warnings.push(format!(
            "{too_bright} of {n} pixels are brighter than the light can make them at any \
             depth: the albedo or the light's intensity is too low, or the light is misplaced"
        ));
    }
    if let Some(r) = refinement.as_ref().filter(|r| r.discarded) {
        let start = match coarse {
            Some((cw, ch)) => format!("the solution at {cw}×{ch}, upsampled"),
            None if r.coarse_iterations > 0 => {
                "the swept solution as its refinement at half resolution moved it".to_string()
            }
            None => "the swept solution".to_string(),
        };
        // The limit is symmetric in ln Z: nearer, it is a little under 5%.
        let bound = 100.0 * ((refine::MAX_SHIFT * r.shift.signum()).exp() - 1.0);
        warnings.push(format!(
            "the refinement was discarded after {} step{}: they moved the whole surface by \
             {:+.2}% of its distance, past the {bound:+.2}% within which a refinement stays \
             near its start (the energy has a lower valley elsewhere, which the image alone \
             does not rule out); the depth is that start, {start}, less accurate than a \
             refined one",
            r.iterations,
            if r.iterations == 1 { "" } else { "s" },
            100.0 * (r.shift.exp() - 1.0),
        ));
    }
    if let Some(r) = refinement.as_ref().filter(|r| !r.converged && !r.discarded) {
        warnings.push(format!(
            "the refinement stopped at its limit of {} step{} without converging (energy \
             {:.3e} from {:.3e})",
            r.iterations,
            if r.iterations == 1 { "" } else { "s" },
            r.energy_end,
            r.energy_start
        ));
    }
    let shadow_pixels = shadow.count();
    if shadow_pixels as f64 > 0.3 * all.len() as f64 {
        warnings.push(format!(
            "{shadow_pixels} of {} pixels are in shadow or unsolved: their depth is \
             interpolated from their neighbours",
            all.len()
        ));
    }
    if grazing > 0 && swept_depth {
        let what = format!(
            "{grazing} of {n} lit pixels have no solution of the scheme (typically where the \
             light grazes the surface): their depth is interpolated from their neighbours"
        );
        if grazing as f64 > 0.01 * n as f64 {
            warnings.push(what);
        } else {
            assumptions.push(what);
        }
    }
    if unfilled > 0 {
        warnings.push(format!(
            "{unfilled} shadowed pixels touch no lit pixel of their part: left without depth"
        ));
    }
    if mean_abs_residual > POOR_FIT {
        warnings.push(format!(
            "the result explains the image poorly (mean relative residual \
             {mean_abs_residual:.3}): the light, the albedo or the reflectance is probably wrong"
        ));
    }
    // The outline's normals against the occluding contour the sweeps assumed there: a solution
    // that took another branch turns them (the vase 40° off the axis: 18–70% misaligned at
    // 64²–128², over a quarter on 9 of 15, while every solution within 5° and 5% stayed at or
    // under 13%; the threshold is Horn's, chosen on its own solves).
    // The outline, tested against the image as Horn's is (`occluding`): an outline pixel
    // brighter than a surface turning away from the view could be there, at the depth the result
    // gives it, contradicts the occluding contour the sweeps and the outline test assume. Such
    // pixels are left out of the agreement below.
    let sigma = f64::from(crate::ps::noise::image_noise(image.data(), w, mask).sigma);
    let margin = if sigma.is_finite() {
        (3.0 * sigma).max(shadow_at)
    } else {
        shadow_at
    };
    let tested = occluding::test_outline(&all, margin, |k, mx, my| {
        let px = pixel_of(all.pixel[k] as usize);
        lnz[k].is_finite()
            && px.i
                > brightest_edge_on(&model, light.intensity, camera, &px, lnz[k], (mx, my)) + margin
    });
    // With the light at the camera the equation needs nothing from the outline (the vase,
    // whose cut ends contradict 8% of its outline, is solved within 4° there); off it, where
    // the light grazes the surface, the solution depends on what flows in from the edges, and
    // a cut edge taken for a contour sends it to another surface (the vase lit from below, 10°
    // to 35° off the axis: 5–27° off the truth, docs/shape-from-shading.md).
    if let Some(t) = tested
        .summary
        .filter(|t| t.fraction > occluding::CONTRADICTED_WARN)
    {
        let what = format!(
            "the mask's outline is not an occluding contour along {:.0}% of it ({} of {} \
             pixels are brighter than a surface turning away from the view can be at their \
             depth): there the mask cuts across the surface (a cut end, a foot on a table)",
            100.0 * t.fraction,
            t.contradicted,
            t.pixels
        );
        if at_camera {
            assumptions.push(format!(
                "{what}; with the light at the camera the solution needs no condition there"
            ));
        } else {
            warnings.push(format!(
                "{what}; with the light off the camera's axis such an edge admits more than \
                 one surface, and the result may be wrong, near that edge and beyond it (a \
                 rendered vase cut so: 16 of its 30 solves 10°–35° off the axis more than 5° or \
                 5% off the truth, 15 of them lit from below the image's horizontal)"
            ));
        }
    }
    let outline = outline_agreement(&all, &normals, &tested.contradicted);
    if let Some(o) = outline.filter(|o| o.misaligned_fraction > OUTLINE_MISALIGNED_WARN) {
        // From about 20° off the axis the rendered shapes begin to fail (2–4 of 25 at 20°,
        // 3–17 at 30°, 15–21 at 40°: docs/shape-from-shading.md), so the light is named then.
        let why = if slant >= 20.0 {
            format!(
                "a light {slant:.0}° off the camera's direction as seen from the surface's \
                 centre, or a small image, admits several; a light nearer the camera or a \
                 larger image is solved more reliably"
            )
        } else {
            "a small image admits several; a larger one is solved more reliably".to_string()
        };
        warnings.push(format!(
            "{} ({why}); the shape is probably wrong",
            outline_contradicted_warning(&o, "the solution")
        ));
    }
    let report = SfsReport {
        method: SfsMethod::Perspective,
        light: light_dir,
        light_slant_deg: slant,
        albedo: options.albedo,
        pixels: all.len(),
        shadow_pixels,
        too_bright_pixels: too_bright,
        singular_points: singular,
        iterations: sweeps,
        coarse_iterations: 0,
        restarts: 0,
        converged,
        mean_abs_residual,
        median_abs_curl: curl.median_abs_curl,
        seconds: started.elapsed().as_secs_f64(),
        assumptions,
        warnings,
        refinement,
        outline,
        outline_repair: None,
        occluding: tested.summary,
    };
    let swept_size = coarse.unwrap_or((w, h));
    Ok((
        SfsResult {
            depth,
            normals,
            p: pmap,
            q: qmap,
            residual,
            shadow,
            report,
        },
        swept_size,
    ))
}

/// Masks of more pixels than this are swept at half resolution (recursively) when the result
/// is refined: the refinement needs only a start on the right branch, and the sweeps cost
/// more per pixel than the refinement's steps from an upsampled start.
const SWEEP_AT_MOST: usize = 1 << 14;

/// The swept (or upsampled) ln-depth on every pixel of the mask, and what the sweeps did.
struct Swept {
    /// ln Z per pixel of the mask (NaN where no value could be filled).
    lnz: Vec<f64>,
    /// Whether the value was solved (not interpolated).
    known: Vec<bool>,
    /// Sweeps (at the resolution swept).
    sweeps: usize,
    converged: bool,
    last_change: f64,
    /// Lit pixels with no root of the scheme.
    grazing: usize,
    /// Contour pixels extrapolated.
    extrapolated: usize,
    /// Pixels left without a value.
    unfilled: usize,
    singular: usize,
    /// For an upsampled start: the size swept (half resolution, or less recursively).
    coarse: Option<(usize, usize)>,
    /// For an upsampled start: the refinement steps taken at the lower resolutions to make it.
    coarse_steps: Option<usize>,
    /// For an upsampled start: whether the refinement at the resolution below was discarded
    /// (the swept solution there was upsampled).
    coarse_discarded: bool,
}

/// For a large mask whose result is to be refined: the solution of the half-resolution image
/// (each 2×2 block of mask pixels averaged, the camera scaled), upsampled bilinearly in ln Z to
/// every pixel of `all`. `None` when the mask is small enough to sweep, refinement is off, a
/// start is given, or no 2×2 block lies in the mask.
fn coarse_start(
    image: &ScalarMap,
    mask: &Mask,
    camera: &Intrinsics,
    light: &PointLight,
    options: &PerspectiveOptions,
    all: &Unknowns,
) -> Result<Option<Swept>> {
    if options.refine.is_none() || options.start.is_some() || all.len() <= SWEEP_AT_MOST {
        return Ok(None);
    }
    let (w, h) = (image.width(), image.height());
    let (cw, ch) = (w / 2, h / 2);
    if cw < 2 || ch < 2 {
        return Ok(None);
    }
    let block = |c: usize, r: usize| {
        [
            (2 * c, 2 * r),
            (2 * c + 1, 2 * r),
            (2 * c, 2 * r + 1),
            (2 * c + 1, 2 * r + 1),
        ]
    };
    let cmask = Grid::from_fn(cw, ch, |c, r| {
        block(c, r).iter().all(|&(x, y)| *mask.at(x, y))
    });
    if cmask.count() == 0 {
        return Ok(None);
    }
    let cimage = Grid::from_fn(cw, ch, |c, r| {
        if *cmask.at(c, r) {
            block(c, r)
                .iter()
                .map(|&(x, y)| *image.at(x, y))
                .sum::<f32>()
                / 4.0
        } else {
            0.0
        }
    });
    // Block (c, r) covers pixels 2c and 2c + 1: its centre is pixel 2c + 0.5.
    let ccam = Intrinsics {
        fx: camera.fx / 2.0,
        fy: camera.fy / 2.0,
        cx: (camera.cx - 0.5) / 2.0,
        cy: (camera.cy - 0.5) / 2.0,
    };
    // Whatever fails at half resolution (a mask too thin to have lit blocks, say) is swept at
    // full resolution instead.
    let Ok((coarse, swept_size)) = solve_swept(&cimage, &cmask, &ccam, light, options) else {
        return Ok(None);
    };
    let clnz = coarse.depth.map(|&d| {
        let d = f64::from(d);
        if d.is_finite() && d > 0.0 {
            d.ln()
        } else {
            f64::NAN
        }
    });
    let mut lnz = vec![f64::NAN; all.len()];
    let mut known = vec![false; all.len()];
    for (k, &pix) in all.pixel.iter().enumerate() {
        let (c, r) = (pix as usize % w, pix as usize / w);
        let (mut sum, mut weight) = (0.0, 0.0);
        for (x, y, wt) in crate::sfs::pyramid::bilinear_from_half(c, r, cw, ch) {
            let v = *clnz.at(x, y);
            if v.is_finite() && wt > 0.0 {
                sum += wt * v;
                weight += wt;
            }
        }
        if weight > 1e-9 {
            lnz[k] = sum / weight;
            known[k] = true;
        }
    }
    // A part of the mask with no 2×2 block has no value at half resolution: sweep it all.
    if fill_harmonic(all, &mut lnz, &known) > 0 {
        return Ok(None);
    }
    let r = &coarse.report;
    Ok(Some(Swept {
        lnz,
        known,
        sweeps: r.iterations,
        converged: r.converged,
        last_change: 0.0,
        grazing: 0,
        extrapolated: 0,
        unfilled: 0,
        singular: r.singular_points,
        coarse: Some(swept_size),
        // A refinement discarded at the lower resolution changed nothing there.
        coarse_steps: Some(r.refinement.as_ref().map_or(0, |f| {
            f.coarse_iterations + if f.discarded { 0 } else { f.iterations }
        })),
        coarse_discarded: r.refinement.as_ref().is_some_and(|f| f.discarded),
    }))
}

/// Fills the unknown entries of `v` (on `u`'s pixels) with the harmonic interpolation of the
/// known ones (Gauss–Seidel to a change of 1e-10); returns how many stay unknown (in parts
/// with no known value).
fn fill_harmonic(u: &Unknowns, v: &mut [f64], known: &[bool]) -> usize {
    // Reachability first: breadth-first from the known values.
    let mut reached = known.to_vec();
    let mut queue: std::collections::VecDeque<usize> = (0..u.len()).filter(|&k| known[k]).collect();
    while let Some(k) = queue.pop_front() {
        for j in [u.left[k], u.right[k], u.up[k], u.down[k]] {
            if j != NONE && !reached[j as usize] {
                reached[j as usize] = true;
                v[j as usize] = v[k];
                queue.push_back(j as usize);
            }
        }
    }
    let free: Vec<usize> = (0..u.len()).filter(|&k| !known[k] && reached[k]).collect();
    for _ in 0..10_000 {
        let mut change = 0f64;
        for &k in &free {
            let (mut sum, mut count) = (0.0, 0.0);
            for j in [u.left[k], u.right[k], u.up[k], u.down[k]] {
                if j != NONE && reached[j as usize] {
                    sum += v[j as usize];
                    count += 1.0;
                }
            }
            let new = sum / count;
            change = change.max((new - v[k]).abs());
            v[k] = new;
        }
        if change < 1e-10 {
            break;
        }
    }
    reached.iter().filter(|&&r| !r).count()
}

/// The brightest an occluding contour can make outline pixel `px` at ln-depth `lnz`, its
/// outward direction in the image the unit (mx, my) (x right, y up): the
/// largest predicted brightness over the normals n(t) = √(1 − t²) n₀ + t·(towards the camera),
/// t ∈ (0, [`occluding::MAX_RIM_NZ`]], n₀ the normal at right angles to the pixel's ray whose
/// projection points along (mx, my) (the contour's normal under perspective). Infinite (no
/// bound) where the point or its distance to the light is not finite.
fn brightest_edge_on(
    model: &Model,
    intensity: f64,
    camera: &Intrinsics,
    px: &Pixel,
    lnz: f64,
    (mx, my): (f64, f64),
) -> f64 {
    let ray = Vector3::new(px.xi, px.eta, 1.0).normalize();
    let x = Vector3::new(px.xi, px.eta, 1.0) * lnz.exp();
    // Internal frame: x right, y down. The outward direction and the outline's tangent, as
    // displacements in the plane z = 1.
    let out = Vector3::new(mx / camera.fx, -my / camera.fy, 0.0);
    let tangent = Vector3::new(my / camera.fx, mx / camera.fy, 0.0);
    let mut n0 = ray.cross(&tangent);
    if n0.dot(&out) < 0.0 {
        n0 = -n0;
    }
    let Some(n0) = n0.try_normalize(1e-12) else {
        return f64::INFINITY;
    };
    let to_light = model.s - x;
    let d = to_light.norm();
    (0..=OUTLINE_SAMPLES)
        .map(|i| (occluding::MAX_RIM_NZ * i as f64 / OUTLINE_SAMPLES as f64).max(1e-3))
        .map(|t| {
            let n = n0 * (1.0 - t * t).sqrt() - ray * t;
            intensity * model.brightness.eval(n.dot(&to_light) / d) / (d * d)
        })
        .try_fold(0.0, |most: f64, b| b.is_finite().then(|| most.max(b)))
        // A depth whose point or distance is not finite bounds nothing: no contradiction.
        .unwrap_or(f64::INFINITY)
}

/// Values of n_z sampled by [`brightest_edge_on`].
const OUTLINE_SAMPLES: usize = 50;

#[cfg(test)]
mod tests {
    use super::*;

    /// The scheme's residual vanishes (to the discretisation's order) on the exact depth of a
    /// tilted plane lit by an oblique light.
    #[test]
    fn residual_vanishes_on_a_plane() {
        for s in [
            Vector3::zeros(),
            Vector3::new(100.0, -60.0, 0.0),
            Vector3::new(-80.0, 30.0, 20.0),
        ] {
            let model = Model {
                s,
                at_camera: s.norm() == 0.0,
                phi: 1e5,
                brightness: Brightness::Lambert(1.0),
                fx: 200.0,
                fy: 200.0,
            };
            // Plane through (0, 0, 250) with normal (0.3, −0.2, −1) (facing the camera).
            let nrm = Vector3::new(0.3, -0.2, -1.0).normalize();
            let depth = |xi: f64, eta: f64| {
                let w = Vector3::new(xi, eta, 1.0);
                250.0 * nrm.z / nrm.dot(&w)
            };
            let mut worst = 0f64;
            for (c, r) in [(10.0, 5.0), (-20.0, 30.0), (0.0, 0.0)] {
                let (xi, eta) = (c / 200.0, r / 200.0);
                let zz = depth(xi, eta);
                let x = Vector3::new(xi, eta, 1.0) * zz;
                let d = (s - x).norm();
                let cos = nrm.dot(&(s - x)) / d;
                let px = Pixel {
                    xi,
                    eta,
                    q: (1.0 + xi * xi + eta * eta).sqrt(),
                    i: 1e5 * cos / (d * d),
                };
                let z = |dc: f64, dr: f64| depth(xi + dc / 200.0, eta + dr / 200.0).ln();
                let nb = [
                    Some(z(-1.0, 0.0)),
                    Some(z(1.0, 0.0)),
                    Some(z(0.0, -1.0)),
                    Some(z(0.0, 1.0)),
                ];
                let (k, rhs) = model.terms(&px, zz.ln());
                let res = residual_at(&model, &px, zz.ln(), nb, k);
                println!("s {s:?} pixel ({c}, {r}): residual {res:.3e}, rhs {rhs:.4}, k {k:?}");
                worst = worst.max(res.abs() / rhs);
            }
            assert!(worst < 1e-3, "{worst}");
        }
    }

    /// On a linear ln-depth (equal one-sided differences), the upwind Hamiltonian is the exact
    /// sup: W(P) − k·P (the closed form), whatever the drift within the coercive range.
    #[test]
    fn upwind_hamiltonian_is_exact_on_linear_data() {
        for (xi, eta) in [(0.0, 0.0), (0.3, -0.2), (-0.5, 0.4)] {
            for p in [[0.0, 0.0], [2.0, -1.0], [-7.0, 3.0], [0.5, 12.0]] {
                for k in [[0.0, 0.0], [0.3, -0.2], [-0.4, 0.1]] {
                    let axes = [
                        Axis {
                            back: Some(p[0]),
                            fwd: Some(p[0]),
                        },
                        Axis {
                            back: Some(p[1]),
                            fwd: Some(p[1]),
                        },
                    ];
                    let got = upwind_hamiltonian(xi, eta, k, axes).unwrap();
                    let w = Vector3::new(p[0], p[1], 1.0 + xi * p[0] + eta * p[1]).norm();
                    let want = w - k[0] * p[0] - k[1] * p[1];
                    assert!(
                        (got - want).abs() < 1e-9 * (1.0 + want.abs()),
                        "{got} vs {want}"
                    );
                }
            }
        }
    }

    /// The upwind Hamiltonian is monotone: it grows with the backward differences and falls
    /// with the forward ones (Barles–Souganidis), checked on random differences.
    #[test]
    fn upwind_hamiltonian_is_monotone() {
        let mut seed = 7u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) * 10.0 - 5.0
        };
        for _ in 0..2000 {
            let (xi, eta) = (0.1 * rnd(), 0.1 * rnd());
            let k = [0.1 * rnd(), 0.1 * rnd()];
            let d = [rnd(), rnd(), rnd(), rnd()];
            let h = |d: [f64; 4]| {
                upwind_hamiltonian(
                    xi,
                    eta,
                    k,
                    [
                        Axis {
                            back: Some(d[0]),
                            fwd: Some(d[1]),
                        },
                        Axis {
                            back: Some(d[2]),
                            fwd: Some(d[3]),
                        },
                    ],
                )
                .unwrap()
            };
            let base = h(d);
            for (i, sign) in [(0, 1.0), (1, -1.0), (2, 1.0), (3, -1.0)] {
                let mut e = d;
                e[i] += 0.01;
                assert!(sign * (h(e) - base) >= -1e-12, "{d:?} {i}");
            }
        }
    }

    /// The tabulated brightness inverts itself, and the Lambertian one is ρc.
    #[test]
    fn brightness_inverts() {
        let lambert = Brightness::new(&Material::lambertian(), 0.8).unwrap();
        // The grey mix of white is 1 to f32 rounding.
        assert!((lambert.eval(0.5) - 0.4).abs() < 1e-7);
        assert!((lambert.inverse(lambert.eval(0.5)) - 0.5).abs() < 1e-12);
        let rough = Material {
            diffuse: Diffuse::OrenNayar { sigma: 0.4 },
            ..Material::lambertian()
        };
        let t = Brightness::new(&rough, 0.8).unwrap();
        for c in [0.05, 0.3, 0.77, 0.99] {
            assert!((t.inverse(t.eval(c)) - c).abs() < 1e-6, "{c}");
        }
    }
}
