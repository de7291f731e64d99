//! Shape from shading: depth and normals from one image, a known (or estimated) distant light and
//! albedo, through the [`ReflectanceMap`] E(x, y) = ρ R(p, q).
//!
//! One equation per pixel for two unknowns (p, q): the problem is ill-posed without more
//! information, and every method here says which information it adds.
//!
//! | method | adds | light | reference |
//! | --- | --- | --- | --- |
//! | [`SfsMethod::Horn`] | smoothness (decreasing to a small floor, 1e-4 by default) and integrability; occluding-contour normals | any in front, any BRDF | Horn, "Height and gradient from shading", IJCV 5(1) 1990 |
//! | [`SfsMethod::TsaiShah`] | linearisation of R in depth, one Newton step per pixel and sweep | oblique, any BRDF | Tsai & Shah, "Shape from shading using linear approximation", IVC 12(8) 1994 |
//! | [`SfsMethod::FastMarching`] | viscosity solution of the eikonal equation from the singular (brightest) points | at the viewer, Lambertian | Kimmel & Sethian, "Optimal algorithm for shape from shading and path planning", JMIV 14 2001 |
//! | [`SfsMethod::Perspective`] ([`perspective::solve`]) | a pinhole camera and a near point light whose inverse-square fall-off tells near from far: well posed, no smoothness or boundary prior | a point light at a known position (any isotropic BRDF when at the camera centre, Lambertian elsewhere) | Prados & Faugeras, "Shape from shading: a well-posed problem?", CVPR 2005 |
//!
//! When the light or albedo is not known, [`estimate::estimate_light`] estimates both from the
//! image statistics (after Zheng & Chellappa, PAMI 1991).
//!
//! # What can go wrong, and how it is reported
//! - **Convex/concave ambiguity.** R(p, q) = R(−p, −q) for a light at the viewer, and nearly so
//!   for any light near it: a bump and a dent look alike. Horn's method chooses by its boundary
//!   (occluding contours: the object is convex there) and by its start (a convex "balloon" inside
//!   the mask); fast marching makes every singular point a local maximum. Both say so in
//!   [`SfsReport::assumptions`].
//! - **Frontal light for linear methods.** Tsai–Shah's Newton step divides by ∂R/∂z, which is 0
//!   for a flat start under a light at the viewer: it refuses lights within
//!   [`FRONTAL_SLANT_DEG`] of the view ([`crate::Error::InvalidParameter`]), and fast marching
//!   refuses lights farther than that.
//! - **Unknown or wrong albedo.** Brightness above the albedo (R > 1) is impossible; the count of
//!   such pixels is reported and warned about, and the data-fit residual E/ρ − R is exported.
//! - **Shadows.** Pixels darker than `shadow_level` carry no slope information; they are
//!   counted, and shaped by the neighbours only (Horn) or left to the Newton step's prior
//!   (Tsai–Shah).
//! - A method that stops without converging says so in [`SfsReport::converged`].

pub mod estimate;
mod fast_marching;
mod horn;
mod line_search;
pub mod occluding;
pub mod outline_repair;
pub mod perspective;
pub(crate) mod pyramid;
pub mod reflectance_map;
pub mod start;
mod tsai_shah;

use crate::error::{Error, Result};
use crate::grid::{Grid, Mask, NormalMap, ScalarMap};
use crate::integrate::sparse::{NONE, Unknowns};
use crate::sfs::reflectance_map::{ReflectanceMap, normal_from_gradient};
use nalgebra::Vector3;
use serde::Serialize;
use std::time::Instant;

/// Lights closer than this to the viewing direction (degrees) count as frontal.
pub const FRONTAL_SLANT_DEG: f64 = 5.0;
/// Default final smoothness weight λ of Horn's method. Fixed rather than grown with the image's
/// noise: larger weights lower the normal error of noisy images and raise the depth error under
/// an oblique light (docs/shape-from-shading.md, "Smoothness against image noise").
pub const DEFAULT_SMOOTHNESS: f64 = 1e-4;
/// Default relative brightness E/ρ below which a pixel is in shadow.
pub const DEFAULT_SHADOW_LEVEL: f64 = 0.01;
/// Fraction of pixels brighter than the albedo above which the albedo is reported as wrong.
const TOO_BRIGHT_WARN: f64 = 0.01;
/// Mean |E/ρ − R| above which the shading is reported as not fitting.
const POOR_FIT: f64 = 0.02;
/// Angle (degrees) by which a normal beside the mask's outline may turn from the outline's
/// outward direction, in the image plane, and still agree with an occluding contour there: the
/// outward direction is taken from the pixel's eight neighbours, which resolve directions
/// 45° apart, so a smaller angle can be the outline's quantisation alone.
pub const OUTLINE_TOLERANCE_DEG: f64 = 45.0;
/// Fraction of the outline's pixels turned by more than [`OUTLINE_TOLERANCE_DEG`] above which a
/// result that assumed an occluding boundary is reported as contradicting it. Chosen on rendered
/// scenes (sphere, ellipsoid, vase, bust; Lambertian and Oren–Nayar σ = 0.4; frontal, 30° and
/// 40° lights; 32²–128²): solves within 6° of the truth reach at most 0.18 (the vase, whose cut
/// ends are not occluding), solves under an oblique light more than 12.5° off at least 0.35
/// (docs/shape-from-shading.md, "Does the result honour the occluding boundary?"). The
/// perspective method warns at the same fraction: over its rendered solves at 64²–128²,
/// lights 20°–40° off the axis, those within 5° and 5% reached at most 0.13.
pub const OUTLINE_MISALIGNED_WARN: f64 = 0.25;
/// Largest gradient magnitude any method returns (a slope of 89.4°).
pub(crate) const MAX_GRADIENT: f64 = 100.0;

/// Relative damping of the Gauss–Newton equations of Horn's method and of the perspective
/// refinement (see [`gauss_newton_damping`]).
const GAUSS_NEWTON_DAMPING: f64 = 1e-6;

/// What is added to a diagonal entry `d` of Gauss–Newton normal equations whose diagonal has
/// the mean `mean`: 10⁻⁶ of each, which keeps the equations definite where only the smoothness
/// reaches an unknown and leaves the step otherwise unchanged.
pub(crate) fn gauss_newton_damping(d: f64, mean: f64) -> f64 {
    GAUSS_NEWTON_DAMPING * d + GAUSS_NEWTON_DAMPING * mean.max(f64::MIN_POSITIVE)
}

/// A shape-from-shading method (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SfsMethod {
    /// Horn 1990: gradients and height with integrability, smoothness relaxed to a small floor.
    Horn,
    /// Tsai–Shah 1994: per-pixel Newton iteration of the depth-linearised brightness equation.
    TsaiShah,
    /// Kimmel–Sethian 2001: fast marching for a light at the viewer.
    FastMarching,
    /// Prados–Faugeras 2005: perspective camera, near point light with fall-off
    /// ([`perspective::solve`]; not a method of the distant-light [`shape_from_shading`]).
    Perspective,
}

impl SfsMethod {
    /// Every method of the distant-light, orthographic model ([`shape_from_shading`]).
    pub const ALL: [SfsMethod; 3] = [
        SfsMethod::Horn,
        SfsMethod::TsaiShah,
        SfsMethod::FastMarching,
    ];

    /// The name used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            SfsMethod::Horn => "horn",
            SfsMethod::TsaiShah => "tsai-shah",
            SfsMethod::FastMarching => "fast-marching",
            SfsMethod::Perspective => "perspective",
        }
    }

    /// Whether the method can solve under `rmap`'s light and BRDF, and if not, why.
    pub fn applicable(self, rmap: &ReflectanceMap) -> std::result::Result<(), String> {
        let slant = rmap.slant_deg();
        match self {
            SfsMethod::Horn => Ok(()),
            SfsMethod::TsaiShah if slant < FRONTAL_SLANT_DEG => Err(format!(
                "the light is {slant:.1}° from the viewing direction: the linear Tsai–Shah \
                 method has no slope information from a flat start under a frontal light \
                 (∂R/∂z = 0); use horn or fast-marching"
            )),
            SfsMethod::TsaiShah => Ok(()),
            SfsMethod::FastMarching if slant > FRONTAL_SLANT_DEG => Err(format!(
                "the light is {slant:.1}° from the viewing direction: fast marching solves the \
                 eikonal equation of a light at the viewer (within {FRONTAL_SLANT_DEG}°); use \
                 horn or tsai-shah"
            )),
            SfsMethod::FastMarching if !rmap.is_lambertian() => Err(
                "fast marching needs the Lambertian reflectance map (its eikonal equation is \
                 |∇z|² = 1/E² − 1)"
                    .to_string(),
            ),
            SfsMethod::FastMarching => Ok(()),
            SfsMethod::Perspective => Err(
                "the perspective method needs a camera and a light's position, not a distant \
                 light: use sfs::perspective::solve"
                    .to_string(),
            ),
        }
    }
}

/// What the edge of the mask is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Boundary {
    /// The mask's edge is an occluding contour (the surface turns away from the camera there):
    /// Horn's method starts from a convex surface over the mask, rising steeply from its edge;
    /// where the image shows that the edge is none (brighter than an edge-on surface can be,
    /// [`occluding`]), the start rises from the rest of it, and the result warns.
    #[default]
    Occluding,
    /// No information: the surface simply continues beyond the mask; Horn's method starts from
    /// a plane.
    Free,
}

/// Shape-from-shading options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SfsOptions {
    /// The method.
    pub method: SfsMethod,
    /// What the mask's edge is (Horn).
    pub boundary: Boundary,
    /// Iteration limit (0: the method's default).
    pub max_iterations: usize,
    /// Final smoothness weight λ of Horn's method (it starts at 0.1, or at this if larger, and
    /// is halved every iteration down to this).
    pub smoothness: f64,
    /// Relative brightness E/ρ below which a pixel is in shadow.
    pub shadow_level: f64,
    /// Horn: solve at lower resolutions first (2×2 block means, while a level keeps 3 000
    /// pixels) and start from that solution, refined at the final λ (default); `false` runs the
    /// whole continuation in λ at full resolution only.
    pub coarse_to_fine: bool,
    /// Horn with an occluding boundary: when the result contradicts that boundary and the image
    /// is too small for a coarse-to-fine start, solve it again upsampled 2× and return that
    /// result if it honours the boundary ([`outline_repair`]; default `true`).
    pub outline_repair: bool,
    /// Horn: repeat the continuation in λ from its own result while that converges, lowers
    /// the energy and does not contradict the occluding boundary (at most
    /// [`horn::MAX_RESTARTS`] times; default `true`); `false` runs it once.
    pub restarts: bool,
}

impl Default for SfsOptions {
    fn default() -> Self {
        SfsOptions {
            method: SfsMethod::Horn,
            boundary: Boundary::Occluding,
            max_iterations: 0,
            smoothness: DEFAULT_SMOOTHNESS,
            shadow_level: DEFAULT_SHADOW_LEVEL,
            coarse_to_fine: true,
            outline_repair: true,
            restarts: true,
        }
    }
}

/// What a shape-from-shading run did, assumed and found.
#[non_exhaustive]
#[derive(Debug, Clone, Serialize)]
pub struct SfsReport {
    /// The method.
    pub method: SfsMethod,
    /// The unit light direction used.
    pub light: [f64; 3],
    /// Angle of the light from the viewing direction, degrees.
    pub light_slant_deg: f64,
    /// The albedo used (brightness of a surface facing the light).
    pub albedo: f64,
    /// Pixels solved.
    pub pixels: usize,
    /// Pixels darker than the shadow level (perspective: pixels whose depth was not fitted to
    /// their own brightness, see [`perspective::solve`]).
    pub shadow_pixels: usize,
    /// Pixels brighter than the albedo allows (E/ρ > 1).
    pub too_bright_pixels: usize,
    /// Singular points (E/ρ ≈ 1) used as sources (fast marching).
    pub singular_points: usize,
    /// Iterations run (perspective: sweeps, at the resolution swept; the refinement's steps are
    /// in `refinement`).
    pub iterations: usize,
    /// Iterations run at lower resolutions to make the start (Horn's coarse to fine, each
    /// level on its own limit; 0 otherwise: the perspective refinement's are in `refinement`).
    pub coarse_iterations: usize,
    /// Horn: how many times the continuation in λ was repeated from its own result and kept
    /// (each converged and lowered the energy; counted in the iterations above). 0 otherwise.
    pub restarts: usize,
    /// Whether the iteration met its tolerance (perspective: the sweeps').
    pub converged: bool,
    /// Mean |E/ρ − R(p, q)| over lit pixels: how well the result explains the image.
    pub mean_abs_residual: f64,
    /// Median |curl| of the returned gradient field (0 for an integrable field).
    pub median_abs_curl: f64,
    /// Seconds spent.
    pub seconds: f64,
    /// What the method assumed to choose one surface among those that explain the image.
    pub assumptions: Vec<String>,
    /// What looks wrong.
    pub warnings: Vec<String>,
    /// The variational refinement's report (perspective only; `None` when not run).
    pub refinement: Option<perspective::RefineReport>,
    /// How well the normals beside the mask's outline agree with an occluding contour there
    /// (Horn's method under [`Boundary::Occluding`], and the perspective method, which takes
    /// the outline for an occluding contour), when the outline is inside the image; `None`
    /// otherwise.
    pub outline: Option<OutlineAgreement>,
    /// What the outline repair did, when it was tried ([`outline_repair`]; Horn only).
    pub outline_repair: Option<outline_repair::OutlineRepair>,
    /// The outline tested against the image: where it is brighter than an occluding contour
    /// can be ([`occluding`]; Horn under [`Boundary::Occluding`], before solving, when the
    /// image's noise could be measured; the perspective method, at the depth its result gives
    /// each outline pixel), when the outline is inside the image.
    pub occluding: Option<occluding::OccludingTest>,
}

/// Whether a result honours the occluding boundary it assumed: at an occluding contour the
/// surface turns away from the camera, so a normal beside the mask's outline points outwards,
/// along the outline's normal in the image (Ikeuchi and Horn, "Numerical shape from shading and
/// occluding boundaries", Artificial Intelligence 17, 1981). A solve that settled on another
/// surface explaining the image as well (a rough surface's flatter reflectance map, a small
/// image) turns those normals elsewhere, while its residual stays as low as a correct solve's.
#[non_exhaustive]
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct OutlineAgreement {
    /// Mask pixels with a neighbour (of eight) outside the mask but inside the image (the
    /// image's border is not an outline), except where the offsets to those neighbours cancel
    /// (a line one pixel wide has no outward direction).
    pub pixels: usize,
    /// Mean angle, in the image plane, between those pixels' normals and the outline's outward
    /// direction (the sum of the offsets to the outside neighbours), degrees.
    pub mean_angle_deg: f64,
    /// Fraction of them turned by more than [`OUTLINE_TOLERANCE_DEG`].
    pub misaligned_fraction: f64,
}

/// The first part of the warning that a result contradicts the occluding boundary it assumed
/// (`o.misaligned_fraction` above [`OUTLINE_MISALIGNED_WARN`]): what was measured and its two
/// readings, `settled` naming what may have settled on another surface ("the iteration",
/// "the solution"). A sentence fragment: each method finishes it with why its result can take
/// another surface and what to try.
pub(crate) fn outline_contradicted_warning(o: &OutlineAgreement, settled: &str) -> String {
    format!(
        "the result contradicts the occluding boundary it assumed: {:.0}% of the {} pixels \
         beside the mask's outline have normals turned more than {OUTLINE_TOLERANCE_DEG:.0}° \
         from it (mean {:.1}°). Either the outline is not an occluding contour there, or \
         {settled} settled on another surface that explains the image as well",
        100.0 * o.misaligned_fraction,
        o.pixels,
        o.mean_angle_deg,
    )
}

/// [`OutlineAgreement`] of `normals` over the unknowns `u`, leaving out the unknowns flagged in
/// `exclude` (per unknown, or empty: the outline's pixels that the image says are not on an
/// occluding contour, [`occluding`]); `None` when no other unknown touches a pixel outside the
/// mask inside the image.
pub(crate) fn outline_agreement(
    u: &Unknowns,
    normals: &NormalMap,
    exclude: &[bool],
) -> Option<OutlineAgreement> {
    let (w, h) = (u.w, u.h);
    let inside = u.inside();
    let (mut pixels, mut sum, mut misaligned) = (0usize, 0.0, 0usize);
    for (k, &p) in u.pixel.iter().enumerate() {
        if exclude.get(k).copied().unwrap_or(false) {
            continue;
        }
        let (x, y) = ((p as usize % w) as i64, (p as usize / w) as i64);
        // Outward, x right and y up (rows run down).
        let (mut ox, mut oy) = (0.0f64, 0.0f64);
        for dy in -1i64..=1 {
            for dx in -1i64..=1 {
                let (a, b) = (x + dx, y + dy);
                if (dx, dy) != (0, 0)
                    && (0..w as i64).contains(&a)
                    && (0..h as i64).contains(&b)
                    && !inside[b as usize * w + a as usize]
                {
                    ox += dx as f64;
                    oy -= dy as f64;
                }
            }
        }
        let out = ox.hypot(oy);
        let n = normals.data()[p as usize].cast::<f64>();
        if out == 0.0 || !n.iter().all(|v| v.is_finite()) {
            continue;
        }
        // A normal facing the camera has no direction in the image: 90°, as a random one's mean.
        let along = n.x.hypot(n.y);
        let angle = if along > 0.0 {
            ((n.x * ox + n.y * oy) / (along * out))
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees()
        } else {
            90.0
        };
        pixels += 1;
        sum += angle;
        if angle > OUTLINE_TOLERANCE_DEG {
            misaligned += 1;
        }
    }
    (pixels > 0).then(|| OutlineAgreement {
        pixels,
        mean_angle_deg: sum / pixels as f64,
        misaligned_fraction: misaligned as f64 / pixels as f64,
    })
}

/// The result of [`shape_from_shading`].
#[non_exhaustive]
#[derive(Debug, Clone)]
pub struct SfsResult {
    /// Height towards the camera (pixel units), zero-mean per connected part; NaN outside.
    pub depth: ScalarMap,
    /// Unit normals; NaN outside.
    pub normals: NormalMap,
    /// p = ∂z/∂x; NaN outside.
    pub p: ScalarMap,
    /// q = ∂z/∂y (y up); NaN outside.
    pub q: ScalarMap,
    /// E/ρ − R(p, q) per pixel; NaN outside.
    pub residual: ScalarMap,
    /// Pixels in shadow.
    pub shadow: Mask,
    /// What was done.
    pub report: SfsReport,
}

/// The normalised image on the mask's pixels, with their neighbourhoods.
pub(crate) struct Shading<'a> {
    pub u: Unknowns,
    /// E/ρ per unknown (clamped to [0, 1]).
    pub e: Vec<f64>,
    /// In shadow, per unknown.
    pub shadow: Vec<bool>,
    pub rmap: &'a ReflectanceMap,
    pub options: &'a SfsOptions,
    /// Told of each iteration (iterative methods) or of each pixel fixed (fast marching).
    pub progress: &'a dyn crate::progress::Progress,
    /// A start surface given by the caller, per unknown (Horn only: [`shape_from_shading_from`]).
    pub start: Option<Vec<f64>>,
    /// The margin of the test of the outline against the image ([`occluding`]), when the
    /// method assumes the outline is an occluding contour; `None`: not tested.
    pub occluding_tolerance: Option<f64>,
}

impl Shading<'_> {
    /// The test of the outline against the image ([`occluding::test`]); untested (no summary,
    /// nothing flagged) without [`Self::occluding_tolerance`].
    pub(crate) fn outline(&self) -> occluding::Outline {
        match self.occluding_tolerance {
            Some(tolerance) => occluding::test(&self.u, &self.e, self.rmap, tolerance),
            None => occluding::Outline {
                summary: None,
                contradicted: vec![false; self.u.len()],
            },
        }
    }
}

/// What a solver returns, per unknown.
pub(crate) struct Solved {
    pub p: Vec<f64>,
    pub q: Vec<f64>,
    /// Depth.
    pub z: Vec<f64>,
    /// Normals, when the method knows better than (p, q) (fast marching near the contour).
    pub normals: Option<Vec<Vector3<f64>>>,
    pub iterations: usize,
    /// Iterations at lower resolutions that made the start (Horn's coarse to fine).
    pub coarse_iterations: usize,
    /// Repeats of Horn's continuation in λ from its own result that were kept.
    pub restarts: usize,
    pub converged: bool,
    pub singular: usize,
    pub assumptions: Vec<String>,
    /// What the method itself found wrong (added to the report's warnings).
    pub warnings: Vec<String>,
}

/// Shape from shading of `image` (linear brightness) inside `mask`, for a surface of albedo
/// `albedo` (the brightness of a surface facing the light) under the light and BRDF of `rmap`.
///
/// # Errors
/// [`Error::InvalidParameter`] when the sizes differ, the mask is empty, the image holds a
/// non-finite value in the mask, the albedo is not finite and > 0, the light is not in front of
/// the surface, or the method cannot solve under this light (see [`SfsMethod::applicable`]).
///
/// # Example
/// ```
/// use photostereo::sfs::reflectance_map::ReflectanceMap;
/// use photostereo::synth::scene::{Albedo, Scene};
/// use photostereo::sfs::{shape_from_shading, SfsOptions};
/// use photostereo::nalgebra::Vector3;
/// // A sphere lit from the upper right, rendered with its closed-form reflectance map.
/// let truth = Scene::sphere(48, 19.0, Albedo::Constant(1.0)).height_field();
/// let rmap = ReflectanceMap::lambertian(Vector3::new(0.4, 0.3, 0.87))?;
/// let image = truth.normals.map(|n| {
///     let n = n.cast::<f64>();
///     if n.x.is_nan() { 0.0 } else { rmap.eval(-n.x / n.z, -n.y / n.z) as f32 }
/// });
/// let r = shape_from_shading(&image, &truth.mask, &rmap, 1.0, &SfsOptions::default())?;
/// let err = photostereo::eval::metrics::angular_errors(&r.normals, &truth.normals, &truth.mask)?;
/// assert!(err.mean_deg < 5.0, "{}", err.mean_deg);
/// # Ok::<(), photostereo::Error>(())
/// ```
pub fn shape_from_shading(
    image: &ScalarMap,
    mask: &Mask,
    rmap: &ReflectanceMap,
    albedo: f64,
    options: &SfsOptions,
) -> Result<SfsResult> {
    shape_from_shading_with_progress(image, mask, rmap, albedo, options, &crate::progress::Silent)
}

/// [`shape_from_shading`], telling `progress` of each iteration (iterative methods, up to
/// the iteration limit) or of each pixel fixed (fast marching): runs on large images take
/// minutes.
///
/// # Errors
/// As [`shape_from_shading`].
pub fn shape_from_shading_with_progress(
    image: &ScalarMap,
    mask: &Mask,
    rmap: &ReflectanceMap,
    albedo: f64,
    options: &SfsOptions,
    progress: &dyn crate::progress::Progress,
) -> Result<SfsResult> {
    solve_image(image, mask, rmap, albedo, options, None, progress)
}

/// [`shape_from_shading_with_progress`] from a given surface: Horn's method refines `start`
/// (heights towards the camera in pixels, as [`SfsResult::depth`] gives them; any offset)
/// instead of starting from the convex or plane surface of [`Boundary`], by Gauss–Newton
/// steps at the final smoothness alone: no continuation in λ, no coarse-to-fine start, no
/// repeats and no outline repair, since each of those exists to find a basin that the start
/// now names. The result is the minimum of the energy nearest `start` (a depth map from a
/// sensor, stereo or photometric stereo whose detail the shading is to refine, or an earlier
/// result).
///
/// Horn's energy has several minima on most shapes under an oblique light, and the default
/// start does not always lead to the right one (a frame-filling bas-relief at 30°: 11° off),
/// while the iteration started near the true surface stays near it: what the start is worth
/// decides what the result is worth.
///
/// A start at another resolution or with holes (a depth sensor's) is brought to the image's
/// grid first by [`start::prepare_start`].
///
/// # Errors
/// As [`shape_from_shading`]; [`Error::DimensionMismatch`] when `start` is not of the image's
/// size; [`Error::InvalidParameter`] (`start`) when a pixel of the mask has no finite start
/// height, or (`method`) for a method other than Horn's.
pub fn shape_from_shading_from(
    image: &ScalarMap,
    mask: &Mask,
    rmap: &ReflectanceMap,
    albedo: f64,
    options: &SfsOptions,
    start: &ScalarMap,
    progress: &dyn crate::progress::Progress,
) -> Result<SfsResult> {
    solve_image(image, mask, rmap, albedo, options, Some(start), progress)
}

/// The solve behind [`shape_from_shading_with_progress`] and [`shape_from_shading_from`].
fn solve_image(
    image: &ScalarMap,
    mask: &Mask,
    rmap: &ReflectanceMap,
    albedo: f64,
    options: &SfsOptions,
    given_start: Option<&ScalarMap>,
    progress: &dyn crate::progress::Progress,
) -> Result<SfsResult> {
    let start = Instant::now();
    image.check_same_size(mask, "mask")?;
    if !(albedo.is_finite() && albedo > 0.0) {
        return Err(Error::param(
            "albedo",
            format!("{albedo} must be finite and > 0"),
        ));
    }
    check_shadow_level(options.shadow_level)?;
    if !(options.smoothness.is_finite() && options.smoothness >= 0.0) {
        return Err(Error::param(
            "smoothness",
            format!("{} must be finite and ≥ 0", options.smoothness),
        ));
    }
    // A surface facing the light is at its brightest for every reflectance the crate has;
    // where even it is dark (a pure mirror, whose delta lobe the map leaves out), the image
    // holds no shading.
    let l = rmap.light();
    let facing = if l.z > 0.0 {
        rmap.eval(-l.x / l.z, -l.y / l.z)
    } else {
        1.0
    };
    if facing.is_nan() || facing <= 0.0 {
        return Err(Error::param(
            "material",
            "its reflectance map is dark everywhere (a pure mirror's reflection is a delta the \
             map leaves out): shape from shading needs a diffuse or glossy reflectance",
        ));
    }
    if rmap.light().z <= 0.0 {
        return Err(Error::param(
            "light",
            format!(
                "direction ({:.3}, {:.3}, {:.3}) is at or behind the horizon: shape from shading \
                 needs a light in front of the surface (z > 0)",
                rmap.light().x,
                rmap.light().y,
                rmap.light().z
            ),
        ));
    }
    options
        .method
        .applicable(rmap)
        .map_err(|why| Error::param("method", why))?;
    if mask.count() == 0 {
        return Err(Error::param("mask", "is empty: no pixel to solve"));
    }
    // The first pixel of the mask where `map` is not finite: (column, row, value).
    let unfinite = |map: &ScalarMap| {
        (0..mask.len())
            .find(|&i| mask.data()[i] && !map.data()[i].is_finite())
            .map(|i| (i % map.width(), i / map.width(), map.data()[i]))
    };
    if let Some((x, y, v)) = unfinite(image) {
        return Err(Error::param(
            "image",
            format!("pixel ({x}, {y}) inside the mask is {v}: mask it out or repair the image"),
        ));
    }
    if let Some(z) = given_start {
        image.check_same_size(z, "start")?;
        if let Some((x, y, v)) = unfinite(z) {
            return Err(Error::param(
                "start",
                format!(
                    "pixel ({x}, {y}) inside the mask has no finite height ({v}): the start \
                     surface must cover the mask"
                ),
            ));
        }
        if options.method != SfsMethod::Horn {
            return Err(Error::param(
                "method",
                format!(
                    "{} does not refine a given start surface; horn does",
                    options.method.name()
                ),
            ));
        }
    }
    let u = Unknowns::new(mask);
    let z0 = given_start.map(|z| {
        u.pixel
            .iter()
            .map(|&pix| f64::from(z.data()[pix as usize]))
            .collect()
    });
    let mut too_bright = 0usize;
    let e: Vec<f64> = u
        .pixel
        .iter()
        .map(|&pix| {
            let v = f64::from(image.data()[pix as usize]) / albedo;
            if v > 1.0 + 1e-3 {
                too_bright += 1;
            }
            v.clamp(0.0, 1.0)
        })
        .collect();
    let shadow: Vec<bool> = e.iter().map(|&v| v <= options.shadow_level).collect();
    // Horn's default boundary takes the outline for an occluding contour: tested against the
    // image, three times its noise (over the albedo) above what a contour could show.
    let occluding_tolerance = (options.method == SfsMethod::Horn
        && options.boundary == Boundary::Occluding)
        .then(|| crate::ps::noise::image_noise(image.data(), image.width(), mask).sigma)
        .filter(|sigma| sigma.is_finite())
        .map(|sigma| (3.0 * f64::from(sigma) / albedo).max(options.shadow_level));
    let shading = Shading {
        u,
        e,
        shadow,
        rmap,
        options,
        progress,
        start: z0,
        occluding_tolerance,
    };
    let (solved, repair) = match options.method {
        SfsMethod::Horn => outline_repair::solve(&shading)?,
        SfsMethod::TsaiShah => (tsai_shah::solve(&shading)?, None),
        SfsMethod::FastMarching => (fast_marching::solve(&shading)?, None),
        SfsMethod::Perspective => {
            return Err(Error::param(
                "method",
                "perspective is solved by sfs::perspective::solve",
            ));
        }
    };
    finish(shading, solved, repair, albedo, too_bright, start)
}

/// Checks a shadow level: finite, in [0, 1).
pub(crate) fn check_shadow_level(level: f64) -> Result<()> {
    if level.is_finite() && (0.0..1.0).contains(&level) {
        Ok(())
    } else {
        Err(Error::param(
            "shadow-level",
            format!("{level} is outside [0, 1)"),
        ))
    }
}

/// Depth, normals, residual and report from a solver's per-unknown output.
fn finish(
    s: Shading,
    solved: Solved,
    repair: Option<outline_repair::OutlineRepair>,
    albedo: f64,
    too_bright: usize,
    start: Instant,
) -> Result<SfsResult> {
    let (w, h) = (s.u.w, s.u.h);
    let n = s.u.len();
    let p_map = s.u.to_map(&solved.p);
    let q_map = s.u.to_map(&solved.q);
    let depth = {
        let mut z = solved.z;
        s.u.zero_mean_parts(&mut z);
        s.u.to_map(&z)
    };
    let mut normals = Grid::new(w, h, Vector3::repeat(f32::NAN));
    let mut residual = Grid::new(w, h, f32::NAN);
    let mut shadow = Grid::new(w, h, false);
    let (mut abs_sum, mut lit) = (0.0, 0usize);
    for k in 0..n {
        let pix = s.u.pixel[k] as usize;
        let nk = match &solved.normals {
            Some(v) => v[k],
            None => normal_from_gradient(solved.p[k], solved.q[k]),
        };
        normals.data_mut()[pix] = nk.cast::<f32>();
        let r = s.rmap.eval(solved.p[k], solved.q[k]);
        let res = s.e[k] - r;
        residual.data_mut()[pix] = res as f32;
        shadow.data_mut()[pix] = s.shadow[k];
        if !s.shadow[k] {
            abs_sum += res.abs();
            lit += 1;
        }
    }
    let mean_abs_residual = if lit > 0 { abs_sum / lit as f64 } else { 0.0 };
    let curl = crate::ps::normals::integrability(&p_map, &q_map).summary;
    let shadow_pixels = s.shadow.iter().filter(|&&b| b).count();
    let mut warnings = Vec::new();
    if too_bright as f64 > TOO_BRIGHT_WARN * n as f64 {
        warnings.push(format!(
            "{too_bright} of {n} pixels are brighter than the albedo {albedo:.4} allows \
             (E/ρ > 1): the albedo (or the light's intensity) is too low; they were clipped"
        ));
    }
    if mean_abs_residual > POOR_FIT {
        warnings.push(format!(
            "the result explains the image poorly (mean |E/ρ − R| = {mean_abs_residual:.3}): \
             the light direction, the albedo or the reflectance model is probably wrong"
        ));
    }
    if shadow_pixels as f64 > 0.3 * n as f64 {
        warnings.push(format!(
            "{shadow_pixels} of {n} pixels are in shadow: their shape comes from their \
             neighbours only"
        ));
    }
    if !solved.converged {
        warnings.push(format!(
            "{} stopped after {} iterations without converging",
            s.options.method.name(),
            solved.iterations
        ));
    }
    let tested = s.outline();
    if let Some(t) = tested.summary
        && t.fraction > occluding::CONTRADICTED_WARN
    {
        warnings.push(format!(
            "the mask's outline is not an occluding contour along {:.0}% of it ({} of {} \
             pixels are brighter than a surface turning away from the view can be): there the \
             mask cuts across the surface (a cut end, a foot on a table), nothing fixes the \
             shape at that edge, and the result is probably wrong near it",
            100.0 * t.fraction,
            t.contradicted,
            t.pixels
        ));
    }
    let outline = (s.options.method == SfsMethod::Horn
        && s.options.boundary == Boundary::Occluding)
        .then(|| outline_agreement(&s.u, &normals, &tested.contradicted))
        .flatten();
    if let Some(o) = outline
        && o.misaligned_fraction > OUTLINE_MISALIGNED_WARN
    {
        warnings.push(format!(
            "{} (a rough or small image admits several); the shape is probably wrong: try the \
             perspective method with the light's position, or a larger image{}",
            outline_contradicted_warning(&o, "the iteration"),
            match repair.and_then(|r| r.upsampled) {
                Some(u) if u.misaligned_fraction <= OUTLINE_MISALIGNED_WARN => {
                    " (solved again upsampled 2×, it honoured the boundary but did not converge, \
                     so it was not kept)"
                        .to_string()
                }
                Some(u) => format!(
                    " (solved again upsampled 2×, it contradicted the boundary too: {:.0}% \
                     misaligned)",
                    100.0 * u.misaligned_fraction
                ),
                None if repair.is_some() => {
                    " (solving it again upsampled 2× did not give a result)".to_string()
                }
                None => String::new(),
            }
        ));
    }
    warnings.extend(solved.warnings);
    let light = s.rmap.light();
    let report = SfsReport {
        method: s.options.method,
        light: [light.x, light.y, light.z],
        light_slant_deg: s.rmap.slant_deg(),
        albedo,
        pixels: n,
        shadow_pixels,
        too_bright_pixels: too_bright,
        singular_points: solved.singular,
        iterations: solved.iterations,
        coarse_iterations: solved.coarse_iterations,
        restarts: solved.restarts,
        converged: solved.converged,
        mean_abs_residual,
        median_abs_curl: curl.median_abs_curl,
        seconds: start.elapsed().as_secs_f64(),
        assumptions: solved.assumptions,
        warnings,
        refinement: None,
        outline,
        outline_repair: repair,
        occluding: tested.summary,
    };
    Ok(SfsResult {
        depth,
        normals,
        p: p_map,
        q: q_map,
        residual,
        shadow,
        report,
    })
}

/// Euclidean distance from each unknown's centre to the nearest pixel centre outside the mask
/// but inside the image (the image border is not an edge), minus ½ (the contour lies half-way):
/// Felzenszwalb & Huttenlocher's separable exact transform ("Distance transforms of sampled
/// functions", Theory of Computing 2012). With unknowns flagged in `exclude` (per unknown, or
/// empty), an outside pixel counts only when one of its eight neighbours is an unflagged
/// unknown: the distance is to the rest of the outline (the flagged pixels are where the image
/// says it is no occluding contour, [`occluding`]); a part of the mask whose whole outline is
/// flagged then takes its distances from another part's, across the background. `None` when
/// no pixel counts.
pub(crate) fn distance_to_edge(u: &Unknowns, exclude: &[bool]) -> Option<Vec<f64>> {
    let (w, h) = (u.w, u.h);
    let inside = u.inside();
    if inside.iter().all(|&b| b) {
        return None;
    }
    const INF: f64 = 1e20;
    let mut f: Vec<f64> = inside.iter().map(|&b| if b { INF } else { 0.0 }).collect();
    if exclude.iter().any(|&b| b) {
        let mut kept = vec![false; w * h];
        for (k, &p) in u.pixel.iter().enumerate() {
            kept[p as usize] = !exclude[k];
        }
        let (wi, hi) = (w as i64, h as i64);
        for y in 0..hi {
            for x in 0..wi {
                let q = (y * wi + x) as usize;
                if inside[q] {
                    continue;
                }
                let next_to_kept = (-1..=1).any(|dy: i64| {
                    (-1..=1).any(|dx: i64| {
                        let (a, b) = (x + dx, y + dy);
                        (0..wi).contains(&a) && (0..hi).contains(&b) && kept[(b * wi + a) as usize]
                    })
                });
                if !next_to_kept {
                    f[q] = INF;
                }
            }
        }
        if f.iter().all(|&v| v == INF) {
            return None;
        }
    }
    let mut column = vec![0.0; h];
    for x in 0..w {
        for y in 0..h {
            column[y] = f[y * w + x];
        }
        let d = edt_1d(&column);
        for y in 0..h {
            f[y * w + x] = d[y];
        }
    }
    for y in 0..h {
        let d = edt_1d(&f[y * w..(y + 1) * w]);
        f[y * w..(y + 1) * w].copy_from_slice(&d);
    }
    Some(
        u.pixel
            .iter()
            .map(|&p| (f[p as usize].sqrt() - 0.5).max(0.5))
            .collect(),
    )
}

/// Squared distance transform of a sampled function in one dimension (lower envelope of
/// parabolas).
fn edt_1d(f: &[f64]) -> Vec<f64> {
    let n = f.len();
    let mut d = vec![0.0; n];
    let mut v = vec![0usize; n];
    let mut z = vec![0.0f64; n + 1];
    let mut k = 0usize;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    for q in 1..n {
        loop {
            let vk = v[k];
            let s = ((f[q] + (q * q) as f64) - (f[vk] + (vk * vk) as f64))
                / (2.0 * q as f64 - 2.0 * vk as f64);
            if s <= z[k] && k > 0 {
                k -= 1;
            } else {
                k += 1;
                v[k] = q;
                z[k] = s;
                z[k + 1] = f64::INFINITY;
                break;
            }
        }
    }
    k = 0;
    for (q, dq) in d.iter_mut().enumerate() {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let dx = q as f64 - v[k] as f64;
        *dq = dx * dx + f[v[k]];
    }
    d
}

/// (p, q) scaled down to magnitude [`MAX_GRADIENT`] when steeper.
pub(crate) fn clamp_gradient(p: f64, q: f64) -> (f64, f64) {
    let m = p.hypot(q);
    if m > MAX_GRADIENT {
        (p * MAX_GRADIENT / m, q * MAX_GRADIENT / m)
    } else {
        (p, q)
    }
}

/// Central (or one-sided at the mask's edge) differences of per-unknown values: (∂/∂x, ∂/∂y)
/// with y up.
pub(crate) fn differences(u: &Unknowns, z: &[f64], k: usize) -> (f64, f64) {
    let d = |a: u32, b: u32, here: f64| -> f64 {
        match (a != NONE, b != NONE) {
            (true, true) => (z[b as usize] - z[a as usize]) / 2.0,
            (true, false) => here - z[a as usize],
            (false, true) => z[b as usize] - here,
            (false, false) => 0.0,
        }
    };
    // x: left → right; y up: the row below (down) → the row above (up).
    (d(u.left[k], u.right[k], z[k]), d(u.down[k], u.up[k], z[k]))
}

/// The object of a rendered or masked-out photograph: every pixel except the black (≤ 0 or
/// non-finite) background connected to the image border. Dark pixels inside the object (its
/// shadows) stay in the mask, where a plain threshold would cut them out.
pub fn object_mask(image: &ScalarMap) -> Mask {
    let (w, h) = (image.width(), image.height());
    let black = |i: usize| {
        let v = image.data()[i];
        v.is_nan() || v <= 0.0
    };
    let mut background = vec![false; w * h];
    let mut stack: Vec<usize> = (0..w)
        .flat_map(|x| [x, (h.saturating_sub(1)) * w + x])
        .chain((0..h).flat_map(|y| [y * w, y * w + w.saturating_sub(1)]))
        .filter(|&i| i < w * h && black(i))
        .collect();
    while let Some(i) = stack.pop() {
        if background[i] {
            continue;
        }
        background[i] = true;
        let (x, y) = (i % w, i / w);
        let mut push = |j: usize| {
            if !background[j] && black(j) {
                stack.push(j);
            }
        };
        if x > 0 {
            push(i - 1);
        }
        if x + 1 < w {
            push(i + 1);
        }
        if y > 0 {
            push(i - w);
        }
        if y + 1 < h {
            push(i + w);
        }
    }
    Grid::from_fn(w, h, |x, y| !background[y * w + x])
}

#[cfg(test)]
mod outline_tests {
    use super::*;

    /// A disc of radius 12 in a 40×32 image, with its normals given by `f(x, y)` (x right, y up,
    /// from the centre).
    fn disc(f: impl Fn(f64, f64) -> Vector3<f64>) -> (Unknowns, NormalMap) {
        let (w, h, r) = (40usize, 32usize, 12.0);
        let at = |i: usize| ((i % w) as f64 - 20.0, 16.0 - (i / w) as f64);
        let mask = Grid::from_fn(w, h, |x, y| {
            let (dx, dy) = at(y * w + x);
            dx.hypot(dy) < r
        });
        let normals = Grid::from_fn(w, h, |x, y| {
            let (dx, dy) = at(y * w + x);
            f(dx / r, dy / r).cast::<f32>()
        });
        (Unknowns::new(&mask), normals)
    }

    fn sphere(x: f64, y: f64) -> Vector3<f64> {
        Vector3::new(x, y, (1.0 - x * x - y * y).max(0.0).sqrt())
    }

    /// The true normals of a sphere agree with its outline to within the outline's
    /// quantisation; the same normals turned 90° about the view (a surface whose slope runs
    /// along the outline) are all misaligned, at a mean of 90°; normals facing the camera have
    /// no direction in the image and count as misaligned.
    #[test]
    fn a_spheres_outline_agrees_and_a_turned_one_does_not() {
        let (u, n) = disc(sphere);
        let a = outline_agreement(&u, &n, &[]).unwrap();
        assert!(a.pixels > 40, "{a:?}");
        assert_eq!(a.misaligned_fraction, 0.0, "{a:?}");
        assert!(a.mean_angle_deg < 15.0, "{a:?}");
        let (u, n) = disc(|x, y| sphere(-y, x));
        let turned = outline_agreement(&u, &n, &[]).unwrap();
        assert_eq!(turned.pixels, a.pixels);
        assert!(turned.misaligned_fraction > 0.95, "{turned:?}");
        assert!((turned.mean_angle_deg - 90.0).abs() < 15.0, "{turned:?}");
        let (u, n) = disc(|_, _| Vector3::z());
        assert_eq!(
            outline_agreement(&u, &n, &[]).unwrap().misaligned_fraction,
            1.0
        );
    }

    /// A mask that fills the image has no outline inside it: nothing is judged.
    #[test]
    fn the_image_border_is_not_an_outline() {
        let mask = Grid::new(20, 10, true);
        let normals = Grid::new(20, 10, Vector3::new(0.0f32, 0.0, 1.0));
        assert!(outline_agreement(&Unknowns::new(&mask), &normals, &[]).is_none());
    }
}

#[cfg(test)]
mod distance_tests {
    use super::*;

    /// The distance to the mask's edge, and to the rest of it when part of the outline is
    /// left out: a rectangle whose top row is excluded takes its distances from the sides and
    /// the bottom (the top row's middle is then as far as the rectangle's half-width allows),
    /// nothing excluded is the plain transform, and an outline wholly excluded leaves none.
    #[test]
    fn distance_to_the_rest_of_the_outline() {
        let (w, h) = (14, 12);
        let mut mask = Grid::new(w, h, false);
        for y in 2..10 {
            for x in 2..12 {
                mask.data_mut()[y * w + x] = true;
            }
        }
        let u = Unknowns::new(&mask);
        let at = |d: &[f64], x: usize, y: usize| {
            d[u.pixel
                .iter()
                .position(|&p| p as usize == y * w + x)
                .unwrap()]
        };
        let plain = distance_to_edge(&u, &[]).unwrap();
        assert_eq!(plain, distance_to_edge(&u, &vec![false; u.len()]).unwrap());
        assert_eq!(at(&plain, 6, 2), 0.5);
        assert_eq!(at(&plain, 6, 5), 3.5);
        let top: Vec<bool> = u.pixel.iter().map(|&p| p as usize / w == 2).collect();
        let rest = distance_to_edge(&u, &top).unwrap();
        // Column 6 of the top row: 5 from column 1 (outside, next to the kept left side), 6
        // from column 12, 8 from row 10, less ½; not ½ from row 1 above it.
        assert_eq!(at(&rest, 6, 2), 4.5);
        assert_eq!(at(&rest, 6, 9), 0.5);
        assert_eq!(at(&rest, 2, 5), 0.5);
        assert!(distance_to_edge(&u, &vec![true; u.len()]).is_none());
    }
}
