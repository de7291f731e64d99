//! `data-synth`: renders synthetic photometric-stereo data sets with ground truth.
//!
//! One of the library's named scenes ([`SceneKind`]) made of one material — Lambertian,
//! Oren–Nayar, or a specular lobe (Phong, Blinn–Phong, Torrance–Sparrow, Ward, mirror) over a
//! Lambertian diffuse lobe — is rendered under a generated set of distant lights with
//! [`photostereo::synth::render::render`] (cast shadows, optional shot and read noise, clipping, grey or
//! RGB; optionally area lights with soft shadows and diffuse interreflections), and written with [`photostereo::synth::write::write_synthetic`]: one image per light
//! (`img_NNN.exr` or `img_NNN.png`), `lights.json` naming them and `mask.png`, with the ground
//! truth in `gt/`: `normal_gt.exr`, `depth_gt.exr`, `albedo_gt.exr`, and per-light shadow masks
//! `shadow_NNN.png`.
//!
//! ```text
//! cargo run -p data-synth -- --shape vase --brdf blinn-phong --lights 24 --noise 0.01 -o scene/
//! photostereo scene/*.exr --lights scene/lights.json --mask scene/mask.png -o out/
//! ```
//!
//! (With the PNG formats use `scene/img_*.png`: `scene/*.png` also matches `mask.png`.)
//!
//! Flags are checked before anything is rendered or written: a value out of range, or a
//! parameter given to a model or light set that does not use it, prints `error: ...` naming the
//! flag and exits with status 1 (as do clap's own parse errors), leaving the output folder
//! untouched. Warnings (a near-degenerate light set, clipped samples, black images) go to stderr;
//! the one-line summary of what was written goes to stdout.

use anyhow::{Context, Result, bail, ensure};
use clap::{Parser, ValueEnum};
use photostereo::camera::Intrinsics;
use photostereo::capture::lights::{Lights, MAX_LIGHT_CONDITION};
use photostereo::synth::area_light::MAX_AREA_LIGHT_SAMPLES;
use photostereo::synth::interreflection::{
    DEFAULT_BOUNCE_SAMPLES, MAX_BOUNCE_SAMPLES, MAX_BOUNCES,
};
use photostereo::synth::near::{NearPlacement, render_near, two_ring_rig};
use photostereo::synth::reflectance::{
    BlinnPhong, Diffuse, Material, Mirror, Phong, Specular, TorranceSparrow, Ward,
};
use photostereo::synth::render::{DEFAULT_LIGHT_RADIUS_DEG, RenderOptions, Rendering, render};
use photostereo::synth::scene::{Albedo, Scene, SceneKind};
use photostereo::synth::write::{ImageFormat, write_synthetic_with_camera};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Smallest accepted `--size`: below this the scenes with several objects have no room for them.
const MIN_SIZE: usize = 8;
/// Largest accepted `--size`: bigger images take very long to render (cast shadows are ray
/// marched per pixel and light) and need gigabytes per image set.
const MAX_SIZE: usize = 8192;
/// Default `--size`.
const DEFAULT_SIZE: usize = 256;
/// Fewest lights that determine a normal and an albedo.
const MIN_LIGHTS: usize = 3;
/// Default `--lights` (every set but `diligent`, which has its own 96).
const DEFAULT_LIGHTS: usize = 12;
/// Default `--albedo-value`.
const DEFAULT_ALBEDO: f32 = 0.7;
/// Relative amplitude of the `smooth` albedo texture: it spans value·(1 ± this).
const SMOOTH_AMPLITUDE: f32 = 0.3;
/// Ratio of the darker to the lighter square of the `checker` albedo.
const CHECKER_RATIO: f32 = 0.5;
/// Default Oren–Nayar σ, degrees.
const DEFAULT_OREN_NAYAR_SIGMA_DEG: f64 = 20.0;
/// Default Torrance–Sparrow Beckmann roughness m.
const DEFAULT_BECKMANN_M: f64 = 0.3;
/// Default Ward α_x (and α_y unless given).
const DEFAULT_WARD_ALPHA: f64 = 0.2;
/// Default Phong / Blinn–Phong exponent.
const DEFAULT_SHININESS: f64 = 40.0;
/// Default specular reflectance k_s.
const DEFAULT_KS: f64 = 0.5;
/// Default F₀ of Torrance–Sparrow: a dielectric (glass, plastic).
const DEFAULT_F0_DIELECTRIC: f64 = 0.04;
/// Default F₀ of the mirror: a polished metal (≈ chrome).
const DEFAULT_F0_MIRROR: f64 = 0.8;
/// Default minimum elevation of the Fibonacci set, degrees.
const DEFAULT_FIBONACCI_ELEVATION: f64 = 30.0;
/// Default elevation of the ring, degrees.
const DEFAULT_RING_ELEVATION: f64 = 45.0;
/// Default elevation of the cluster's centre, degrees.
const DEFAULT_CLUSTER_ELEVATION: f64 = 60.0;
/// Default half angle of the cone set, degrees.
const DEFAULT_CONE_ANGLE: f64 = 45.0;
/// Default angular radius of the cluster, degrees.
const DEFAULT_CLUSTER_RADIUS: f64 = 5.0;
/// Default out-of-plane tilt of the coplanar set, degrees.
const DEFAULT_TILT: f64 = 2.0;
/// Number of lights of `Lights::diligent_grid`.
const DILIGENT_LIGHTS: usize = 96;
/// Largest interreflection hit table `data-synth` asks for, bytes (4 per ray and pixel): above
/// it `--bounce-samples` or `--size` is refused before rendering.
const MAX_HIT_TABLE_BYTES: usize = 4 << 30;
/// Mixed into `--seed` to seed the random light sets, so that the directions do not come from
/// the same random stream as the noise of the first image (which the renderer seeds with
/// `--seed` itself).
const LIGHT_SEED_MIX: u64 = 0x9E37_79B9_7F4A_7C15;

/// Render a synthetic photometric-stereo data set (images, lights.json, mask.png and ground
/// truth in gt/) that `photostereo` reads directly.
///
/// Example:
///
///   data-synth --shape vase --brdf blinn-phong --lights 24 --noise 0.01 -o scene/
///   photostereo scene/*.exr --lights scene/lights.json --mask scene/mask.png -o out/
///
/// Every object of the scene gets the material of --brdf: specular models sit on a Lambertian
/// diffuse lobe (the dichromatic model) unless --no-diffuse. A flag that the chosen --brdf,
/// --light-set or --shape does not use is an error rather than silently ignored.
#[derive(Debug, Parser)]
#[command(
    name = "data-synth",
    version,
    verbatim_doc_comment,
    allow_negative_numbers = true
)]
struct Cli {
    // --- Scene ---
    /// Scene to render (the library's named scenes).
    #[arg(long, value_enum, default_value_t = ShapeArg::Sphere, help_heading = "Scene")]
    shape: ShapeArg,
    /// Image width and height in pixels (the image is N×N) [default: 256]; not with --shape
    /// demo, which is fixed at 320×240.
    #[arg(long, value_name = "N", help_heading = "Scene")]
    size: Option<usize>,
    /// Sphere radius in pixels, --shape sphere only [default: 0.4 × size, the library's
    /// sphere]. The other scenes have fixed proportions.
    #[arg(long, value_name = "R", help_heading = "Scene")]
    radius: Option<f64>,
    /// Albedo texture [default: constant]: constant, a checkerboard of value and value/2 with
    /// squares of size/8 px, or a smooth texture value·(1 ± 0.3·sin·sin) of period size/4 px.
    /// Not with --shape demo (it has its own textures), nor without a diffuse lobe (the albedo
    /// scales only the diffuse lobe).
    #[arg(long, value_enum, help_heading = "Scene")]
    albedo: Option<AlbedoArg>,
    /// Albedo value in (0, 1] [default: 0.7]: the constant, the lighter checker square, or
    /// the mean of the smooth texture. Not where --albedo is not allowed.
    #[arg(long, value_name = "RHO", help_heading = "Scene")]
    albedo_value: Option<f32>,

    // --- Reflectance ---
    /// Reflectance model of every object. Specular models (phong, blinn-phong,
    /// torrance-sparrow, ward) add their lobe to a Lambertian diffuse one unless --no-diffuse;
    /// oren-nayar is diffuse only; mirror is purely specular.
    #[arg(long, value_enum, default_value_t = Brdf::Lambertian, help_heading = "Reflectance")]
    brdf: Brdf,
    /// Roughness, per model: oren-nayar σ, the facet-slope deviation in DEGREES (default 20,
    /// in (0, 90)); torrance-sparrow Beckmann m, the RMS facet slope (default 0.3, > 0); ward
    /// α_x, the lobe width along the image x direction (default 0.2, > 0).
    #[arg(long, value_name = "R", help_heading = "Reflectance")]
    roughness: Option<f64>,
    /// Ward only: lobe width α_y across the tangent (> 0) [default: --roughness, isotropic];
    /// a different value makes the lobe anisotropic.
    #[arg(long, value_name = "A", help_heading = "Reflectance")]
    alpha_y: Option<f64>,
    /// Phong and blinn-phong only: exponent n (≥ 0; larger is a tighter highlight)
    /// [default: 40].
    #[arg(long, value_name = "N", help_heading = "Reflectance")]
    shininess: Option<f64>,
    /// Specular reflectance k_s in [0, 1] of phong, blinn-phong and ward; the overall scale of
    /// torrance-sparrow's lobe (whose reflectance is k_s·F) [default: 0.5].
    #[arg(long, value_name = "KS", help_heading = "Reflectance")]
    specular: Option<f64>,
    /// Fresnel reflectance at normal incidence F₀ in [0, 1], torrance-sparrow and mirror only
    /// [default: 0.04 for torrance-sparrow (a dielectric), 0.8 for mirror (a metal)].
    #[arg(long, value_name = "F0", help_heading = "Reflectance")]
    f0: Option<f64>,
    /// Colour of the diffuse lobe, three values in [0, 1] multiplying the albedo per channel
    /// [default: 1,1,1]. Grey renderings see its BT.601 mix; use --color for RGB images.
    #[arg(long, value_name = "R,G,B", help_heading = "Reflectance")]
    diffuse_color: Option<String>,
    /// Colour of the specular lobe, three values in [0, 1] [default: 1,1,1: a dielectric's
    /// white highlight; a metal's is its own colour]. Specular models only.
    #[arg(long, value_name = "R,G,B", help_heading = "Reflectance")]
    specular_color: Option<String>,
    /// Drop the diffuse lobe under a specular model: a pure specular surface (mirror is
    /// always pure specular).
    #[arg(long, help_heading = "Reflectance")]
    no_diffuse: bool,

    // --- Lights ---
    /// How the light directions are spread.
    #[arg(long, value_enum, default_value_t = LightSetArg::Fibonacci, help_heading = "Lights")]
    light_set: LightSetArg,
    /// Number of lights, one image per light (at least 3) [default: 12]; not with
    /// --light-set diligent, which always has 96.
    #[arg(long, value_name = "N", help_heading = "Lights")]
    lights: Option<usize>,
    /// Elevation above the image plane in degrees: fibonacci, the minimum (default 30, in
    /// [0, 90)); ring, the ring's (default 45, in (0, 90)); clustered, the cluster centre's
    /// (default 60, in (0, 90], above --cone-angle).
    #[arg(long, value_name = "DEG", help_heading = "Lights")]
    elevation: Option<f64>,
    /// Angle in degrees: cone, the half angle about the viewing axis (default 45, in
    /// (0, 90]); clustered, the cluster's radius (default 5, in (0, 90)).
    #[arg(long, value_name = "DEG", help_heading = "Lights")]
    cone_angle: Option<f64>,
    /// Coplanar only: out-of-plane tilt in degrees, in [0, 90) (default 2; 0 is exactly
    /// coplanar, rank 2).
    #[arg(long, value_name = "DEG", help_heading = "Lights")]
    tilt: Option<f64>,

    // --- Camera ---
    /// Standard deviation of additive Gaussian read noise, in image units (a white Lambertian
    /// surface facing the light is 1).
    #[arg(
        long,
        default_value_t = 0.0,
        value_name = "SIGMA",
        help_heading = "Camera"
    )]
    noise: f32,
    /// Poisson shot noise: electrons collected at value 1 (> 0) [default: no shot noise].
    #[arg(long, value_name = "N", help_heading = "Camera")]
    full_well: Option<f32>,
    /// Saturation level (> 0): values above it are clipped to it [default: none]. The PNG
    /// formats store at most 1 whatever this is, so with them it must be ≤ 1.
    #[arg(long, value_name = "LEVEL", help_heading = "Camera")]
    saturation: Option<f32>,
    /// Ambient light added as A·albedo·diffuse colour to every pixel (0 for a dark room). With
    /// A > 0 the frame with every lamp off is written too, as `ambient.exr` (or `.png`), through
    /// the same camera: pass it to photostereo as --ambient, and the images as `img_*`
    #[arg(long, default_value_t = 0.0, value_name = "A", help_heading = "Camera")]
    ambient: f32,
    /// Angular radius of each light in degrees, in (0, 90) [default: 1.5]: the size of mirror
    /// highlights, and of area lights. Point lights ignore it, so --brdf mirror or
    /// --area-light-samples only.
    #[arg(long, value_name = "DEG", help_heading = "Camera")]
    light_radius: Option<f64>,
    /// Mirror highlights integrate over each pixel on an N×N grid of sub-pixel positions, as a
    /// camera pixel collects light over its area (1: point sampling at the pixel centre). Other
    /// terms are smooth across a pixel and always sampled at its centre.
    #[arg(long, default_value_t = 1, value_name = "N", help_heading = "Camera")]
    pixel_samples: usize,
    /// Render R, G and B images with the material colours instead of grey ones.
    #[arg(long, help_heading = "Camera")]
    color: bool,
    /// Do not compute cast shadows (attached shadows, n·l ≤ 0, are always present).
    #[arg(long, help_heading = "Camera")]
    no_cast_shadows: bool,
    /// Seed of the noise, of the random light sets (cone, clustered) and of the sample
    /// rotations of area lights and interreflections: the same seed and flags give
    /// byte-identical images.
    #[arg(long, default_value_t = 0, value_name = "S", help_heading = "Camera")]
    seed: u64,

    // --- Light transport ---
    /// Bounces of diffuse interreflection, 0 to 64: light reflected by the surface lights it
    /// again, so concave shapes (groove, bowl, relief, torus) get brighter than the local
    /// model says. 0 (the default): none.
    #[arg(
        long,
        default_value_t = 0,
        value_name = "N",
        help_heading = "Light transport"
    )]
    bounces: usize,
    /// Cosine-weighted rays per pixel for the interreflections, 1 to 1024 [default: 64]; the
    /// rays are traced once for all lights and bounces and take 4 bytes each per pixel. With
    /// --bounces only.
    #[arg(long, value_name = "N", help_heading = "Light transport")]
    bounce_samples: Option<usize>,
    /// Area lights: sample each light as a disc of radius --light-radius over N directions (2
    /// to 1024), for the shading and soft cast shadows with penumbrae [default: point lights].
    #[arg(long, value_name = "N", help_heading = "Light transport")]
    area_light_samples: Option<usize>,

    // --- Near lights ---
    /// Render an LED rig instead of distant lights: --lights LEDs (default 16), half on a ring
    /// at 25° and half at 45° from the optical axis, all at this many scene widths from the
    /// scene's centre, seen by a pinhole camera at the same distance; the images then show the
    /// inverse-square fall-off and the per-point light directions, lights.json holds each
    /// LED's `position` (and `principal`, `mu` with --led-mu), and K.txt the camera. Units:
    /// one scene pixel at the base plane. Not with --light-set, --elevation, --cone-angle,
    /// --tilt, --light-radius, --pixel-samples, --bounces, --area-light-samples or --brdf
    /// mirror.
    #[arg(long, value_name = "SIZES", help_heading = "Near lights")]
    near_distance: Option<f64>,
    /// --near-distance: each LED's angular profile cos^MU about the direction to the scene's
    /// centre (0, the default: isotropic; 1: a Lambertian LED).
    #[arg(
        long,
        value_name = "MU",
        requires = "near_distance",
        help_heading = "Near lights"
    )]
    led_mu: Option<f64>,

    // --- Output ---
    /// Image file format.
    #[arg(long, value_enum, default_value_t = FormatArg::Exr, help_heading = "Output")]
    format: FormatArg,
    /// Encode 8-bit PNGs with the sRGB transfer function, as cameras do (photostereo decodes
    /// 8-bit files as sRGB by default); --format png8 only.
    #[arg(long, help_heading = "Output")]
    srgb: bool,
    /// Output folder (created if needed).
    #[arg(long, short, value_name = "DIR", help_heading = "Output")]
    output: PathBuf,
}

/// `--shape` values: one per [`SceneKind`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum ShapeArg {
    /// A sphere of radius 0.4·size (or --radius), no background.
    Sphere,
    /// An ellipsoid (semi-axes 0.42, 0.3, 0.3 of the size), no background.
    Ellipsoid,
    /// A vase (a surface of revolution), no background.
    Vase,
    /// MATLAB's peaks surface over the whole image.
    Peaks,
    /// A plane with a step of 0.1·size at the centre (a depth discontinuity).
    Step,
    /// A plane tilted at slope 0.5 along x.
    Ramp,
    /// A bumpy torus on a ground plane (non-convex: self- and cast shadows).
    Torus,
    /// A pyramid and a Gaussian bump on a ground plane.
    Bumps,
    /// A 90° V-groove along y in a plane (concave: its faces light each other).
    Groove,
    /// A bowl, a hollow spherical cap, in a plane (concave).
    Bowl,
    /// Gaussian dimples, bumps and a groove on a plane: concave and convex detail.
    Relief,
    /// The built-in scene (fixed 320×240): hemisphere, bump, pyramid, dome on a checkered ground.
    Demo,
    /// A bust-like head: a face of Gaussian features on an ellipsoid, no background.
    Bust,
}

impl ShapeArg {
    /// The library's scene.
    fn kind(self) -> SceneKind {
        match self {
            ShapeArg::Sphere => SceneKind::Sphere,
            ShapeArg::Ellipsoid => SceneKind::Ellipsoid,
            ShapeArg::Vase => SceneKind::Vase,
            ShapeArg::Peaks => SceneKind::Peaks,
            ShapeArg::Step => SceneKind::Step,
            ShapeArg::Ramp => SceneKind::Ramp,
            ShapeArg::Torus => SceneKind::Torus,
            ShapeArg::Bumps => SceneKind::Bumps,
            ShapeArg::Groove => SceneKind::Groove,
            ShapeArg::Bowl => SceneKind::Bowl,
            ShapeArg::Relief => SceneKind::Relief,
            ShapeArg::Demo => SceneKind::Demo,
            ShapeArg::Bust => SceneKind::Bust,
        }
    }
}

/// `--albedo` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum AlbedoArg {
    /// The same albedo everywhere.
    Constant,
    /// A checkerboard.
    Checker,
    /// A smooth sinusoidal texture.
    Smooth,
}

/// `--brdf` values: the reflectance model, each mapped to a library [`Material`] by
/// [`Cli::material`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Brdf {
    /// Ideal diffuse reflection, albedo·max(0, n·l): the photometric-stereo model.
    Lambertian,
    /// Rough diffuse (Oren–Nayar 1994), σ = --roughness in degrees: flatter, back-scattering.
    OrenNayar,
    /// Phong lobe (energy-normalised), k_s = --specular, n = --shininess, over Lambertian.
    Phong,
    /// Blinn–Phong half-vector lobe, k_s = --specular, n = --shininess, over Lambertian.
    BlinnPhong,
    /// Torrance–Sparrow microfacets (Beckmann m = --roughness, Schlick F₀ = --f0, scale
    /// --specular), over Lambertian.
    TorranceSparrow,
    /// Ward's Gaussian lobe, α_x = --roughness, α_y = --alpha-y (anisotropic when they
    /// differ), k_s = --specular, over Lambertian.
    Ward,
    /// Ideal mirror (a chrome ball), Schlick F₀ = --f0; highlights are lights of angular radius
    /// --light-radius reflected in the surface.
    Mirror,
}

/// The parameter flags of the reflectance models, for checking which model uses which.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Param {
    /// `--roughness`.
    Roughness,
    /// `--alpha-y`.
    AlphaY,
    /// `--shininess`.
    Shininess,
    /// `--specular`.
    Specular,
    /// `--f0`.
    F0,
    /// `--specular-color`.
    SpecularColor,
    /// `--no-diffuse`.
    NoDiffuse,
    /// `--light-radius`.
    LightRadius,
}

impl Param {
    /// The flag.
    fn flag(self) -> &'static str {
        match self {
            Param::Roughness => "--roughness",
            Param::AlphaY => "--alpha-y",
            Param::Shininess => "--shininess",
            Param::Specular => "--specular",
            Param::F0 => "--f0",
            Param::SpecularColor => "--specular-color",
            Param::NoDiffuse => "--no-diffuse",
            Param::LightRadius => "--light-radius",
        }
    }
}

impl Brdf {
    /// Whether the model reads the parameter `p`. (The diffuse colour and the albedo are used
    /// by every model that has a diffuse lobe; see [`Cli::material`].)
    fn uses(self, p: Param) -> bool {
        use Param as P;
        match self {
            Brdf::Lambertian => false,
            Brdf::OrenNayar => p == P::Roughness,
            Brdf::Phong | Brdf::BlinnPhong => {
                matches!(
                    p,
                    P::Shininess | P::Specular | P::SpecularColor | P::NoDiffuse
                )
            }
            Brdf::TorranceSparrow => matches!(
                p,
                P::Roughness | P::Specular | P::F0 | P::SpecularColor | P::NoDiffuse
            ),
            Brdf::Ward => matches!(
                p,
                P::Roughness | P::AlphaY | P::Specular | P::SpecularColor | P::NoDiffuse
            ),
            // --no-diffuse agrees with what a mirror is; accepted as a no-op.
            Brdf::Mirror => matches!(p, P::F0 | P::SpecularColor | P::NoDiffuse | P::LightRadius),
        }
    }
}

/// `--light-set` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum LightSetArg {
    /// Near-uniform directions on a Fibonacci spiral over the cap above --elevation.
    Fibonacci,
    /// Evenly spaced azimuths on a ring at --elevation.
    Ring,
    /// Random directions (--seed) within --cone-angle of the viewing axis.
    Cone,
    /// DiLiGenT-like: 96 lights on a 12×8 planar grid in front of the object.
    Diligent,
    /// Near-degenerate, for stability tests: lights in one plane through the viewing axis,
    /// tilted alternately by ±--tilt out of it.
    Coplanar,
    /// Near-degenerate, for stability tests: random directions (--seed) within --cone-angle of
    /// one direction at --elevation.
    Clustered,
}

impl LightSetArg {
    /// Sets meant to be badly conditioned: warned about, not rejected.
    fn near_degenerate(self) -> bool {
        matches!(self, LightSetArg::Coplanar | LightSetArg::Clustered)
    }
}

/// `--format` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum FormatArg {
    /// Float32 EXR, linear, unclipped.
    Exr,
    /// 16-bit PNG, linear, clipped to [0, 1].
    Png16,
    /// 8-bit PNG, clipped to [0, 1]; linear, or sRGB-encoded with --srgb.
    Png8,
}

impl FormatArg {
    /// The library's image format.
    fn image_format(self, srgb: bool) -> ImageFormat {
        match self {
            FormatArg::Exr => ImageFormat::Exr,
            FormatArg::Png16 => ImageFormat::Png16,
            FormatArg::Png8 => ImageFormat::Png8 { srgb },
        }
    }
}

/// The name of a flag value, as typed on the command line.
fn value_name<T: ValueEnum>(v: T) -> String {
    v.to_possible_value()
        .map(|p| p.get_name().to_owned())
        .unwrap_or_default()
}

/// Everything to do, validated: what `main` renders and writes.
#[derive(Debug)]
struct Plan {
    /// The scene to render, every object with the material of `--brdf`.
    scene: Scene,
    /// `--shape` as given, for the summary.
    shape: ShapeArg,
    /// `--brdf` as given, for the summary.
    brdf: Brdf,
    /// The lights, one per image.
    lights: Lights,
    /// What the light set is, for the summary.
    lights_summary: String,
    /// Noise, clipping, seed, shadows, ambient, colour, light size.
    render: RenderOptions,
    /// Image file format.
    format: ImageFormat,
    /// Output folder.
    output: PathBuf,
    /// Things to tell the user before rendering (e.g. a near-degenerate light set).
    warnings: Vec<String>,
    /// --near-distance: where the scene stands before the pinhole camera.
    near: Option<(NearPlacement, Intrinsics)>,
}

impl Cli {
    /// Checks every flag and builds the scene, the lights and the render options; fails with a
    /// message naming the flag at fault before anything is rendered or written.
    fn plan(self) -> Result<Plan> {
        let material = self.material()?;
        let scene = self.scene(material)?;
        let render = self.render_options()?;
        let format = self.format()?;
        let mut warnings = Vec::new();
        let near = self.near_rig(&scene)?;
        let (lights, lights_summary) = match &near {
            Some((lights, summary, _)) => (lights.clone(), summary.clone()),
            None => self.light_set(&mut warnings)?,
        };
        let near = near.map(|(_, _, placed)| placed);
        check_no_stale_files(&self.output, lights.len(), format)?;
        Ok(Plan {
            scene,
            shape: self.shape,
            brdf: self.brdf,
            lights,
            lights_summary,
            render,
            format,
            output: self.output,
            warnings,
            near,
        })
    }

    /// The material of `--brdf` and its parameters: rejects parameters the model does not use
    /// and values out of range.
    fn material(&self) -> Result<Material> {
        let brdf = self.brdf;
        let name = value_name(brdf);
        let given = [
            (Param::Roughness, self.roughness.is_some()),
            (Param::AlphaY, self.alpha_y.is_some()),
            (Param::Shininess, self.shininess.is_some()),
            (Param::Specular, self.specular.is_some()),
            (Param::F0, self.f0.is_some()),
            (Param::SpecularColor, self.specular_color.is_some()),
            (Param::NoDiffuse, self.no_diffuse),
            // Area lights have a radius whatever the model.
            (
                Param::LightRadius,
                self.light_radius.is_some() && self.area_light_samples.is_none(),
            ),
        ];
        for (p, is_given) in given {
            if is_given && !brdf.uses(p) {
                if p == Param::LightRadius {
                    bail!(
                        "--light-radius has no effect with point lights and --brdf {name}: it applies to --brdf mirror, or to area lights (--area-light-samples)"
                    );
                }
                let users: Vec<String> = Brdf::value_variants()
                    .iter()
                    .filter(|b| b.uses(p))
                    .map(|b| value_name(*b))
                    .collect();
                bail!(
                    "{} has no effect with --brdf {name}: it applies to --brdf {}",
                    p.flag(),
                    users.join(", ")
                );
            }
        }
        let has_diffuse = !(brdf == Brdf::Mirror || self.no_diffuse);
        if !has_diffuse {
            let why = if brdf == Brdf::Mirror {
                "--brdf mirror has no diffuse lobe".to_owned()
            } else {
                format!("--no-diffuse removes the diffuse lobe of --brdf {name}")
            };
            if self.diffuse_color.is_some() {
                bail!("--diffuse-color has no effect: {why}");
            }
            for (flag, is_given) in [
                ("--albedo", self.albedo.is_some()),
                ("--albedo-value", self.albedo_value.is_some()),
            ] {
                ensure!(
                    !is_given,
                    "{flag} has no effect: {why}, and the albedo scales only the diffuse lobe"
                );
            }
        }
        let unit = |flag: &str, v: f64| -> Result<f64> {
            ensure!((0.0..=1.0).contains(&v), "{flag} {v}: must be in [0, 1]");
            Ok(v)
        };
        let positive = |flag: &str, v: f64, what: &str| -> Result<f64> {
            ensure!(
                v.is_finite() && v > 0.0,
                "{flag} {v}: {what} must be finite and > 0"
            );
            Ok(v)
        };
        let ks = || unit("--specular", self.specular.unwrap_or(DEFAULT_KS));
        let shininess = || -> Result<f64> {
            let n = self.shininess.unwrap_or(DEFAULT_SHININESS);
            ensure!(
                n.is_finite() && n >= 0.0,
                "--shininess {n}: the exponent must be finite and ≥ 0"
            );
            Ok(n)
        };
        let specular = match brdf {
            Brdf::Lambertian | Brdf::OrenNayar => None,
            Brdf::Phong => Some(Specular::Phong(Phong {
                ks: ks()?,
                exponent: shininess()?,
            })),
            Brdf::BlinnPhong => Some(Specular::BlinnPhong(BlinnPhong {
                ks: ks()?,
                exponent: shininess()?,
            })),
            Brdf::TorranceSparrow => Some(Specular::TorranceSparrow(TorranceSparrow {
                ks: ks()?,
                roughness: positive(
                    "--roughness",
                    self.roughness.unwrap_or(DEFAULT_BECKMANN_M),
                    "the Beckmann roughness m of --brdf torrance-sparrow",
                )?,
                f0: unit("--f0", self.f0.unwrap_or(DEFAULT_F0_DIELECTRIC))?,
            })),
            Brdf::Ward => {
                let alpha_x = positive(
                    "--roughness",
                    self.roughness.unwrap_or(DEFAULT_WARD_ALPHA),
                    "α_x of --brdf ward",
                )?;
                let alpha_y = match self.alpha_y {
                    Some(a) => positive("--alpha-y", a, "α_y of --brdf ward")?,
                    None => alpha_x,
                };
                Some(Specular::Ward(Ward {
                    ks: ks()?,
                    alpha_x,
                    alpha_y,
                }))
            }
            Brdf::Mirror => Some(Specular::Mirror(Mirror {
                f0: unit("--f0", self.f0.unwrap_or(DEFAULT_F0_MIRROR))?,
            })),
        };
        let diffuse = if !has_diffuse {
            Diffuse::None
        } else if brdf == Brdf::OrenNayar {
            let deg = self.roughness.unwrap_or(DEFAULT_OREN_NAYAR_SIGMA_DEG);
            ensure!(
                deg > 0.0 && deg < 90.0,
                "--roughness {deg}: σ of --brdf oren-nayar is in degrees and must be in (0, 90)"
            );
            Diffuse::OrenNayar {
                sigma: deg.to_radians(),
            }
        } else {
            Diffuse::Lambertian
        };
        let color = |flag: &str, text: &Option<String>| -> Result<[f64; 3]> {
            text.as_deref().map_or(Ok([1.0; 3]), |t| parse_rgb(flag, t))
        };
        Ok(Material {
            diffuse,
            diffuse_color: color("--diffuse-color", &self.diffuse_color)?,
            specular,
            specular_color: color("--specular-color", &self.specular_color)?,
        })
    }

    /// The albedo texture of `--albedo` and `--albedo-value`, scaled to the image size.
    fn albedo(&self, size: usize) -> Result<Albedo> {
        let v = self.albedo_value.unwrap_or(DEFAULT_ALBEDO);
        ensure!(v > 0.0 && v <= 1.0, "--albedo-value {v}: must be in (0, 1]");
        let size = size as f64;
        Ok(match self.albedo.unwrap_or(AlbedoArg::Constant) {
            AlbedoArg::Constant => Albedo::Constant(v),
            AlbedoArg::Checker => Albedo::Checker {
                size: (size / 8.0).max(2.0),
                a: v,
                b: CHECKER_RATIO * v,
            },
            AlbedoArg::Smooth => {
                let top = 1.0 / (1.0 + SMOOTH_AMPLITUDE);
                ensure!(
                    v <= top,
                    "--albedo-value {v} with --albedo smooth: the texture reaches {v}·{} = {}, above 1; use at most {top:.3}",
                    1.0 + SMOOTH_AMPLITUDE,
                    v * (1.0 + SMOOTH_AMPLITUDE)
                );
                Albedo::Smooth {
                    mean: v,
                    amplitude: SMOOTH_AMPLITUDE * v,
                    period: (size / 4.0).max(4.0),
                }
            }
        })
    }

    /// The scene of `--shape`, every object made of `material`.
    fn scene(&self, material: Material) -> Result<Scene> {
        if self.shape == ShapeArg::Demo {
            for (flag, is_given) in [
                ("--size", self.size.is_some()),
                ("--albedo", self.albedo.is_some()),
                ("--albedo-value", self.albedo_value.is_some()),
            ] {
                ensure!(
                    !is_given,
                    "{flag} has no effect with --shape demo: the demo scene has a fixed size (320×240) and its own albedo textures"
                );
            }
        }
        if self.radius.is_some() && self.shape != ShapeArg::Sphere {
            bail!(
                "--radius applies only to --shape sphere (the other scenes have fixed proportions)"
            );
        }
        let size = self.size.unwrap_or(DEFAULT_SIZE);
        ensure!(
            (MIN_SIZE..=MAX_SIZE).contains(&size),
            "--size {size}: must be between {MIN_SIZE} and {MAX_SIZE} pixels"
        );
        // The demo scene has its own albedo: do not validate flags it refuses anyway.
        let albedo = if self.shape == ShapeArg::Demo {
            Albedo::Constant(DEFAULT_ALBEDO)
        } else {
            self.albedo(size)?
        };
        if let Some(radius) = self.radius {
            let half = size as f64 / 2.0;
            // At least 1 px so that the sphere covers a pixel centre whatever the parity of the
            // size; at most size/2 so that its outline stays inside the image.
            ensure!(
                (1.0..=half).contains(&radius),
                "--radius {radius}: must be between 1 and size/2 = {half} pixels so that the sphere fits in the {size}×{size} image"
            );
            let mut scene = Scene::sphere(size, radius, albedo);
            for o in &mut scene.objects {
                o.material = material;
            }
            return Ok(scene);
        }
        Ok(self.shape.kind().build(size, albedo, material))
    }

    /// The render options of the camera flags.
    fn render_options(&self) -> Result<RenderOptions> {
        ensure!(
            self.noise.is_finite() && self.noise >= 0.0,
            "--noise {}: must be finite and ≥ 0",
            self.noise
        );
        ensure!(
            self.ambient.is_finite() && self.ambient >= 0.0,
            "--ambient {}: must be finite and ≥ 0",
            self.ambient
        );
        if let Some(fw) = self.full_well {
            ensure!(
                fw.is_finite() && fw > 0.0,
                "--full-well {fw}: the electrons at value 1 must be finite and > 0"
            );
        }
        if let Some(level) = self.saturation {
            ensure!(
                level.is_finite() && level > 0.0,
                "--saturation {level}: must be finite and > 0"
            );
            ensure!(
                self.format == FormatArg::Exr || level <= 1.0,
                "--saturation {level}: --format {} stores values up to 1 only; use a level ≤ 1 or --format exr",
                value_name(self.format)
            );
        }
        let light_radius_deg = self.light_radius.unwrap_or(DEFAULT_LIGHT_RADIUS_DEG);
        ensure!(
            light_radius_deg > 0.0 && light_radius_deg < 90.0,
            "--light-radius {light_radius_deg}: must be in (0, 90) degrees"
        );
        ensure!(
            self.bounces <= MAX_BOUNCES,
            "--bounces {}: must be at most {MAX_BOUNCES}",
            self.bounces
        );
        if let Some(n) = self.bounce_samples {
            ensure!(
                self.bounces > 0,
                "--bounce-samples has no effect without --bounces"
            );
            ensure!(
                (1..=MAX_BOUNCE_SAMPLES).contains(&n),
                "--bounce-samples {n}: must be between 1 and {MAX_BOUNCE_SAMPLES}"
            );
        }
        let bounce_samples = self.bounce_samples.unwrap_or(DEFAULT_BOUNCE_SAMPLES);
        if self.bounces > 0 {
            let size = self.size.unwrap_or(DEFAULT_SIZE);
            let bytes = size
                .saturating_mul(size)
                .saturating_mul(bounce_samples)
                .saturating_mul(4);
            ensure!(
                bytes <= MAX_HIT_TABLE_BYTES,
                "--bounce-samples {bounce_samples} at --size {size}: the interreflection rays take up to {} MiB (4 bytes per ray and pixel), above {} MiB; use fewer samples or a smaller size",
                bytes >> 20,
                MAX_HIT_TABLE_BYTES >> 20
            );
        }
        if let Some(n) = self.area_light_samples {
            ensure!(
                (2..=MAX_AREA_LIGHT_SAMPLES).contains(&n),
                "--area-light-samples {n}: must be between 2 and {MAX_AREA_LIGHT_SAMPLES} (omit it for point lights)"
            );
        }
        let options = RenderOptions {
            cast_shadows: !self.no_cast_shadows,
            ambient: self.ambient,
            noise_sigma: self.noise,
            full_well: self.full_well,
            clip: self.saturation,
            light_radius_deg,
            pixel_samples: self.pixel_samples,
            color: self.color,
            seed: self.seed,
            bounces: self.bounces,
            bounce_samples,
            area_light_samples: self.area_light_samples.unwrap_or(0),
        };
        // The checks above cover the library's; this keeps the two from drifting apart.
        options.validate().context("invalid camera flags")?;
        Ok(options)
    }

    /// The image format of `--format` and `--srgb`.
    fn format(&self) -> Result<ImageFormat> {
        ensure!(
            !self.srgb || self.format == FormatArg::Png8,
            "--srgb applies only to --format png8 (EXR and 16-bit PNG are written linear), not --format {}",
            value_name(self.format)
        );
        Ok(self.format.image_format(self.srgb))
    }

    /// --near-distance: the LED rig, its summary, the placement and the camera; `None` without
    /// it.
    #[allow(clippy::type_complexity)]
    fn near_rig(
        &self,
        scene: &Scene,
    ) -> Result<Option<(Lights, String, (NearPlacement, Intrinsics))>> {
        let Some(d) = self.near_distance else {
            return Ok(None);
        };
        ensure!(
            d.is_finite() && d >= 1.0,
            "--near-distance {d}: must be at least 1 (scene widths from the scene's centre)"
        );
        for (flag, given) in [
            ("--light-set", self.light_set != LightSetArg::Fibonacci),
            ("--elevation", self.elevation.is_some()),
            ("--cone-angle", self.cone_angle.is_some()),
            ("--tilt", self.tilt.is_some()),
            ("--light-radius", self.light_radius.is_some()),
            ("--bounces", self.bounces > 0),
            ("--area-light-samples", self.area_light_samples.is_some()),
            ("--pixel-samples", self.pixel_samples > 1),
            ("--brdf mirror", self.brdf == Brdf::Mirror),
        ] {
            if given {
                bail!("{flag} does not apply to the LED rig of --near-distance");
            }
        }
        let mu = self.led_mu.unwrap_or(0.0);
        ensure!(
            mu.is_finite() && (0.0..=1000.0).contains(&mu),
            "--led-mu {mu}: must be in 0..=1000"
        );
        let count = self.lights.unwrap_or(16);
        ensure!(count >= 4, "--lights {count}: the LED rig needs at least 4");
        let reach = d * scene.width.max(scene.height) as f64;
        let placement = NearPlacement {
            distance: reach,
            scale: 1.0,
        };
        let target = photostereo::nalgebra::Vector3::new(0.0, 0.0, -reach);
        let lights = two_ring_rig(count, reach, target, mu)?;
        let summary = format!(
            "{count} LEDs at {} scene widths ({} units){}, camera at the same distance",
            num(d),
            num(reach),
            if mu > 0.0 {
                format!(", profile cos^{}", num(mu))
            } else {
                String::new()
            }
        );
        Ok(Some((
            lights,
            summary,
            (placement, placement.camera(scene)),
        )))
    }

    /// The lights of `--light-set` and its flags, with a description for the summary. A
    /// near-degenerate set gets a warning with its condition number; any other set must pass
    /// [`Lights::check_usable`].
    fn light_set(&self, warnings: &mut Vec<String>) -> Result<(Lights, String)> {
        use LightSetArg as S;
        let set = self.light_set;
        let set_name = value_name(set);
        for (flag, is_given, users) in [
            (
                "--elevation",
                self.elevation.is_some(),
                &[S::Fibonacci, S::Ring, S::Clustered][..],
            ),
            (
                "--cone-angle",
                self.cone_angle.is_some(),
                &[S::Cone, S::Clustered],
            ),
            ("--tilt", self.tilt.is_some(), &[S::Coplanar]),
        ] {
            if is_given && !users.contains(&set) {
                let names: Vec<String> = users.iter().map(|s| value_name(*s)).collect();
                bail!(
                    "{flag} has no effect with --light-set {set_name}: it applies to --light-set {}",
                    names.join(", ")
                );
            }
        }
        let n = if set == S::Diligent {
            if let Some(n) = self.lights {
                bail!(
                    "--lights {n}: --light-set diligent always has {DILIGENT_LIGHTS} lights; omit --lights"
                );
            }
            DILIGENT_LIGHTS
        } else {
            let n = self.lights.unwrap_or(DEFAULT_LIGHTS);
            ensure!(
                n >= MIN_LIGHTS,
                "--lights {n}: photometric stereo needs at least {MIN_LIGHTS} lights"
            );
            n
        };
        let light_seed = self.seed ^ LIGHT_SEED_MIX;
        let (lights, summary) = match set {
            S::Fibonacci => {
                let e = self.elevation.unwrap_or(DEFAULT_FIBONACCI_ELEVATION);
                ensure!(
                    (0.0..90.0).contains(&e),
                    "--elevation {e}: the minimum elevation of --light-set fibonacci must be in [0, 90) degrees"
                );
                (Lights::fibonacci(n, e), format!("above {e}°"))
            }
            S::Ring => {
                let e = self.elevation.unwrap_or(DEFAULT_RING_ELEVATION);
                // At 90° every light of the ring is the same overhead light.
                ensure!(
                    e > 0.0 && e < 90.0,
                    "--elevation {e}: the elevation of --light-set ring must be in (0, 90) degrees"
                );
                (Lights::ring(n, e, 0.0), format!("at {e}°"))
            }
            S::Cone => {
                let a = self.cone_angle.unwrap_or(DEFAULT_CONE_ANGLE);
                ensure!(
                    a > 0.0 && a <= 90.0,
                    "--cone-angle {a}: the half angle of --light-set cone must be in (0, 90] degrees"
                );
                (
                    // A cone about the viewing axis is a cluster centred at elevation 90°
                    // (`Lights::random_cone` about (0, 0, 1) up to 1e-16, without depending on
                    // nalgebra for the axis).
                    Lights::clustered(n, 90.0, a, light_seed),
                    format!("within {a}° of the viewing axis"),
                )
            }
            S::Diligent => (Ok(Lights::diligent_grid()), "on a 12×8 grid".to_owned()),
            S::Coplanar => {
                let t = self.tilt.unwrap_or(DEFAULT_TILT);
                ensure!(
                    (0.0..90.0).contains(&t),
                    "--tilt {t}: must be in [0, 90) degrees"
                );
                (Lights::coplanar(n, t), format!("tilted ±{t}°"))
            }
            S::Clustered => {
                let e = self.elevation.unwrap_or(DEFAULT_CLUSTER_ELEVATION);
                let r = self.cone_angle.unwrap_or(DEFAULT_CLUSTER_RADIUS);
                ensure!(
                    e > 0.0 && e <= 90.0,
                    "--elevation {e}: the cluster centre of --light-set clustered must be in (0, 90] degrees"
                );
                ensure!(
                    r > 0.0 && r < 90.0,
                    "--cone-angle {r}: the cluster radius of --light-set clustered must be in (0, 90) degrees"
                );
                ensure!(
                    r < e,
                    "--cone-angle {r} with --elevation {e}: the cluster would reach below the horizon; use a radius below the elevation"
                );
                (
                    Lights::clustered(n, e, r, light_seed),
                    format!("within {r}° of elevation {e}°"),
                )
            }
        };
        let lights = lights.with_context(|| format!("--lights {n} --light-set {set_name}"))?;
        let condition = lights.condition_number();
        let mut summary = format!("{n} {set_name} lights {summary}");
        if set.near_degenerate() {
            warnings.push(format!(
                "--light-set {set_name} is near-degenerate by design: condition number {} (photostereo rejects sets above {MAX_LIGHT_CONDITION:.0e}; the solver's error grows with it)",
                format_condition(condition)
            ));
            write!(summary, ", condition {}", format_condition(condition))?;
        } else {
            lights.check_usable(MAX_LIGHT_CONDITION).with_context(|| {
                format!(
                    "--light-set {set_name} with --lights {n}: the light set cannot determine normals (condition number {})",
                    format_condition(condition)
                )
            })?;
        }
        if matches!(set, S::Cone | S::Clustered) {
            write!(summary, " (seed {})", self.seed)?;
        }
        Ok((lights, summary))
    }
}

/// A condition number for messages: ∞ for a singular set, one decimal below 10⁴, else
/// scientific with 3 significant digits.
fn format_condition(c: f64) -> String {
    if !c.is_finite() || c > 1e12 {
        "∞ (singular)".to_owned()
    } else if c < 1e4 {
        format!("{c:.1}")
    } else {
        format!("{c:.2e}")
    }
}

/// Parses `r,g,b` into three values in [0, 1].
fn parse_rgb(flag: &str, text: &str) -> Result<[f64; 3]> {
    let values: Vec<f64> = text
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| anyhow::anyhow!("{flag} {text}: expected three numbers r,g,b"))?;
    let [r, g, b] = values[..] else {
        bail!(
            "{flag} {text}: expected three numbers r,g,b, found {}",
            values.len()
        );
    };
    for v in [r, g, b] {
        ensure!(
            (0.0..=1.0).contains(&v),
            "{flag} {text}: every component must be in [0, 1], {v} is not"
        );
    }
    Ok([r, g, b])
}

/// Refuses to write into a folder holding `img_*` files that this run would not overwrite (left
/// by an earlier run with more lights or another format): the glob `DIR/img_*` would then pick
/// up images that `lights.json` does not describe.
fn check_no_stale_files(dir: &Path, lights: usize, format: ImageFormat) -> Result<()> {
    if !dir.exists() {
        return Ok(());
    }
    ensure!(
        dir.is_dir(),
        "--output {}: exists and is not a folder",
        dir.display()
    );
    let ext = format.extension();
    // The names write_synthetic gives its files.
    let ours = |name: &str| (0..lights).any(|k| name == format!("img_{k:03}.{ext}"));
    let mut stale: Vec<String> = std::fs::read_dir(dir)
        .with_context(|| format!("--output {}: cannot list the folder", dir.display()))?
        .filter_map(Result::ok)
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("img_") && !ours(n))
        .collect();
    if stale.is_empty() {
        return Ok(());
    }
    stale.sort();
    let shown = stale.iter().take(3).cloned().collect::<Vec<_>>().join(", ");
    let more = if stale.len() > 3 { ", …" } else { "" };
    bail!(
        "--output {}: holds {} file(s) from an earlier run that this run would not overwrite ({shown}{more}); `photostereo {}/img_*` would pick them up. Remove them or choose another folder",
        dir.display(),
        stale.len(),
        dir.display()
    )
}

/// A number for the summary: rounded to 6 significant digits and printed in its shortest form,
/// so that f32 flags (0.8 → 0.800000011920929) and degree round trips (30° → 29.999999999999996)
/// print as typed.
fn num(v: f64) -> String {
    let rounded: f64 = format!("{v:.5e}").parse().unwrap_or(v);
    format!("{rounded}")
}

/// `r,g,b` for the summary.
fn rgb(c: [f64; 3]) -> String {
    c.map(num).join(",")
}

impl Plan {
    /// The material every object is made of (the scenes are built with one).
    fn material(&self) -> Material {
        self.scene
            .objects
            .first()
            .map_or_else(Material::lambertian, |o| o.material)
    }

    /// The model and its parameters, from the material actually rendered: the specular lobe
    /// with its parameters, then the diffuse lobe under it (`over lambertian`), or the diffuse
    /// model alone.
    fn describe_material(&self) -> String {
        let m = self.material();
        let colour = |c: [f64; 3]| (c != [1.0; 3]).then(|| format!("colour {}", rgb(c)));
        let with = |name: &str, params: Vec<String>, c: Option<String>| {
            let all: Vec<String> = params.into_iter().chain(c).collect();
            if all.is_empty() {
                name.to_owned()
            } else {
                format!("{name} ({})", all.join(", "))
            }
        };
        let diffuse = match m.diffuse {
            Diffuse::None => None,
            Diffuse::Lambertian => Some(with("lambertian", vec![], colour(m.diffuse_color))),
            Diffuse::OrenNayar { sigma } => Some(with(
                "oren-nayar",
                vec![format!("σ {}°", num(sigma.to_degrees()))],
                colour(m.diffuse_color),
            )),
        };
        let (name, params) = match m.specular {
            None => return diffuse.unwrap_or_else(|| "black".to_owned()),
            Some(Specular::Phong(p)) => (
                "phong",
                vec![
                    format!("k_s {}", num(p.ks)),
                    format!("n {}", num(p.exponent)),
                ],
            ),
            Some(Specular::BlinnPhong(p)) => (
                "blinn-phong",
                vec![
                    format!("k_s {}", num(p.ks)),
                    format!("n {}", num(p.exponent)),
                ],
            ),
            Some(Specular::TorranceSparrow(p)) => (
                "torrance-sparrow",
                vec![
                    format!("k_s {}", num(p.ks)),
                    format!("m {}", num(p.roughness)),
                    format!("F0 {}", num(p.f0)),
                ],
            ),
            Some(Specular::Ward(p)) if p.alpha_x == p.alpha_y => (
                "ward",
                vec![
                    format!("k_s {}", num(p.ks)),
                    format!("α {}", num(p.alpha_x)),
                ],
            ),
            Some(Specular::Ward(p)) => (
                "ward",
                vec![
                    format!("k_s {}", num(p.ks)),
                    format!("α_x {}", num(p.alpha_x)),
                    format!("α_y {}", num(p.alpha_y)),
                ],
            ),
            Some(Specular::Mirror(p)) => (
                "mirror",
                vec![
                    format!("F0 {}", num(p.f0)),
                    format!("lights {}° in radius", num(self.render.light_radius_deg)),
                ],
            ),
        };
        let specular = with(name, params, colour(m.specular_color));
        match diffuse {
            Some(d) => format!("{specular} over {d}"),
            None if self.brdf == Brdf::Mirror => specular,
            None => format!("{specular}, no diffuse"),
        }
    }

    /// The camera settings.
    fn describe_camera(&self) -> String {
        let o = &self.render;
        let mut parts = vec![format!("noise σ {}", num(f64::from(o.noise_sigma)))];
        if let Some(fw) = o.full_well {
            parts.push(format!("full well {}", num(f64::from(fw))));
        }
        if let Some(level) = o.clip {
            parts.push(format!("clipped at {}", num(f64::from(level))));
        }
        if o.ambient > 0.0 {
            parts.push(format!("ambient {}", num(f64::from(o.ambient))));
        }
        if !o.cast_shadows {
            parts.push("no cast shadows".to_owned());
        }
        if o.area_light_samples > 1 {
            parts.push(format!(
                "area lights {}° in radius ({} samples)",
                num(o.light_radius_deg),
                o.area_light_samples
            ));
        }
        if o.bounces > 0 {
            parts.push(format!(
                "{} bounce{} of interreflection ({} rays)",
                o.bounces,
                if o.bounces == 1 { "" } else { "s" },
                o.bounce_samples
            ));
        }
        parts.push(if o.color { "RGB" } else { "grey" }.to_owned());
        parts.push(format!("seed {}", o.seed));
        parts.join(", ")
    }
}

/// Counts of samples lost to clipping, and black images, for warnings.
fn clipping_warnings(plan: &Plan, rendering: &Rendering) -> Vec<String> {
    let mut warnings = Vec::new();
    if let Some(level) = plan.render.clip {
        let clipped: usize = rendering.saturated.iter().map(|m| m.count()).sum();
        if clipped > 0 {
            let images = rendering.saturated.iter().filter(|m| m.count() > 0).count();
            warnings.push(format!(
                "{clipped} pixel samples in {images} of {} images were clipped at --saturation {level} (they read back as saturated)",
                rendering.images.len()
            ));
        }
    }
    if plan.format != ImageFormat::Exr {
        let above: usize = rendering
            .images
            .iter()
            .flatten()
            .map(|p| p.data().iter().filter(|v| **v > 1.0).count())
            .sum();
        if above > 0 {
            warnings.push(format!(
                "{above} samples above 1 were clipped to 1 in the PNGs (and will read as saturated); lower --albedo-value, --specular or --ambient, or use --format exr"
            ));
        }
    }
    let black = rendering
        .images
        .iter()
        .filter(|planes| planes.iter().all(|p| p.data().iter().all(|v| *v <= 0.0)))
        .count();
    if black > 0 {
        let hint = if plan.brdf == Brdf::Mirror {
            ": no mirror highlight falls on a pixel centre; raise --light-radius or --size"
        } else {
            ""
        };
        warnings.push(format!(
            "{black} of {} images are entirely black{hint}",
            rendering.images.len()
        ));
    }
    warnings
}

/// Renders and writes the data set; prints warnings to stderr and returns the summary line.
fn run(plan: &Plan) -> Result<String> {
    let rendering = match &plan.near {
        Some((placement, camera)) => {
            render_near(&plan.scene, &plan.lights, camera, placement, &plan.render)
        }
        None => render(&plan.scene, &plan.lights, &plan.render),
    }
    .context("rendering failed")?;
    ensure!(
        rendering.truth.mask.count() > 0,
        "the scene covers no pixel"
    );
    let warnings = clipping_warnings(plan, &rendering);
    let camera = plan.near.as_ref().map(|(_, k)| k);
    let written =
        write_synthetic_with_camera(&rendering, &plan.lights, camera, &plan.output, plan.format)
            .with_context(|| format!("cannot write the data set to {}", plan.output.display()))?;
    for w in warnings {
        eprintln!("warning: {w}");
    }
    Ok(format!(
        "wrote {} files to {}: {} {} images {}×{} of {}, {}, {}, camera: {}; lights.json, mask.png{}{}, ground truth and shadow masks",
        written.len(),
        plan.output.display(),
        plan.lights.len(),
        match plan.format {
            ImageFormat::Exr => "EXR",
            ImageFormat::Png16 => "16-bit PNG",
            ImageFormat::Png8 { srgb: true } => "8-bit sRGB PNG",
            ImageFormat::Png8 { srgb: false } => "8-bit linear PNG",
        },
        plan.scene.width,
        plan.scene.height,
        value_name(plan.shape),
        plan.describe_material(),
        plan.lights_summary,
        plan.describe_camera(),
        if plan.near.is_some() { ", K.txt" } else { "" },
        if rendering.ambient.is_some() {
            format!(
                ", {}.{} (every lamp off: pass it as --ambient)",
                photostereo::synth::write::AMBIENT_STEM,
                plan.format.extension()
            )
        } else {
            String::new()
        },
    ))
}

/// Parses the flags, renders, writes, and prints the summary; every error (clap's included)
/// prints as `error: ...` with exit status 1.
fn main() {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        // --help and --version print to stdout and succeed.
        Err(e) if !e.use_stderr() => e.exit(),
        Err(e) => {
            // Printing can only fail when stderr is gone; the status still says it all.
            let _ = e.print();
            std::process::exit(1);
        }
    };
    let result = cli.plan().and_then(|plan| {
        for w in &plan.warnings {
            eprintln!("warning: {w}");
        }
        run(&plan)
    });
    match result {
        Ok(summary) => println!("{summary}"),
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::exit(1);
        }
    }
}

/// Flag parsing and validation, without rendering.
#[cfg(test)]
mod tests {
    use super::*;

    /// An output folder that planning never creates.
    const OUT: &str = "/nonexistent/data-synth-test";

    /// Parses a command line (program name and `-o` added).
    fn cli(args: &[&str]) -> Cli {
        Cli::try_parse_from(
            std::iter::once("data-synth")
                .chain(args.iter().copied())
                .chain(["-o", OUT]),
        )
        .expect("flags parse")
    }

    /// The plan of `args`.
    fn plan(args: &[&str]) -> Plan {
        cli(args)
            .plan()
            .unwrap_or_else(|e| panic!("{args:?}: {e:#}"))
    }

    /// The error message of planning `args`.
    fn plan_error(args: &[&str]) -> String {
        format!("{:#}", cli(args).plan().expect_err("should be rejected"))
    }

    /// The defaults, and the per-shape and per-light-set defaults, give a valid plan.
    #[test]
    fn defaults_make_a_valid_plan() {
        let p = plan(&[]);
        assert_eq!((p.scene.width, p.scene.height), (256, 256));
        assert_eq!(p.lights.len(), 12);
        assert_eq!(p.lights_summary, "12 fibonacci lights above 30°");
        assert_eq!(p.render, RenderOptions::default());
        assert_eq!(p.format, ImageFormat::Exr);
        assert_eq!(p.material(), Material::lambertian());
        assert!(p.warnings.is_empty());
        assert_eq!(p.describe_camera(), "noise σ 0, grey, seed 0");
        let camera = plan(&[
            "--noise",
            "0.01",
            "--full-well",
            "1000",
            "--saturation",
            "0.8",
            "--ambient",
            "0.05",
            "--no-cast-shadows",
            "--color",
            "--seed",
            "3",
        ]);
        assert_eq!(
            camera.describe_camera(),
            "noise σ 0.01, full well 1000, clipped at 0.8, ambient 0.05, no cast shadows, RGB, seed 3"
        );
        let transport = plan(&[
            "--shape",
            "groove",
            "--bounces",
            "2",
            "--bounce-samples",
            "32",
            "--area-light-samples",
            "16",
            "--light-radius",
            "4",
        ]);
        assert_eq!(
            (
                transport.render.bounces,
                transport.render.bounce_samples,
                transport.render.area_light_samples,
                transport.render.light_radius_deg
            ),
            (2, 32, 16, 4.0)
        );
        assert_eq!(
            transport.describe_camera(),
            "noise σ 0, area lights 4° in radius (16 samples), 2 bounces of interreflection (32 rays), grey, seed 0"
        );
        // The help states the library's default light radius.
        let help = <Cli as clap::CommandFactory>::command()
            .render_long_help()
            .to_string();
        assert!(
            help.contains(&format!("[default: {DEFAULT_LIGHT_RADIUS_DEG}]")),
            "--light-radius help is out of date"
        );
        let demo = plan(&["--shape", "demo"]);
        assert_eq!((demo.scene.width, demo.scene.height), (320, 240));
        assert_eq!(
            plan(&["--light-set", "ring"]).lights_summary,
            "12 ring lights at 45°"
        );
        assert_eq!(plan(&["--light-set", "diligent"]).lights.len(), 96);
        // The library's sphere and --radius 0.4·size are the same scene.
        assert_eq!(
            plan(&["--size", "50", "--radius", "20"]).scene,
            plan(&["--size", "50"]).scene
        );
    }

    /// Every scene of the library has a `--shape` value of the same name, and it builds a
    /// scene that covers pixels even at the smallest size.
    #[test]
    fn every_scene_kind_is_a_shape() {
        assert_eq!(ShapeArg::value_variants().len(), SceneKind::ALL.len());
        for kind in SceneKind::ALL {
            let shape = ShapeArg::from_str(kind.name(), false)
                .unwrap_or_else(|e| panic!("{}: {e}", kind.name()));
            assert_eq!(shape.kind(), kind);
            let size = if kind == SceneKind::Demo {
                vec![]
            } else {
                vec!["--size", "8"]
            };
            let mut args = vec!["--shape", kind.name()];
            args.extend(size);
            let p = plan(&args);
            assert!(p.scene.height_field().mask.count() > 0, "{}", kind.name());
        }
    }

    /// Each model builds the material of its defaults, and its parameters reach it.
    #[test]
    fn models_and_their_defaults() {
        let m = |args: &[&str]| plan(args).material();
        let on = m(&["--brdf", "oren-nayar"]);
        assert_eq!(
            on.diffuse,
            Diffuse::OrenNayar {
                sigma: 20f64.to_radians()
            }
        );
        assert_eq!(on.specular, None);
        let bp = m(&["--brdf", "blinn-phong"]);
        assert_eq!(
            bp.specular,
            Some(Specular::BlinnPhong(BlinnPhong {
                ks: 0.5,
                exponent: 40.0
            }))
        );
        assert_eq!(bp.diffuse, Diffuse::Lambertian);
        assert_eq!(
            m(&["--brdf", "phong", "--no-diffuse", "--shininess", "0"]),
            Material {
                diffuse: Diffuse::None,
                specular: Some(Specular::Phong(Phong {
                    ks: 0.5,
                    exponent: 0.0
                })),
                ..Material::lambertian()
            }
        );
        assert_eq!(
            m(&["--brdf", "torrance-sparrow"]).specular,
            Some(Specular::TorranceSparrow(TorranceSparrow {
                ks: 0.5,
                roughness: 0.3,
                f0: 0.04
            }))
        );
        assert_eq!(
            m(&["--brdf", "ward", "--roughness", "0.1"]).specular,
            Some(Specular::Ward(Ward {
                ks: 0.5,
                alpha_x: 0.1,
                alpha_y: 0.1
            }))
        );
        assert_eq!(
            m(&["--brdf", "ward", "--alpha-y", "0.4"]).specular,
            Some(Specular::Ward(Ward {
                ks: 0.5,
                alpha_x: 0.2,
                alpha_y: 0.4
            }))
        );
        let mirror = m(&["--brdf", "mirror", "--specular-color", "1,0.8,0.3"]);
        assert_eq!(mirror.diffuse, Diffuse::None);
        assert_eq!(mirror.specular, Some(Specular::Mirror(Mirror { f0: 0.8 })));
        assert_eq!(mirror.specular_color, [1.0, 0.8, 0.3]);
        let coloured = m(&["--diffuse-color", "1, 0.5,0.25"]);
        assert_eq!(coloured.diffuse_color, [1.0, 0.5, 0.25]);
        // Every object of a multi-object scene gets the material.
        let p = plan(&["--shape", "bumps", "--brdf", "ward", "--size", "32"]);
        assert!(p.scene.objects.len() > 1);
        assert!(p.scene.objects.iter().all(|o| o.material == p.material()));
        let summary = |args: &[&str]| plan(args).describe_material();
        assert_eq!(
            summary(&["--brdf", "ward", "--alpha-y", "0.4"]),
            "ward (k_s 0.5, α_x 0.2, α_y 0.4) over lambertian"
        );
        assert_eq!(summary(&[]), "lambertian");
        assert_eq!(summary(&["--brdf", "oren-nayar"]), "oren-nayar (σ 20°)");
        assert_eq!(
            summary(&["--brdf", "oren-nayar", "--roughness", "30"]),
            "oren-nayar (σ 30°)"
        );
        assert_eq!(
            summary(&[
                "--brdf",
                "phong",
                "--no-diffuse",
                "--specular-color",
                "1,0.5,0"
            ]),
            "phong (k_s 0.5, n 40, colour 1,0.5,0), no diffuse"
        );
        assert_eq!(
            summary(&["--brdf", "mirror"]),
            "mirror (F0 0.8, lights 1.5° in radius)"
        );
    }

    /// Near-degenerate sets are written with a warning; the others must be usable.
    #[test]
    fn degenerate_sets_warn_instead_of_failing() {
        let p = plan(&["--light-set", "coplanar", "--tilt", "0"]);
        assert_eq!(p.lights.len(), 12);
        assert_eq!(p.warnings.len(), 1);
        assert!(
            p.warnings[0].contains("condition number ∞"),
            "{:?}",
            p.warnings
        );
        let p = plan(&["--light-set", "clustered"]);
        assert!(
            p.warnings[0].contains("condition number"),
            "{:?}",
            p.warnings
        );
        // A random cone this narrow is as bad as a cluster but not meant to be: rejected.
        let e = plan_error(&["--light-set", "cone", "--cone-angle", "0.01"]);
        assert!(e.contains("cannot determine normals"), "{e}");
        // The cone is about the viewing axis, within its half angle.
        let cone = plan(&[
            "--light-set",
            "cone",
            "--cone-angle",
            "30",
            "--lights",
            "200",
        ])
        .lights;
        let cos = 30f64.to_radians().cos();
        assert!(cone.directions().iter().all(|d| d.z >= cos - 1e-12));
        assert!(
            cone.directions()
                .iter()
                .any(|d| d.z < 28f64.to_radians().cos())
        );
        // The random sets follow the seed.
        let a = plan(&["--light-set", "cone", "--seed", "1"]).lights;
        assert_eq!(a, plan(&["--light-set", "cone", "--seed", "1"]).lights);
        assert_ne!(a, plan(&["--light-set", "cone", "--seed", "2"]).lights);
    }

    /// Every rejected value names its flag in the message.
    #[test]
    fn bad_values_name_their_flag() {
        for (args, flag) in [
            (&["--lights", "2"][..], "--lights"),
            (&["--size", "4"], "--size"),
            (&["--radius", "0"], "--radius"),
            (&["--radius", "200"], "--radius"),
            (&["--radius", "NaN"], "--radius"),
            (&["--shape", "bumps", "--radius", "10"], "--radius"),
            (&["--shape", "demo", "--size", "64"], "--size"),
            (&["--shape", "demo", "--albedo", "checker"], "--albedo"),
            (&["--albedo-value", "0"], "--albedo-value"),
            (
                &["--albedo", "smooth", "--albedo-value", "0.9"],
                "--albedo-value",
            ),
            (&["--noise", "-1"], "--noise"),
            (&["--ambient", "inf"], "--ambient"),
            (&["--full-well", "0"], "--full-well"),
            (&["--saturation", "-1"], "--saturation"),
            (&["--saturation", "2", "--format", "png16"], "--saturation"),
            (&["--srgb"], "--srgb"),
            (&["--srgb", "--format", "png16"], "--srgb"),
            (&["--elevation", "90"], "--elevation"),
            (&["--light-set", "ring", "--elevation", "90"], "--elevation"),
            (&["--light-set", "cone", "--elevation", "30"], "--elevation"),
            (
                &["--light-set", "cone", "--cone-angle", "95"],
                "--cone-angle",
            ),
            (
                &["--light-set", "ring", "--cone-angle", "10"],
                "--cone-angle",
            ),
            (&["--tilt", "2"], "--tilt"),
            (&["--light-set", "coplanar", "--tilt", "-1"], "--tilt"),
            (
                &[
                    "--light-set",
                    "clustered",
                    "--elevation",
                    "10",
                    "--cone-angle",
                    "20",
                ],
                "--cone-angle",
            ),
            (&["--light-set", "diligent", "--lights", "96"], "--lights"),
            (&["--brdf", "ward", "--shininess", "10"], "--shininess"),
            (&["--brdf", "lambertian", "--specular", "0.2"], "--specular"),
            (&["--roughness", "0.2"], "--roughness"),
            (&["--brdf", "phong", "--roughness", "0.2"], "--roughness"),
            (&["--brdf", "oren-nayar", "--no-diffuse"], "--no-diffuse"),
            (&["--brdf", "oren-nayar", "--roughness", "0"], "--roughness"),
            (
                &["--brdf", "oren-nayar", "--roughness", "90"],
                "--roughness",
            ),
            (&["--brdf", "ward", "--roughness", "0"], "--roughness"),
            (&["--brdf", "ward", "--alpha-y", "-0.1"], "--alpha-y"),
            (&["--brdf", "blinn-phong", "--alpha-y", "0.1"], "--alpha-y"),
            (
                &["--brdf", "torrance-sparrow", "--roughness", "inf"],
                "--roughness",
            ),
            (&["--brdf", "phong", "--specular", "1.5"], "--specular"),
            (&["--brdf", "phong", "--shininess", "-1"], "--shininess"),
            (&["--brdf", "phong", "--f0", "0.5"], "--f0"),
            (&["--brdf", "mirror", "--specular", "0.5"], "--specular"),
            (&["--brdf", "mirror", "--f0", "1.1"], "--f0"),
            (&["--brdf", "torrance-sparrow", "--f0", "-0.1"], "--f0"),
            (
                &["--brdf", "mirror", "--diffuse-color", "1,1,1"],
                "--diffuse-color",
            ),
            (
                &["--brdf", "mirror", "--albedo-value", "0.5"],
                "--albedo-value",
            ),
            (
                &["--brdf", "ward", "--no-diffuse", "--albedo", "checker"],
                "--albedo",
            ),
            (&["--specular-color", "1,1,1"], "--specular-color"),
            (&["--diffuse-color", "1,0.5"], "--diffuse-color"),
            (&["--diffuse-color", "1,0.5,x"], "--diffuse-color"),
            (&["--diffuse-color", "1,0.5,1.2"], "--diffuse-color"),
            (&["--light-radius", "2"], "--light-radius"),
            (&["--bounces", "65"], "--bounces"),
            (&["--bounce-samples", "16"], "--bounce-samples"),
            (
                &["--bounces", "1", "--bounce-samples", "0"],
                "--bounce-samples",
            ),
            (
                &["--bounces", "1", "--bounce-samples", "2000"],
                "--bounce-samples",
            ),
            (
                &[
                    "--bounces",
                    "1",
                    "--bounce-samples",
                    "1024",
                    "--size",
                    "2048",
                ],
                "--bounce-samples",
            ),
            (&["--area-light-samples", "1"], "--area-light-samples"),
            (&["--area-light-samples", "5000"], "--area-light-samples"),
            (
                &["--area-light-samples", "8", "--light-radius", "90"],
                "--light-radius",
            ),
            (
                &["--brdf", "mirror", "--light-radius", "0"],
                "--light-radius",
            ),
        ] {
            let e = plan_error(args);
            assert!(e.contains(flag), "{args:?}: {e}");
        }
    }
}
