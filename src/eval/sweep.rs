//! Speed against accuracy: sweeps of the normal estimators ([`crate::ps::solve`]), shape from
//! shading ([`crate::sfs`]) and the integrators ([`crate::integrate`]) over image noise, number
//! of lights and specular strength, on crate-rendered scenes with ground truth.
//!
//! Every row holds an error against the truth and the wall time of the stage that produced it,
//! so one can be charted against the other. [`pareto_front`] picks the rows that no other row
//! beats on both. The sweeps go past where the methods work, on purpose: 3 lights with
//! shadows, noise up to 10 % of the brightest pixel, strong highlights, and depth
//! discontinuities. `photostereo bench sweep` charts them.
//!
//! The scenes:
//! - **Normals** ([`normal_sweep`]): [`Scene::sphere_on_ground`]. It has attached and cast
//!   shadows, and Blinn–Phong highlights (exponent [`BLINN_PHONG_EXPONENT`]) when k_s > 0. The
//!   lights are a Fibonacci spiral at least [`MIN_ELEVATION_DEG`] above the horizon.
//! - **Shape from shading** ([`sfs_sweep`]): a Lambertian sphere under one light. The light is
//!   at the viewer for Horn and fast marching, and [`SFS_OBLIQUE_SLANT_DEG`] off it for Horn and
//!   Tsai–Shah. Photometric stereo with 3 and 8 lights runs on the same sphere as a reference.
//! - **Depth** ([`depth_sweep`]): true normals with Gaussian noise added, integrated on a vase
//!   (a non-rectangular mask) and on a sphere floating above a plane. Its silhouette is a
//!   depth discontinuity of [`FLOAT_HEIGHT`]·size.

use crate::capture::dataset::Capture;
use crate::capture::lights::{Light, Lights};
use crate::capture::stack::ColorMode;
use crate::error::{Error, Result};
use crate::eval::metrics::{angular_errors, depth_errors, depth_rmse_per_part};
use crate::eval::timed;
use crate::grid::NormalMap;
use crate::integrate::{IntegrationOptions, Integrator, integrate_normals};
use crate::nalgebra::Vector3;
use crate::progress::{Progress, Silent};
use crate::ps::solve::{Method, SolveOptions};
use crate::run::pipeline::{Config, reconstruct};
use crate::sfs::reflectance_map::ReflectanceMap;
use crate::sfs::{SfsMethod, SfsOptions, shape_from_shading};
use crate::synth::reflectance::{BlinnPhong, Material, Specular};
use crate::synth::render::{RenderOptions, render};
use crate::synth::scene::{Albedo, Object, Primitive, Scene, SceneKind};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;

/// Default image size (square) of the normal and depth sweeps.
pub const DEFAULT_SIZE: usize = 256;
/// Default image size (square) of the shape-from-shading sweep.
pub const DEFAULT_SFS_SIZE: usize = 128;
/// Lights of the reference condition (the noise and specularity sweeps).
pub const REFERENCE_LIGHTS: usize = 32;
/// Image noise σ of the reference condition (images peak near 1).
pub const REFERENCE_NOISE: f32 = 0.01;
/// Lowest light elevation of the Fibonacci light sets, degrees above the horizon.
pub const MIN_ELEVATION_DEG: f64 = 30.0;
/// Blinn–Phong exponent of the specularity sweep.
pub const BLINN_PHONG_EXPONENT: f64 = 50.0;
/// Albedo of the shape-from-shading sphere (known to the solver, as SFS needs).
pub const SFS_ALBEDO: f32 = 0.8;
/// Slant of the oblique shape-from-shading light, degrees from the viewing direction.
pub const SFS_OBLIQUE_SLANT_DEG: f64 = 30.0;
/// Light counts of the photometric-stereo reference in the shape-from-shading sweep.
pub const SFS_REFERENCE_LIGHTS: [usize; 2] = [3, 8];
/// Estimator of the photometric-stereo reference in the shape-from-shading sweep (the default).
pub const SFS_REFERENCE_METHOD: Method = Method::Auto;
/// Height of the floating sphere's silhouette above the plane, as a fraction of the size.
pub const FLOAT_HEIGHT: f64 = 0.12;
/// Specular strength of the glossy comparison of error against time: every sweep measures it,
/// the [`SweepOptions::quick`] one included.
pub const GLOSSY_KS: f64 = 0.2;
/// Normal noise (per component; about 2.3° mean error) of the integrators' comparison of error
/// against time: every depth sweep measures it, the [`SweepOptions::quick`] one included.
pub const DEPTH_PARETO_NOISE: f64 = 0.05;

/// What a row varies.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Axis {
    /// Image noise σ (normals) or normal noise σ (depth).
    Noise,
    /// Number of lights (images).
    Lights,
    /// Specular reflectance k_s.
    Specularity,
}

impl Axis {
    /// The name used in tables.
    pub fn name(self) -> &'static str {
        match self {
            Axis::Noise => "noise",
            Axis::Lights => "lights",
            Axis::Specularity => "specularity",
        }
    }
}

/// What to sweep, and how.
#[derive(Debug, Clone, PartialEq)]
pub struct SweepOptions {
    /// Image size (square) of the normal and depth sweeps, at least 32.
    pub size: usize,
    /// Image size (square) of the shape-from-shading sweep, at least 32 (Horn's iteration costs
    /// about 2 s at 128²).
    pub sfs_size: usize,
    /// Lights of the noise and specularity sweeps.
    pub lights: usize,
    /// Image noise σ of the light-count and specularity sweeps.
    pub noise: f32,
    /// Image noise levels σ (normals and shape from shading).
    pub noise_levels: Vec<f32>,
    /// Light counts, each at least 3.
    pub light_counts: Vec<usize>,
    /// Specular reflectances k_s.
    pub ks_levels: Vec<f64>,
    /// Normal noise levels σ of the depth sweep (per component, before renormalising).
    pub normal_noise_levels: Vec<f64>,
    /// Photometric-stereo estimators.
    pub methods: Vec<Method>,
    /// Shape-from-shading methods.
    pub sfs: Vec<SfsMethod>,
    /// Integrators.
    pub integrators: Vec<Integrator>,
    /// Timed runs per point. The rows hold the median time; the errors do not change between
    /// runs.
    pub repeat: usize,
    /// Seed of the noise.
    pub seed: u64,
}

impl Default for SweepOptions {
    fn default() -> Self {
        SweepOptions {
            size: DEFAULT_SIZE,
            sfs_size: DEFAULT_SFS_SIZE,
            lights: REFERENCE_LIGHTS,
            noise: REFERENCE_NOISE,
            noise_levels: vec![0.0, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1],
            light_counts: vec![3, 4, 5, 6, 8, 12, 16, 24, 32, 48, 96],
            ks_levels: vec![0.0, 0.05, 0.1, 0.2, 0.4, 0.8],
            normal_noise_levels: vec![0.0, 0.01, 0.02, 0.05, 0.1, 0.2],
            methods: Method::ALL.to_vec(),
            sfs: SfsMethod::ALL.to_vec(),
            integrators: Integrator::ALL.to_vec(),
            repeat: 1,
            seed: 1,
        }
    }
}

impl SweepOptions {
    /// Checks every parameter.
    ///
    /// # Errors
    /// [`Error::InvalidParameter`] naming the first bad one.
    pub fn validate(&self) -> Result<()> {
        if self.size < 32 {
            return Err(Error::param("size", format!("{} is below 32", self.size)));
        }
        if self.sfs_size < 32 {
            return Err(Error::param(
                "sfs-size",
                format!("{} is below 32", self.sfs_size),
            ));
        }
        if let Some(l) = std::iter::once(&self.lights)
            .chain(&self.light_counts)
            .find(|l| **l < 3)
        {
            return Err(Error::param(
                "lights",
                format!("{l}: photometric stereo needs at least 3"),
            ));
        }
        if let Some(s) = std::iter::once(&self.noise)
            .chain(&self.noise_levels)
            .find(|s| !(s.is_finite() && **s >= 0.0))
        {
            return Err(Error::param("noise", format!("{s} must be finite and ≥ 0")));
        }
        if let Some(k) = self
            .ks_levels
            .iter()
            .find(|k| !(k.is_finite() && (0.0..=1.0).contains(*k)))
        {
            return Err(Error::param("ks", format!("{k} is outside [0, 1]")));
        }
        if let Some(s) = self
            .normal_noise_levels
            .iter()
            .find(|s| !(s.is_finite() && **s >= 0.0))
        {
            return Err(Error::param(
                "normal-noise",
                format!("{s} must be finite and ≥ 0"),
            ));
        }
        Ok(())
    }

    /// These options cut down for a smoke run of a few seconds: 64² images and a few levels of
    /// each axis (still with [`GLOSSY_KS`] and [`DEPTH_PARETO_NOISE`]).
    pub fn quick(self) -> Self {
        SweepOptions {
            size: 64,
            sfs_size: 64,
            noise_levels: vec![0.0, 0.01, 0.05],
            light_counts: vec![3, 6, 32],
            ks_levels: vec![0.0, GLOSSY_KS],
            normal_noise_levels: vec![0.0, DEPTH_PARETO_NOISE],
            ..self
        }
    }

    fn runs(&self) -> usize {
        self.repeat.max(1)
    }
}

/// One normal estimate against the truth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NormalRow {
    /// What this row's sweep varies.
    pub axis: Axis,
    /// The scene.
    pub scene: &'static str,
    /// `photometric-stereo` or `shape-from-shading`.
    pub family: &'static str,
    /// Method name.
    pub method: String,
    /// Images used (lights).
    pub images: usize,
    /// Shape from shading: the light's angle from the viewing direction, degrees.
    pub light_slant_deg: Option<f64>,
    /// Image noise σ.
    pub noise: f32,
    /// Specular reflectance k_s (0: Lambertian).
    pub ks: f64,
    /// Mean angular error over the solved pixels, degrees.
    pub mean_deg: f64,
    /// Median angular error, degrees.
    pub median_deg: f64,
    /// 95th percentile, degrees.
    pub p95_deg: f64,
    /// Fraction of the mask with a normal (the rest could not be solved alone; the sweep does
    /// not fill it).
    pub coverage: f64,
    /// Median wall time of the stage (solve and normals, or shape from shading), seconds.
    pub seconds: f64,
}

/// One integration against the true depth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DepthRow {
    /// The scene: `vase` or `floating-sphere`.
    pub scene: &'static str,
    /// Integrator name.
    pub method: &'static str,
    /// Normal noise σ (per component, before renormalising).
    pub normal_noise: f64,
    /// Mean angular error of the noisy normals, degrees.
    pub normal_error_deg: f64,
    /// Depth RMSE after removing the mean offset, over the true depth range.
    pub rmse_over_range: f64,
    /// The same with the offset removed per object ([`depth_rmse_per_part`]): the shape error
    /// without the height of the discontinuities, which normals do not tell.
    pub shape_rmse_over_range: f64,
    /// Pixels integrated.
    pub pixels: usize,
    /// Median wall time of the integration, seconds.
    pub seconds: f64,
}

/// The material of specular strength `ks` (Lambertian at 0).
fn material(ks: f64) -> Material {
    if ks > 0.0 {
        Material::with_specular(Specular::BlinnPhong(BlinnPhong {
            ks,
            exponent: BLINN_PHONG_EXPONENT,
        }))
    } else {
        Material::lambertian()
    }
}

/// Renders `scene` under `lights` with noise `sigma` and the truth's mask.
fn capture(
    scene: &Scene,
    lights: &Lights,
    sigma: f32,
    seed: u64,
) -> Result<(Capture, crate::synth::scene::HeightField)> {
    let options = RenderOptions {
        noise_sigma: sigma,
        seed,
        ..RenderOptions::default()
    };
    let rendering = render(scene, lights, &options)?;
    let stack = rendering.to_stack(lights, ColorMode::Grey)?;
    let truth = rendering.truth;
    let capture = Capture::from_stack(stack, lights.clone(), Some(truth.mask.clone()))?;
    Ok((capture, truth))
}

/// Solves `capture` with each of `methods`; one row each.
#[allow(clippy::too_many_arguments)]
fn photometric_rows(
    capture: &Capture,
    truth: &NormalMap,
    methods: &[Method],
    runs: usize,
    axis: Axis,
    scene: &'static str,
    noise: f32,
    ks: f64,
) -> Result<Vec<NormalRow>> {
    methods
        .iter()
        .map(|&m| {
            // The estimators' own coverage and error: pixels they cannot solve alone are left
            // unsolved, not filled from their neighbours (`crate::ps::fill`).
            let config = Config {
                solve: SolveOptions {
                    fill: false,
                    ..SolveOptions::with_method(m)
                },
                integration: None,
                ..Config::default()
            };
            let (recon, seconds) = timed(runs, || reconstruct(capture, &config, &Silent))?;
            let e = angular_errors(&recon.maps.normals, truth, &capture.mask)?;
            Ok(NormalRow {
                axis,
                scene,
                family: "photometric-stereo",
                method: m.name().to_string(),
                images: capture.lights.len(),
                light_slant_deg: None,
                noise,
                ks,
                mean_deg: e.mean_deg,
                median_deg: e.median_deg,
                p95_deg: e.p95_deg,
                coverage: e.pixels as f64 / (e.pixels + e.missing).max(1) as f64,
                seconds,
            })
        })
        .collect()
}

/// Every photometric-stereo estimator on [`Scene::sphere_on_ground`] against image noise (at
/// [`SweepOptions::lights`] lights, Lambertian), light count (at [`SweepOptions::noise`],
/// Lambertian) and specular strength (at both references). `progress` counts conditions.
///
/// # Errors
/// [`Error::InvalidParameter`] for bad options; any error of rendering or solving.
///
/// # Example
/// ```
/// use photostereo::eval::sweep::{normal_sweep, Axis, SweepOptions};
/// use photostereo::ps::solve::Method;
/// let options = SweepOptions {
///     size: 48,
///     noise_levels: vec![0.0, 0.05],
///     light_counts: vec![],
///     ks_levels: vec![],
///     methods: vec![Method::LeastSquares],
///     ..SweepOptions::default()
/// };
/// let rows = normal_sweep(&options, &photostereo::progress::Silent)?;
/// assert_eq!(rows.len(), 2);
/// assert!(rows.iter().all(|r| r.axis == Axis::Noise));
/// // More noise, larger error.
/// assert!(rows[1].mean_deg > rows[0].mean_deg);
/// # Ok::<(), photostereo::Error>(())
/// ```
pub fn normal_sweep(options: &SweepOptions, progress: &dyn Progress) -> Result<Vec<NormalRow>> {
    options.validate()?;
    const SCENE: &str = "sphere-on-ground";
    let conditions: Vec<(Axis, usize, f32, f64)> = options
        .noise_levels
        .iter()
        .map(|&s| (Axis::Noise, options.lights, s, 0.0))
        .chain(
            options
                .light_counts
                .iter()
                .map(|&l| (Axis::Lights, l, options.noise, 0.0)),
        )
        .chain(
            options
                .ks_levels
                .iter()
                .map(|&k| (Axis::Specularity, options.lights, options.noise, k)),
        )
        .collect();
    progress.begin("normal sweep", conditions.len() as u64);
    let mut rows = Vec::new();
    for (axis, count, sigma, ks) in conditions {
        let scene = Scene::sphere_on_ground(options.size, material(ks));
        let lights = Lights::fibonacci(count, MIN_ELEVATION_DEG)?;
        let (capture, truth) = capture(&scene, &lights, sigma, options.seed)?;
        rows.extend(photometric_rows(
            &capture,
            &truth.normals,
            &options.methods,
            options.runs(),
            axis,
            SCENE,
            sigma,
            ks,
        )?);
        progress.advance(1);
    }
    progress.end();
    Ok(rows)
}

/// The unit direction at `slant` degrees from the viewer, azimuth 45° (upper right).
fn slanted(slant_deg: f64) -> Vector3<f64> {
    crate::synth::light_sets::slanted(slant_deg, 45.0)
}

/// Shape from shading on a Lambertian sphere (radius 0.4·size, albedo [`SFS_ALBEDO`], given
/// to the solver) against image noise. Each method runs under the lights it accepts (frontal,
/// and [`SFS_OBLIQUE_SLANT_DEG`] off the viewer). Least squares with
/// [`SFS_REFERENCE_LIGHTS`] lights runs on the same sphere as the photometric reference.
///
/// # Errors
/// [`Error::InvalidParameter`] for bad options; any error of rendering or solving.
pub fn sfs_sweep(options: &SweepOptions, progress: &dyn Progress) -> Result<Vec<NormalRow>> {
    options.validate()?;
    const SCENE: &str = "sphere";
    let scene = SceneKind::Sphere.build(
        options.sfs_size,
        Albedo::Constant(SFS_ALBEDO),
        Material::lambertian(),
    );
    progress.begin(
        "shape-from-shading sweep",
        options.noise_levels.len() as u64,
    );
    let mut rows = Vec::new();
    for &sigma in &options.noise_levels {
        for slant in [0.0, SFS_OBLIQUE_SLANT_DEG] {
            let l = slanted(slant);
            let rmap = ReflectanceMap::lambertian(l)?;
            let lights = Lights::new(vec![Light::new(l)])?;
            let rendering = render(
                &scene,
                &lights,
                &RenderOptions {
                    noise_sigma: sigma,
                    seed: options.seed,
                    ..RenderOptions::default()
                },
            )?;
            let (image, truth) = (&rendering.images[0][0], &rendering.truth);
            for &m in &options.sfs {
                if m.applicable(&rmap).is_err() {
                    continue;
                }
                let o = SfsOptions {
                    method: m,
                    ..SfsOptions::default()
                };
                let (r, seconds) = timed(options.runs(), || {
                    shape_from_shading(image, &truth.mask, &rmap, f64::from(SFS_ALBEDO), &o)
                })?;
                let e = angular_errors(&r.normals, &truth.normals, &truth.mask)?;
                rows.push(NormalRow {
                    axis: Axis::Noise,
                    scene: SCENE,
                    family: "shape-from-shading",
                    method: m.name().to_string(),
                    images: 1,
                    light_slant_deg: Some(slant),
                    noise: sigma,
                    ks: 0.0,
                    mean_deg: e.mean_deg,
                    median_deg: e.median_deg,
                    p95_deg: e.p95_deg,
                    coverage: e.pixels as f64 / (e.pixels + e.missing).max(1) as f64,
                    seconds,
                });
            }
        }
        for count in SFS_REFERENCE_LIGHTS {
            let lights = Lights::fibonacci(count, MIN_ELEVATION_DEG)?;
            let (capture, truth) = capture(&scene, &lights, sigma, options.seed)?;
            rows.extend(photometric_rows(
                &capture,
                &truth.normals,
                &[SFS_REFERENCE_METHOD],
                options.runs(),
                Axis::Noise,
                SCENE,
                sigma,
                0.0,
            )?);
        }
        progress.advance(1);
    }
    progress.end();
    Ok(rows)
}

/// The depth sweep's scenes: a vase alone (its mask is the object) and a sphere floating
/// [`FLOAT_HEIGHT`]·size above a plane that fills the frame.
pub fn depth_scenes(size: usize) -> [(&'static str, Scene); 2] {
    let s = size as f64;
    let vase = SceneKind::Vase.build(size, Albedo::Constant(0.7), Material::lambertian());
    let floating = Scene {
        width: size,
        height: size,
        objects: vec![
            Object::ground(Albedo::Constant(0.5)),
            Object::new(
                Primitive::Sphere {
                    cx: 0.0,
                    cy: 0.0,
                    radius: 0.3 * s,
                    base: FLOAT_HEIGHT * s,
                },
                Albedo::Constant(0.7),
            ),
        ],
    };
    [("vase", vase), ("floating-sphere", floating)]
}

/// `normals` with N(0, σ²) added to each component and renormalised (σ = 0: unchanged).
pub fn perturb_normals(normals: &NormalMap, sigma: f64, seed: u64) -> Result<NormalMap> {
    if !(sigma.is_finite() && sigma >= 0.0) {
        return Err(Error::param(
            "normal-noise",
            format!("{sigma} must be finite and ≥ 0"),
        ));
    }
    if sigma == 0.0 {
        return Ok(normals.clone());
    }
    let dist = Normal::new(0.0, sigma)
        .map_err(|e| Error::param("normal-noise", format!("{sigma}: {e}")))?;
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(seed);
    Ok(normals.map(|n| {
        if !n.iter().all(|v| v.is_finite()) {
            return *n;
        }
        let d = n.cast::<f64>()
            + Vector3::new(
                dist.sample(&mut rng),
                dist.sample(&mut rng),
                dist.sample(&mut rng),
            );
        let len = d.norm();
        if len > 0.0 {
            (d / len).cast::<f32>()
        } else {
            *n
        }
    }))
}

/// Every integrator on the true normals of [`depth_scenes`] with noise added
/// ([`perturb_normals`]) at each [`SweepOptions::normal_noise_levels`]: depth RMSE over range
/// and time.
///
/// # Errors
/// [`Error::InvalidParameter`] for bad options; any error of integration.
pub fn depth_sweep(options: &SweepOptions, progress: &dyn Progress) -> Result<Vec<DepthRow>> {
    options.validate()?;
    let scenes = depth_scenes(options.size);
    progress.begin(
        "depth sweep",
        (scenes.len() * options.normal_noise_levels.len()) as u64,
    );
    let mut rows = Vec::new();
    for (name, scene) in &scenes {
        let truth = scene.height_field();
        for &sigma in &options.normal_noise_levels {
            let normals = perturb_normals(&truth.normals, sigma, options.seed)?;
            let normal_error_deg = angular_errors(&normals, &truth.normals, &truth.mask)?.mean_deg;
            for &m in &options.integrators {
                let o = IntegrationOptions {
                    method: m,
                    ..IntegrationOptions::default()
                };
                let (r, seconds) = timed(options.runs(), || {
                    integrate_normals(&normals, &truth.mask, &o, &Silent)
                })?;
                let e = depth_errors(&r.depth, &truth.depth, &truth.mask)?;
                let shape =
                    depth_rmse_per_part(&r.depth, &truth.depth, &truth.mask, &truth.object)?;
                rows.push(DepthRow {
                    scene: name,
                    method: m.name(),
                    normal_noise: sigma,
                    normal_error_deg,
                    rmse_over_range: e.rmse_over_range,
                    shape_rmse_over_range: shape / e.gt_range,
                    pixels: e.pixels,
                    seconds,
                });
            }
            progress.advance(1);
        }
    }
    progress.end();
    Ok(rows)
}

/// Indices of the points that no other point beats on both coordinates (smaller cost and
/// smaller error), in order of increasing cost: the Pareto front of (cost, error) pairs. Points
/// with a non-finite coordinate are never on it; of equal points, the first is kept.
///
/// # Example
/// ```
/// use photostereo::eval::sweep::pareto_front;
/// // (time, error): the second is slower and worse than the first.
/// let pts = [(1.0, 5.0), (2.0, 6.0), (3.0, 1.0), (0.5, 9.0)];
/// assert_eq!(pareto_front(&pts), vec![3, 0, 2]);
/// ```
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..points.len())
        .filter(|&i| points[i].0.is_finite() && points[i].1.is_finite())
        .collect();
    // By cost, then error, then index: a point is on the front when its error is below every
    // error before it.
    order.sort_by(|&a, &b| {
        points[a]
            .0
            .total_cmp(&points[b].0)
            .then(points[a].1.total_cmp(&points[b].1))
            .then(a.cmp(&b))
    });
    let mut front = Vec::new();
    let mut best = f64::INFINITY;
    for i in order {
        if points[i].1 < best {
            best = points[i].1;
            front.push(i);
        }
    }
    front
}
