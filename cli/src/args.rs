//! Command-line flags and their translation into validated library configuration.

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use photostereo::camera::Intrinsics;
use photostereo::capture::stack::{ColorMode, LoadOptions, Transfer};
use photostereo::eval::bench::{
    integration, interreflections, scaling, specularity, stages, stream,
};
use photostereo::integrate::{BilateralParams, IntegrationOptions, Integrator, LinearSolver};
use photostereo::ps::color::ColorSolve;
use photostereo::ps::interreflection::{self, InterreflectionOptions};
use photostereo::ps::robust::{DEFAULT_SPECULAR_CONE_DEG, DEFAULT_TRIM_HIGH, DEFAULT_TRIM_LOW};
use photostereo::ps::shadows::{DEFAULT_ROUNDS, DEFAULT_SMOOTHNESS, ShadowLabelOptions};
use photostereo::ps::solve::{
    DEFAULT_HIGHLIGHT_FRACTION, DEFAULT_MAX_CONDITION, DEFAULT_SHADOW_THRESHOLD, Method,
    SolveOptions,
};
use photostereo::run::pipeline::Config;
use std::path::{Path, PathBuf};

/// Photometric stereo: images of an object under known distant lights → albedo, normals, depth.
///
/// Run on images:   photostereo images/*.exr --lights lights.json -o out/
/// Run on DiLiGenT: photostereo path/to/catPNG -o out/
/// Built-in scene:  photostereo demo -o out/
#[derive(Debug, Parser)]
#[command(
    name = "photostereo",
    version,
    args_conflicts_with_subcommands = true,
    subcommand_negates_reqs = true,
    arg_required_else_help = true,
    verbatim_doc_comment
)]
pub struct Cli {
    /// Subcommand; without one, reconstruct the given images.
    #[command(subcommand)]
    pub command: Option<Command>,
    /// Reconstruction of images given on the command line.
    #[command(flatten)]
    pub run: RunArgs,
    /// No progress bars.
    #[arg(long, short, global = true)]
    pub quiet: bool,
    /// Worker threads (default: all cores; at most 4 a core).
    #[arg(long, global = true, value_name = "N")]
    pub threads: Option<usize>,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Render the built-in synthetic scene, reconstruct it, and print the error against its
    /// ground truth.
    Demo(DemoArgs),
    /// Angular error of a normal map against ground truth, as JSON.
    Eval(EvalArgs),
    /// Integrate a normal map into depth (EXR), optionally with a mesh (PLY).
    Integrate(IntegrateArgs),
    /// Shape from shading of one image under a known (or estimated) distant light: depth,
    /// normals, the reflectance map's contours and a report.
    Sfs(SfsArgs),
    /// Light calibration: directions from a chrome sphere's highlights, relative intensities
    /// from a matte sphere or grey card; writes a lights file for the main command.
    Calibrate(CalibrateArgs),
    /// Benchmarks, beside the numpy peer where it applies, as JSON.
    #[command(subcommand)]
    Bench(BenchCommand),
}

/// Reconstruction of user images.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// Image files (EXR, PNG, TIFF, JPEG, camera RAW), one per light; or one folder in the DiLiGenT layout; or
    /// one image list (`<name>.txt`: the count, the image paths, optionally the mask).
    #[arg(value_name = "INPUTS")]
    pub inputs: Vec<PathBuf>,
    /// Lights file: JSON {"lights": [{"file", "direction", "intensity"}]} or `x y z` lines.
    #[arg(long, value_name = "FILE")]
    pub lights: Option<PathBuf>,
    /// Object mask (pixels > 0 are solved); default: every pixel (DiLiGenT: its mask.png).
    #[arg(long, value_name = "FILE")]
    pub mask: Option<PathBuf>,
    /// Ambient image: the scene photographed with every lamp off, as the images are (same
    /// camera settings, size and format), subtracted from every image. Room light or a
    /// camera's black level left in the images lifts every shadow and flattens the normals;
    /// the run measures that offset and warns when it matters
    #[arg(long, value_name = "FILE")]
    pub ambient: Option<PathBuf>,
    /// Output folder (refused when it exists and is not empty, unless --force).
    #[arg(long, short, value_name = "DIR")]
    pub output: Option<PathBuf>,
    /// Write into an existing, non-empty output folder, replacing the files this tool writes.
    #[arg(long)]
    pub force: bool,
    /// Solver and integration options.
    #[command(flatten)]
    pub method: MethodArgs,
    /// How images are read.
    #[command(flatten)]
    pub load: LoadArgs,
    /// Memory budget (e.g. 2G, 1536M): a run that would not fit in it loads the images in row
    /// bands instead of whole (PNG without interlacing, TIFF, EXR); one that fits is loaded
    /// whole. Default: 2 GiB, or half the available memory where that is less; a run that
    /// cannot stream in that gets the least budget it can stream in (up to half the available
    /// memory), and one that cannot stream at all is loaded whole where memory allows.
    #[arg(long, value_name = "SIZE")]
    pub max_memory: Option<String>,
    /// Stream in bands of this many rows (default: as many as the budget allows). Alone, it
    /// streams within half the available memory.
    #[arg(long, value_name = "ROWS")]
    pub band_rows: Option<usize>,
    /// Order of the images before a plain list of lights (one that names no image files) is
    /// paired with them by position. `checked`: keep the order given, but refuse numbered names
    /// in text order that differs from numeric order, as a shell glob gives for name.1.png …
    /// name.12.png; `natural`: sort the names numerically (2 before 10); `given`: keep the
    /// order given.
    #[arg(long, value_enum, default_value = "checked", value_name = "ORDER")]
    pub image_order: ImageOrderArg,
}

/// `--image-order` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum ImageOrderArg {
    /// Keep the order given; refuse numbered names sorted as text.
    Checked,
    /// Sort numerically.
    Natural,
    /// Keep the order given.
    Given,
}

impl ImageOrderArg {
    /// The library's image order.
    pub fn order(self) -> photostereo::capture::ImageOrder {
        use photostereo::capture::ImageOrder;
        match self {
            ImageOrderArg::Checked => ImageOrder::Checked,
            ImageOrderArg::Natural => ImageOrder::Natural,
            ImageOrderArg::Given => ImageOrder::AsGiven,
        }
    }
}

/// Solver options shared by the main command and the demo.
#[derive(Debug, Args, Clone)]
pub struct MethodArgs {
    /// Estimator. `auto` (default): least squares with shadow rejection where Lambert's law
    /// fits (χ² test against the image noise), specular rejection where it does not, light
    /// intensities corrected from the data. Linear: `ls` (all samples, the reference),
    /// `threshold` (shadow and saturation rejection), `weighted` (diag(I) rows). Robust:
    /// `trim` (rank trimming), `huber`, `tukey`, `l1` (IRLS), `specular` (half-vector
    /// rejection + Tukey).
    #[arg(long, value_enum, default_value_t = MethodArg::Auto)]
    pub method: MethodArg,
    /// Normal integration: `auto` (masked-ls, or bilateral when the normals show depth jumps;
    /// the choice is reported), `masked-ls` (least squares on the mask only), `poisson` (DCT,
    /// fast, flat background), `path` (mask-aware paths), `fc` (Frankot–Chellappa FFT,
    /// periodic), `bilateral` (discontinuity preserving), or `none`.
    #[arg(long, value_enum, default_value_t = IntegrateArg::Auto)]
    pub integrate: IntegrateArg,
    /// Integration details (camera, solver, bilateral parameters).
    #[command(flatten)]
    pub integration: IntegrationArgs,
    /// Also write the depth map as a triangle mesh, `mesh.ply`.
    #[arg(long)]
    pub mesh: bool,
    /// All but `ls`: drop samples at or below this fraction of the pixel's reference level (its
    /// brightest usable sample once the brightest --highlight-fraction are set aside).
    #[arg(long, default_value_t = DEFAULT_SHADOW_THRESHOLD, value_name = "FRACTION")]
    pub shadow_threshold: f32,
    /// All but `ls`: fraction of each pixel's usable samples, brightest first, that may be
    /// highlights and so do not set the shadow threshold's reference (0: the brightest does).
    #[arg(long, default_value_t = DEFAULT_HIGHLIGHT_FRACTION, value_name = "FRACTION")]
    pub highlight_fraction: f32,
    /// trim: fractions of each pixel's samples dropped from the dark and the bright end.
    #[arg(long, num_args = 2, value_names = ["LOW", "HIGH"],
          default_values_t = [DEFAULT_TRIM_LOW, DEFAULT_TRIM_HIGH])]
    pub trim: Vec<f32>,
    /// specular/auto: half-angle (degrees) of the cone around the normal in which a sample's
    /// half vector marks it specular.
    #[arg(long, default_value_t = DEFAULT_SPECULAR_CONE_DEG, value_name = "DEG")]
    pub specular_cone: f64,
    /// Estimate per-image light-intensity corrections from the data (default: with `auto`);
    /// they are applied only when they converge and fit the images better than the stated
    /// intensities.
    #[arg(long, overrides_with = "no_recalibrate")]
    pub recalibrate: bool,
    /// Never correct the light intensities.
    #[arg(long)]
    pub no_recalibrate: bool,
    /// auto: keep the robust Lambertian fit where Lambert's law fails instead of refitting
    /// those pixels with a diffuse term plus specular lobes (the refit is kept only where it
    /// explains a pixel; it costs 1.5–1.8 s of a run on a DiLiGenT object).
    #[arg(long)]
    pub no_lobes: bool,
    /// auto: noise standard deviation of the samples (after division by intensity), when known;
    /// by default it is estimated from each image.
    #[arg(long, value_name = "SIGMA")]
    pub noise_sigma: Option<f32>,
    /// Flag pixels whose usable lights have a condition number above this.
    #[arg(long, default_value_t = DEFAULT_MAX_CONDITION, value_name = "COND")]
    pub max_condition: f64,
    /// Leave the pixels that cannot be solved alone (fewer than 3 usable samples,
    /// ill-conditioned lights) without a normal instead of filling them in from their samples
    /// and their solved neighbours.
    #[arg(long)]
    pub strict: bool,
    /// Intensities are calibrated so albedo ≤ 1: warn about pixels above it.
    #[arg(long)]
    pub albedo_normalised: bool,
    /// Shadow labelling.
    #[command(flatten)]
    pub shadows: ShadowArgs,
    /// Interreflection compensation.
    #[command(flatten)]
    pub interreflections: InterreflectionArgs,
    /// Near lights.
    #[command(flatten)]
    pub near: NearArgs,
}

/// Near-light options: used when every light in the lights file has a `position` and --camera
/// gives the intrinsics.
#[derive(Debug, Args, Clone)]
pub struct NearArgs {
    /// Solve positioned lights with the distant approximation (each light's `direction`)
    /// instead of the near-light model.
    #[arg(long)]
    pub distant_lights: bool,
    /// Near lights: depth of the start plane along the optical axis, in the units of the light
    /// positions (default: searched from the images around the lights' mean distance).
    #[arg(long, value_name = "DIST", conflicts_with = "distant_lights")]
    pub near_start: Option<f64>,
    /// Near lights: most alternations of normals and depth.
    #[arg(long, default_value_t = photostereo::ps::near::DEFAULT_MAX_ITERATIONS, value_name = "N", conflicts_with = "distant_lights")]
    pub near_iterations: usize,
    /// Near lights: stop when the depth moves by less than this fraction of its range.
    #[arg(long, default_value_t = photostereo::ps::near::DEFAULT_TOLERANCE, value_name = "FRACTION", conflicts_with = "distant_lights")]
    pub near_tolerance: f64,
}

impl NearArgs {
    /// The library's near-light configuration, `None` with --distant-lights.
    pub fn config(&self) -> Result<Option<photostereo::run::pipeline::NearConfig>> {
        if self.distant_lights {
            return Ok(None);
        }
        if let Some(d) = self.near_start
            && !(d.is_finite() && d > 0.0)
        {
            bail!("--near-start {d}: must be a positive distance");
        }
        if self.near_iterations == 0 {
            bail!("--near-iterations must be at least 1");
        }
        if !(self.near_tolerance > 0.0 && self.near_tolerance < 1.0) {
            bail!(
                "--near-tolerance {}: must be in (0, 1)",
                self.near_tolerance
            );
        }
        Ok(Some(photostereo::run::pipeline::NearConfig {
            start_distance: self.near_start,
            max_iterations: self.near_iterations,
            tolerance: self.near_tolerance,
        }))
    }
}

/// Interreflection compensation options.
#[derive(Debug, Args, Clone)]
pub struct InterreflectionArgs {
    /// Compensate interreflections (Nayar, Ikeuchi & Kanade 1991): integrate the normals,
    /// predict the light the surface throws onto itself, subtract it and solve again. Applied
    /// only where the data show it (the residual falls), with the reflectance scale estimated
    /// from the data unless --interreflection-scale gives it. Orthographic shapes only.
    #[arg(long)]
    pub interreflections: bool,
    /// --interreflections: the reflectance per unit albedo (ρ = scale·albedo), when known, e.g.
    /// 1 when the images are divided by the light's irradiance and the camera is radiometric.
    #[arg(long, value_name = "S", requires = "interreflections")]
    pub interreflection_scale: Option<f64>,
    /// --interreflections: rounds of integrate, trace, compensate and solve.
    #[arg(long, default_value_t = interreflection::DEFAULT_ITERATIONS, value_name = "N", requires = "interreflections")]
    pub interreflection_rounds: usize,
    /// --interreflections: cosine-weighted rays per pixel for the form factors.
    #[arg(long, default_value_t = interreflection::DEFAULT_RAYS, value_name = "N", requires = "interreflections")]
    pub interreflection_rays: usize,
}

impl InterreflectionArgs {
    /// The compensation options, `None` when off.
    pub fn options(&self) -> Option<InterreflectionOptions> {
        self.interreflections.then_some(InterreflectionOptions {
            iterations: self.interreflection_rounds,
            rays: self.interreflection_rays,
            scale: self.interreflection_scale,
            ..InterreflectionOptions::default()
        })
    }
}

/// Shadow labelling options, shared by the runs and `eval --diligent`.
#[derive(Debug, Args, Clone)]
pub struct ShadowArgs {
    /// After the solve, label every image's samples lit or shadow as regions (a Potts energy
    /// over the pixel grid, minimised exactly by graph cuts, after ShadowCuts, CVPR 2007) and
    /// refit each pixel from its lit samples: pixels with few lit samples borrow their
    /// neighbours' labels.
    #[arg(long)]
    pub shadow_labels: bool,
    /// --shadow-labels: cost (in nats) of a label change between 4-neighbours.
    #[arg(long, default_value_t = DEFAULT_SMOOTHNESS, value_name = "NATS", requires = "shadow_labels")]
    pub shadow_smoothness: f64,
    /// --shadow-labels: label-and-refit rounds.
    #[arg(long, default_value_t = DEFAULT_ROUNDS, value_name = "N", requires = "shadow_labels")]
    pub shadow_rounds: usize,
}

impl ShadowArgs {
    /// The labelling options, `None` when off.
    pub fn options(&self) -> Option<ShadowLabelOptions> {
        self.shadow_labels.then_some(ShadowLabelOptions {
            smoothness: self.shadow_smoothness,
            rounds: self.shadow_rounds,
        })
    }
}

/// Image reading options.
#[derive(Debug, Args, Clone)]
pub struct LoadArgs {
    /// Colour handling: `grey` (divide by per-channel intensity, mix with BT.601 weights),
    /// `shared` (one normal and an RGB albedo fitted jointly to the three channels) or
    /// `per-channel` (solve R, G and B separately; the normal is the direction of their sum).
    #[arg(long, value_enum, default_value_t = ColorArg::Grey)]
    pub color: ColorArg,
    /// Treat 8-bit images as linear (by default they are decoded as sRGB).
    #[arg(long)]
    pub linear: bool,
    /// Stored value (integers scaled to [0, 1]) at or above which a sample is saturated;
    /// default: the maximum code of integer files, none for float files.
    #[arg(long, value_name = "LEVEL")]
    pub saturation: Option<f32>,
}

/// `demo` options.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Output folder (refused when it exists and is not empty, unless --force).
    #[arg(long, short, value_name = "DIR")]
    pub output: PathBuf,
    /// Write into an existing, non-empty output folder, replacing the files this tool writes.
    #[arg(long)]
    pub force: bool,
    /// Standard deviation of Gaussian image noise (images peak near 1).
    #[arg(long, default_value_t = photostereo::eval::demo::DEFAULT_NOISE)]
    pub noise: f32,
    /// Noise seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Solver and integration options.
    #[command(flatten)]
    pub method: MethodArgs,
}

/// `eval` options.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Estimated normal map (EXR with R, G, B = n_x, n_y, n_z, or an encoded PNG).
    #[arg(long, value_name = "FILE", requires = "gt")]
    pub normals: Option<PathBuf>,
    /// Ground-truth normal map, same layout.
    #[arg(long, value_name = "FILE", requires = "normals")]
    pub gt: Option<PathBuf>,
    /// Estimated depth map (EXR, channel Z).
    #[arg(long, value_name = "FILE", requires = "depth_gt")]
    pub depth: Option<PathBuf>,
    /// Ground-truth depth map (EXR, channel Z).
    #[arg(long, value_name = "FILE", requires = "depth")]
    pub depth_gt: Option<PathBuf>,
    /// How depth is aligned before comparing: `offset` (orthographic: subtract means) or
    /// `median-scale` (perspective: scale by median(gt/estimate)).
    #[arg(long, value_enum, default_value_t = DepthAlign::Offset)]
    pub align: DepthAlign,
    /// Pixels to compare (> 0); default: where both maps are defined.
    #[arg(long, value_name = "FILE")]
    pub mask: Option<PathBuf>,
    /// DiLiGenT-layout folders: reconstruct each with every one of `--methods` and compare
    /// with its `normal_gt.exr` inside its `mask.png` (mean, median, fraction under 5°, 10°,
    /// 20°, timings).
    #[arg(long, value_name = "DIR", num_args = 1.., conflicts_with_all = ["normals", "depth"])]
    pub diligent: Vec<PathBuf>,
    /// With `--diligent`: the estimators to evaluate; lists are comma- or space-separated.
    #[arg(long, value_enum, num_args = 1.., value_delimiter = ',', default_values_t = [MethodArg::Auto])]
    pub methods: Vec<MethodArg>,
    /// With `--diligent`: shadow labelling after each solve.
    #[command(flatten)]
    pub shadows: ShadowArgs,
    /// With `--diligent`: `auto` without the refit with specular lobes.
    #[arg(long)]
    pub no_lobes: bool,
}

/// `--align` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum DepthAlign {
    /// Remove the mean offset.
    Offset,
    /// Scale by the median ratio.
    MedianScale,
}

/// `integrate` options.
#[derive(Debug, Args)]
pub struct IntegrateArgs {
    /// Normal map: EXR (R, G, B = n_x, n_y, n_z) or 8/16-bit PNG encoded n = 2v − 1.
    #[arg(long, value_name = "FILE")]
    pub normals: PathBuf,
    /// Pixels to integrate (> 0); default: where the normals are defined.
    #[arg(long, value_name = "FILE")]
    pub mask: Option<PathBuf>,
    /// Integration method.
    #[arg(long, value_enum, default_value_t = IntegrateArg::Auto)]
    pub method: IntegrateArg,
    /// Integration details.
    #[command(flatten)]
    pub integration: IntegrationArgs,
    /// Output depth map (EXR: channel Z, plus `residual`, and `wu`, `wv` for bilateral).
    #[arg(long, short, value_name = "FILE")]
    pub output: PathBuf,
    /// Also write a triangle mesh of the depth map (binary PLY with normals).
    #[arg(long, value_name = "FILE")]
    pub ply: Option<PathBuf>,
    /// Replace existing output files.
    #[arg(long)]
    pub force: bool,
}

/// `bench` subcommands.
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// End-to-end time on a DiLiGenT-layout folder against `numpy_ps.py diligent`.
    Diligent(BenchArgs),
    /// Time and accuracy of every integrator against image size, and DCT Poisson against
    /// `numpy_ps.py poisson N`.
    Integration(IntegrationBenchArgs),
    /// Normal error of every estimator against specular strength on rendered Blinn–Phong and
    /// Torrance–Sparrow scenes with cast shadows.
    Specularity(SpecularityBenchArgs),
    /// Normal error on rendered concave scenes (V-groove, bowl, relief; a sphere as the
    /// control) with interreflections, without and with compensation (scale known, scale
    /// estimated); JSON to standard output, a chart in `--out`.
    Interreflections(InterreflectionBenchArgs),
    /// Near lights: normal and depth error of the near-light model and of the distant
    /// approximation against the LEDs' distance on rendered scenes (sphere, vase, bumps);
    /// JSON to standard output, a chart in `--out`.
    Near(NearBenchArgs),
    /// Lights recovered from the object (uncalibrated photometric stereo) against the number
    /// of lights and the noise, on rendered scenes with two albedos: light and normal errors,
    /// JSON and a chart.
    FromObject(FromObjectBenchArgs),
    /// Shape from shading: normal and depth error against solve time of every method on
    /// rendered shapes (sphere, vase, peaks, relief, bust) at a frontal and an oblique light;
    /// JSON to standard output, a chart in `--out`.
    Sfs(SfsBenchArgs),
    /// Wall time and peak memory of the in-memory and the streamed (`--max-memory`) run on
    /// the same stack, as child processes, alternating.
    Stream(StreamBenchArgs),
    /// Solve time against pixels × lights per estimator on rendered spheres, with the fitted
    /// log-log slope (1 = linear cost); JSON to standard output, CSV rows to `--csv`.
    Scaling(ScalingBenchArgs),
    /// Error and time of every estimator, shape-from-shading method and integrator against
    /// image noise, light count and specularity on rendered scenes: CSV, JSON and charts
    /// (Pareto fronts included) in `--out`.
    Sweep(SweepBenchArgs),
    /// Everything that feeds `docs/bench` in one run: the sweeps, solver scaling, integrator
    /// timing beside numpy, interreflections and near lights, every shape-from-shading method
    /// on rendered shapes, and DiLiGenT beside the numpy peer when the data is present;
    /// tables, charts and a generated README.md in `--out`.
    All(AllBenchArgs),
}

/// `bench all` options.
#[derive(Debug, Args)]
pub struct AllBenchArgs {
    /// Folder for every table, chart and the generated README.md (required: the
    /// repository's own figures are regenerated with `--out docs/bench`).
    #[arg(long, short, value_name = "DIR", required = true)]
    pub out: PathBuf,
    /// Folder of the real data (DiLiGenT cat and bear under `diligent/`); their part is
    /// skipped, with a message, when absent.
    #[arg(long, value_name = "DIR", default_value = "../shared/data")]
    pub data: PathBuf,
    /// The numpy peer.
    #[command(flatten)]
    pub peer: PeerArgs,
    /// Small sizes and single runs: a smoke run of the whole chain (not for committing).
    #[arg(long)]
    pub quick: bool,
}

/// `bench sweep` options.
#[derive(Debug, Args)]
pub struct SweepBenchArgs {
    /// Image size (square) of the normal and depth sweeps.
    #[arg(long, default_value_t = photostereo::eval::sweep::DEFAULT_SIZE)]
    pub size: usize,
    /// Image size (square) of the shape-from-shading sweep.
    #[arg(long, default_value_t = photostereo::eval::sweep::DEFAULT_SFS_SIZE)]
    pub sfs_size: usize,
    /// Timed runs per point; medians are reported.
    #[arg(long, default_value_t = photostereo::eval::bench::DEFAULT_REPEAT)]
    pub repeat: usize,
    /// Estimators (default: all); lists are comma- or space-separated.
    #[arg(long, value_enum, num_args = 1.., value_delimiter = ',')]
    pub methods: Vec<MethodArg>,
    /// Folder for the tables and charts (required).
    #[arg(long, short, value_name = "DIR", required = true)]
    pub out: PathBuf,
    /// A 64² image and a few levels of each axis: a smoke run of a few seconds.
    #[arg(long)]
    pub quick: bool,
}

/// `bench scaling` options.
#[derive(Debug, Args)]
pub struct ScalingBenchArgs {
    /// Image sizes (square; the sphere fills 0.45 of it); lists are comma- or space-separated.
    #[arg(long, num_args = 1.., value_delimiter = ',', default_values_t = scaling::DEFAULT_SIZES)]
    pub sizes: Vec<usize>,
    /// Light counts (Fibonacci spiral, elevation ≥ 30°); lists are comma- or space-separated.
    #[arg(long, num_args = 1.., value_delimiter = ',', default_values_t = scaling::DEFAULT_LIGHTS)]
    pub lights: Vec<usize>,
    /// Estimators (default: ls, threshold, auto, trim, huber); lists are comma- or space-separated.
    #[arg(long, value_enum, num_args = 1.., value_delimiter = ',')]
    pub methods: Vec<MethodArg>,
    /// Runs per point; medians are reported.
    #[arg(long, default_value_t = photostereo::eval::bench::DEFAULT_REPEAT)]
    pub repeat: usize,
    /// Also write the rows as CSV here.
    #[arg(long, value_name = "FILE")]
    pub csv: Option<PathBuf>,
    /// Also draw time against samples (log-log, slopes in the legend) as STEM.svg and
    /// STEM.png.
    #[arg(long, value_name = "STEM")]
    pub chart: Option<PathBuf>,
}

/// `bench stream` options.
///
/// Example: photostereo bench stream big/ --max-memory 2G (a folder written by
/// `cargo run --release --example large_stack -- big/`).
#[derive(Debug, Args)]
pub struct StreamBenchArgs {
    /// Folder with `img_*` images, `lights.json` and optionally `mask.png`.
    #[arg(value_name = "DIR")]
    pub dir: PathBuf,
    /// Budget of the streamed run.
    #[arg(long, default_value = stream::DEFAULT_MAX_MEMORY, value_name = "SIZE")]
    pub max_memory: String,
    /// Ignore the folder's mask.png (solve the whole frame).
    #[arg(long)]
    pub no_mask: bool,
    /// Integration of both runs.
    #[arg(long, value_enum, default_value_t = IntegrateArg::Poisson)]
    pub integrate: IntegrateArg,
    /// Runs of each; medians are reported.
    #[arg(long, default_value_t = stream::DEFAULT_REPEAT)]
    pub repeat: usize,
}

/// `bench interreflections` options.
#[derive(Debug, Args)]
pub struct InterreflectionBenchArgs {
    /// Image size (square).
    #[arg(long, default_value_t = interreflections::DEFAULT_SIZE)]
    pub size: usize,
    /// Number of lights (Fibonacci spiral up to 60° from the view direction).
    #[arg(long, default_value_t = interreflections::DEFAULT_LIGHTS)]
    pub lights: usize,
    /// The surfaces' albedo (their reflectance).
    #[arg(long, default_value_t = interreflections::DEFAULT_ALBEDO)]
    pub albedo: f64,
    /// Write `interreflections.json` and the chart `interreflections.svg/.png` here.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Also print a Markdown table (to standard error).
    #[arg(long)]
    pub markdown: bool,
}

/// `bench from-object` options.
#[derive(Debug, Args)]
pub struct FromObjectBenchArgs {
    /// Image size (square).
    #[arg(long, default_value_t = 128)]
    pub size: usize,
    /// Light counts; lists are comma- or space-separated.
    #[arg(long, num_args = 1.., value_delimiter = ',', default_values_t = photostereo::eval::from_object::DEFAULT_COUNTS)]
    pub counts: Vec<usize>,
    /// Noise levels (relative to the mean image level).
    #[arg(long, num_args = 1.., value_delimiter = ',', default_values_t = photostereo::eval::from_object::DEFAULT_NOISES)]
    pub noises: Vec<f32>,
    /// Write `from_object.json` and the chart `from_object.svg/.png` here.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Also print a Markdown table (to standard error).
    #[arg(long)]
    pub markdown: bool,
}

/// `bench sfs` options.
#[derive(Debug, Args)]
pub struct SfsBenchArgs {
    /// Image size (square).
    #[arg(long, default_value_t = 128)]
    pub size: usize,
    /// Light slants from the view, degrees; lists are comma- or space-separated.
    #[arg(long, num_args = 1.., value_delimiter = ',', default_values_t = photostereo::eval::sfs::DEFAULT_SLANTS)]
    pub slants: Vec<f64>,
    /// Azimuths of the oblique lights, degrees (x right, y up); lists are comma- or
    /// space-separated. Where an object's detail lies relative to the brightest point of a
    /// smooth convex surface depends on it, and so does Horn's result.
    #[arg(long, num_args = 1.., value_delimiter = ',', default_values_t = photostereo::eval::sfs::DEFAULT_AZIMUTHS)]
    pub azimuths: Vec<f64>,
    /// The methods to run (default: all); lists are comma- or space-separated.
    #[arg(long, num_args = 1.., value_delimiter = ',', value_name = "METHOD")]
    pub methods: Vec<SfsMethodArg>,
    /// Write `sfs.json` and the chart `sfs.svg/.png` here.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Also print a Markdown table (to standard error).
    #[arg(long)]
    pub markdown: bool,
}

/// `bench near` options.
#[derive(Debug, Args)]
pub struct NearBenchArgs {
    /// Image size (square).
    #[arg(long, default_value_t = 128)]
    pub size: usize,
    /// Number of LEDs.
    #[arg(long, default_value_t = 16)]
    pub lights: usize,
    /// Read noise relative to the mean image level.
    #[arg(long, default_value_t = 0.01)]
    pub noise: f32,
    /// LED profile exponent μ (cos^μ).
    #[arg(long, default_value_t = 1.0)]
    pub mu: f64,
    /// Light distances in object sizes; lists are comma- or space-separated.
    #[arg(long, num_args = 1.., value_delimiter = ',', default_values_t = photostereo::eval::near::DEFAULT_DISTANCES)]
    pub distances: Vec<f64>,
    /// Write `near.json` and the chart `near.svg/.png` here.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Also print a Markdown table (to standard error).
    #[arg(long)]
    pub markdown: bool,
}

/// `bench specularity` options.
#[derive(Debug, Args)]
pub struct SpecularityBenchArgs {
    /// Image size (square).
    #[arg(long, default_value_t = specularity::DEFAULT_SIZE)]
    pub size: usize,
    /// Number of lights (Fibonacci spiral up to 60° from the view direction).
    #[arg(long, default_value_t = specularity::DEFAULT_LIGHTS)]
    pub lights: usize,
    /// Specular reflectances k_s to sweep; lists are comma- or space-separated.
    #[arg(long, num_args = 1.., value_delimiter = ',', default_values_t = specularity::DEFAULT_KS)]
    pub ks: Vec<f64>,
    /// Gaussian image noise σ (images peak near 1).
    #[arg(long, default_value_t = specularity::DEFAULT_NOISE)]
    pub noise: f32,
    /// Fraction of each pixel's samples, brightest first, kept out of the shadow threshold's
    /// reference (see the main command's flag of the same name).
    #[arg(long, default_value_t = DEFAULT_HIGHLIGHT_FRACTION, value_name = "FRACTION")]
    pub highlight_fraction: f32,
    /// Estimators to compare (default: all); lists are comma- or space-separated.
    #[arg(long, value_enum, num_args = 1.., value_delimiter = ',')]
    pub methods: Vec<MethodArg>,
    /// Also print a Markdown table (to standard error).
    #[arg(long)]
    pub markdown: bool,
}

/// `bench integration` options.
#[derive(Debug, Args)]
pub struct IntegrationBenchArgs {
    /// Image sizes (square); lists are comma- or space-separated.
    #[arg(long, num_args = 1.., value_delimiter = ',', default_values_t = integration::DEFAULT_SIZES)]
    pub sizes: Vec<usize>,
    /// Methods to time (default: all); lists are comma- or space-separated.
    #[arg(long, value_enum, num_args = 1.., value_delimiter = ',')]
    pub methods: Vec<IntegrateArg>,
    /// Repetitions at sizes up to 512² (one run above); medians are reported.
    #[arg(long, default_value_t = photostereo::eval::bench::DEFAULT_REPEAT)]
    pub repeat: usize,
    /// The numpy peer.
    #[command(flatten)]
    pub peer: PeerArgs,
    /// Also write the rows as CSV here.
    #[arg(long, value_name = "FILE")]
    pub csv: Option<PathBuf>,
    /// Also draw time against pixels (log-log, fitted slopes in the legend) as STEM.svg and
    /// STEM.png.
    #[arg(long, value_name = "STEM")]
    pub chart: Option<PathBuf>,
}

/// The numpy peer a benchmark runs beside photostereo.
#[derive(Debug, Args)]
pub struct PeerArgs {
    /// The numpy peer script to time beside photostereo (skipped when absent).
    #[arg(
        long = "peer",
        value_name = "SCRIPT",
        default_value = "../shared/peers/numpy_ps.py"
    )]
    pub script: PathBuf,
    /// Python interpreter for the peer.
    #[arg(long, default_value = "python3")]
    pub python: String,
}

/// `bench diligent` options.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// DiLiGenT-layout folder to time.
    #[arg(value_name = "DIR")]
    pub dir: PathBuf,
    /// The numpy peer.
    #[command(flatten)]
    pub peer: PeerArgs,
    /// Repetitions; medians are reported.
    #[arg(long, default_value_t = stages::DEFAULT_REPEAT)]
    pub repeat: usize,
    /// Solver and integration options.
    #[command(flatten)]
    pub method: MethodArgs,
}

/// `--method` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum MethodArg {
    /// Lambertian where it fits, specular rejection where not (default).
    Auto,
    /// Plain least squares.
    Ls,
    /// Least squares with shadow and saturation rejection.
    Threshold,
    /// Intensity-weighted least squares with rejection.
    Weighted,
    /// Rank trimming of the darkest and brightest samples.
    Trim,
    /// IRLS, Huber loss.
    Huber,
    /// IRLS, Tukey biweight.
    Tukey,
    /// IRLS, L1 loss.
    L1,
    /// Half-vector specular rejection + Tukey IRLS.
    Specular,
}

impl MethodArg {
    /// The library method.
    pub fn method(self) -> Method {
        match self {
            MethodArg::Auto => Method::Auto,
            MethodArg::Ls => Method::LeastSquares,
            MethodArg::Threshold => Method::Threshold,
            MethodArg::Weighted => Method::ShadowWeighted,
            MethodArg::Trim => Method::Trimmed,
            MethodArg::Huber => Method::Huber,
            MethodArg::Tukey => Method::Tukey,
            MethodArg::L1 => Method::L1,
            MethodArg::Specular => Method::Specular,
        }
    }
}

/// `--integrate` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum IntegrateArg {
    /// DCT Poisson.
    Poisson,
    /// Path integration.
    Path,
    /// Frankot–Chellappa.
    Fc,
    /// Masked least squares.
    MaskedLs,
    /// Bilateral normal integration.
    Bilateral,
    /// Masked least squares, or bilateral when the normals show depth jumps.
    Auto,
    /// No depth.
    None,
}

impl IntegrateArg {
    /// The library method, or `None` for no depth.
    pub fn method(self) -> Option<Integrator> {
        match self {
            IntegrateArg::Poisson => Some(Integrator::Poisson),
            IntegrateArg::Path => Some(Integrator::Path),
            IntegrateArg::Fc => Some(Integrator::FrankotChellappa),
            IntegrateArg::MaskedLs => Some(Integrator::MaskedLs),
            IntegrateArg::Bilateral => Some(Integrator::Bilateral),
            IntegrateArg::Auto => Some(Integrator::Auto),
            IntegrateArg::None => None,
        }
    }
}

/// `--solver` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum SolverArg {
    /// Direct up to 100 000 unknowns, multigrid-preconditioned conjugate gradients beyond.
    Auto,
    /// Sparse Cholesky.
    Direct,
    /// Preconditioned conjugate gradients (DCT for masked-ls, Jacobi for bilateral).
    Cg,
    /// Conjugate gradients preconditioned with multigrid (linear time and memory): on the pixel
    /// grid for masked-ls and bilateral's reweighting steps; for bilateral's re-integration the
    /// grid's smoothing with a coarse level of aggregates that never join the two sides of a cut.
    Multigrid,
}

/// Options of normal integration shared by the main command, `demo` and `integrate`.
#[derive(Debug, Args, Clone)]
pub struct IntegrationArgs {
    /// Pinhole intrinsics K (3×3 text file, pixels) for perspective integration; depth is then
    /// the distance along the optical axis, up to scale.
    #[arg(long, value_name = "K.txt")]
    pub camera: Option<PathBuf>,
    /// Linear solver of `masked-ls` (auto: direct up to 100 000 pixels, conjugate gradients
    /// preconditioned with multigrid on the pixel grid beyond, in at most 56 bytes a pixel of the
    /// mask's bounding box) and `bilateral` (auto: each reweighting step by
    /// multigrid-preconditioned conjugate gradients to the published tolerance; cg: Jacobi, as
    /// published; direct: exact steps, a different fixed point).
    #[arg(long, value_enum, default_value_t = SolverArg::Auto)]
    pub solver: SolverArg,
    /// Bilateral: sigmoid sharpness k (larger keeps more discontinuities).
    #[arg(long, default_value_t = BilateralParams::default().k, value_name = "K")]
    pub bilateral_k: f64,
    /// Bilateral: iteration limit.
    #[arg(long, default_value_t = BilateralParams::default().max_iter, value_name = "N")]
    pub bilateral_iterations: usize,
    /// Bilateral: stop when the energy changes by less than this, relatively (with the
    /// re-integration the steps also stop once three in a row have changed no edge's class).
    #[arg(long, default_value_t = BilateralParams::default().tol, value_name = "TOL")]
    pub bilateral_tol: f64,
    /// Bilateral: return the published method's soft-weighted depth, without the final
    /// re-integration over the cut edges (which is more accurate and does not depend on the
    /// inner solver's tolerance).
    #[arg(long)]
    pub bilateral_published: bool,
}

impl IntegrationArgs {
    /// Library options for `method`.
    pub fn options(&self, method: Integrator) -> Result<IntegrationOptions> {
        if !(self.bilateral_k.is_finite() && self.bilateral_k > 0.0) {
            bail!(
                "--bilateral-k {}: must be a positive number",
                self.bilateral_k
            );
        }
        if self.bilateral_iterations == 0 {
            bail!("--bilateral-iterations must be at least 1");
        }
        if !(self.bilateral_tol >= 0.0 && self.bilateral_tol.is_finite()) {
            bail!("--bilateral-tol {}: must be ≥ 0", self.bilateral_tol);
        }
        let camera = match &self.camera {
            Some(path) => Some(Intrinsics::from_file(path)?),
            None => None,
        };
        Ok(IntegrationOptions {
            method,
            camera,
            solver: match self.solver {
                SolverArg::Auto => LinearSolver::Auto,
                SolverArg::Direct => LinearSolver::Direct,
                SolverArg::Cg => LinearSolver::ConjugateGradient,
                SolverArg::Multigrid => LinearSolver::Multigrid,
            },
            bilateral: BilateralParams {
                k: self.bilateral_k,
                max_iter: self.bilateral_iterations,
                tol: self.bilateral_tol,
                reintegrate: !self.bilateral_published,
                ..BilateralParams::default()
            },
            max_memory: None,
        })
    }
}

/// `--color` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum ColorArg {
    /// BT.601 grey mix.
    Grey,
    /// One normal, RGB albedo, fitted jointly to R, G and B.
    Shared,
    /// Separate R, G, B solves.
    PerChannel,
}

impl MethodArgs {
    /// The library configuration these flags describe.
    pub fn config(&self) -> Result<Config> {
        let solve = SolveOptions {
            method: self.method.method(),
            shadow_threshold: self.shadow_threshold,
            highlight_fraction: self.highlight_fraction,
            max_condition: self.max_condition,
            trim_low: self.trim.first().copied().unwrap_or(DEFAULT_TRIM_LOW),
            trim_high: self.trim.get(1).copied().unwrap_or(DEFAULT_TRIM_HIGH),
            specular_cone_deg: self.specular_cone,
            recalibrate: if self.no_recalibrate {
                Some(false)
            } else if self.recalibrate {
                Some(true)
            } else {
                None
            },
            noise_sigma: self.noise_sigma,
            fill: !self.strict,
            shadow_labels: self.shadows.options(),
            lobes: !self.no_lobes,
            ..SolveOptions::default()
        };
        solve.validate()?;
        let interreflections = self.interreflections.options();
        if let Some(o) = &interreflections {
            o.validate()?;
        }
        Ok(Config {
            solve,
            integration: match self.integrate.method() {
                Some(m) => Some(self.integration.options(m)?),
                None => None,
            },
            albedo_normalised: self.albedo_normalised,
            mesh: self.mesh,
            color: ColorSolve::default(),
            interreflections,
            near: self.near.config()?,
        })
    }
}

impl LoadArgs {
    /// How the channels of an RGB load are solved.
    pub fn color_solve(&self) -> ColorSolve {
        match self.color {
            ColorArg::PerChannel => ColorSolve::PerChannel,
            ColorArg::Grey | ColorArg::Shared => ColorSolve::SharedNormal,
        }
    }

    /// The library load options these flags describe.
    pub fn options(&self) -> Result<LoadOptions> {
        if let Some(s) = self.saturation
            && !(s.is_finite() && s > 0.0)
        {
            bail!("--saturation {s}: must be a positive level");
        }
        Ok(LoadOptions {
            color: match self.color {
                ColorArg::Grey => ColorMode::Grey,
                ColorArg::Shared | ColorArg::PerChannel => ColorMode::PerChannel,
            },
            transfer: if self.linear {
                Transfer::Linear
            } else {
                Transfer::Auto
            },
            saturation: self.saturation,
            window: None,
        })
    }
}

/// Where the images of a run come from.
pub enum Source {
    /// A DiLiGenT-layout folder.
    Diligent(PathBuf),
    /// Image files with a lights file.
    Files {
        /// Images in command-line order.
        images: Vec<PathBuf>,
        /// The lights file.
        lights: PathBuf,
        /// How the images are ordered before plain lights are paired with them.
        order: photostereo::capture::ImageOrder,
    },
}

/// A validated main-command configuration.
pub struct RunConfig {
    /// Input.
    pub source: Source,
    /// Mask file.
    pub mask: Option<PathBuf>,
    /// Ambient image file.
    pub ambient: Option<PathBuf>,
    /// Output folder.
    pub output: PathBuf,
    /// Image reading.
    pub load: LoadOptions,
    /// What to compute.
    pub config: Config,
    /// Stream in row bands within a memory budget (`--max-memory`).
    pub stream: Option<photostereo::run::stream::StreamOptions>,
    /// `--band-rows`, for a run that streams without `--max-memory`.
    pub band_rows: Option<usize>,
    /// The output folder's lock, held for the run (released when the configuration is
    /// dropped).
    pub _lock: photostereo::io::output::OutputLock,
}

impl RunArgs {
    /// Validates the flags of the main command.
    pub fn validate(self) -> Result<RunConfig> {
        if self.inputs.is_empty() {
            bail!(
                "no input images: give image files and --lights FILE, or a DiLiGenT folder (see --help), or run `photostereo demo -o out/`"
            );
        }
        let missing: Vec<&PathBuf> = self.inputs.iter().filter(|p| !p.exists()).collect();
        match (&missing[..], self.inputs.len()) {
            ([], _) => {}
            ([one], 1) => bail!("{}: no such file or folder", one.display()),
            ([one], n) => bail!("{}: no such file (1 of the {n} inputs)", one.display()),
            (gone, n) => bail!(
                "{} of the {n} inputs do not exist: {}",
                gone.len(),
                gone.iter()
                    .take(8)
                    .map(|p| p.display().to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
                    + if gone.len() > 8 { ", …" } else { "" }
            ),
        }
        let output = self
            .output
            .context("no output folder: pass -o DIR (see --help)")?;
        {
            let mut inputs: Vec<&Path> = self.inputs.iter().map(PathBuf::as_path).collect();
            inputs.extend(self.lights.as_deref());
            inputs.extend(self.mask.as_deref());
            inputs.extend(self.ambient.as_deref());
            inputs.extend(self.method.integration.camera.as_deref());
            photostereo::io::output::ensure_apart(&output, &inputs)?;
        }
        let lock = crate::lock_output(&output, self.force)?;
        let mut list_mask = None;
        let source = if self.inputs.len() == 1 && self.inputs[0].is_dir() {
            let dir = self.inputs[0].clone();
            if !photostereo::capture::dataset::is_diligent_dir(&dir) {
                bail!(
                    "{} is a folder but not in the DiLiGenT layout (filenames.txt, light_directions.txt); pass image files and --lights instead",
                    dir.display()
                );
            }
            if self.lights.is_some() {
                bail!(
                    "--lights is not used with a DiLiGenT folder, which has its own light_directions.txt"
                );
            }
            Source::Diligent(dir)
        } else {
            let lights = self.lights.context(
                "no --lights FILE: give the light directions as JSON or `x y z` lines (see README)",
            )?;
            // One image list (`<name>.txt`, as the classic 12-light sets have) names the
            // images and usually the mask.
            if let [list] = &self.inputs[..]
                && photostereo::capture::dataset::is_image_list(list)
            {
                let list = photostereo::capture::dataset::read_image_list(list)?;
                list_mask = list.mask;
                Source::Files {
                    images: list.images,
                    lights,
                    // The list's order is the one meant.
                    order: photostereo::capture::ImageOrder::AsGiven,
                }
            } else {
                Source::Files {
                    images: self.inputs,
                    lights,
                    order: self.image_order.order(),
                }
            }
        };
        let stream = self
            .max_memory
            .as_deref()
            .map(photostereo::run::stream::parse_size)
            .transpose()?
            .map(|max_memory| photostereo::run::stream::StreamOptions {
                max_memory,
                band_rows: self.band_rows,
            });
        Ok(RunConfig {
            _lock: lock,
            stream,
            band_rows: self.band_rows,
            source,
            mask: self.mask.or(list_mask),
            ambient: self.ambient,
            output,
            load: self.load.options()?,
            config: Config {
                color: self.load.color_solve(),
                ..self.method.config()?
            },
        })
    }
}

/// `calibrate` options.
///
/// Example: photostereo calibrate chrome/*.png --mask chrome/mask.png -o lights.json
#[derive(Debug, Args)]
pub struct CalibrateArgs {
    /// Chrome-sphere images, one per light, in the order of the object's images; or one image
    /// list (`<name>.txt`: the count, the image paths, optionally the mask). With
    /// --from-object: the object's own images.
    #[arg(required = true, value_name = "IMAGES")]
    pub images: Vec<PathBuf>,
    /// Recover the lights from the object's own images, without a calibration object
    /// (uncalibrated photometric stereo: factorisation, integrability, minimum albedo
    /// entropy). Needs the object's mask (--mask) and an albedo of a few distinct values;
    /// expect degrees, not tenths, on real objects.
    #[arg(long, conflicts_with_all = ["matte", "matte_mask", "card_mask", "camera", "ball_radius"])]
    pub from_object: bool,
    /// The chrome sphere's mask (pixels > 0; anti-aliased masks are used at half level).
    /// Default: the image list's mask, else the sphere is detected in the images.
    #[arg(long, value_name = "FILE")]
    pub mask: Option<PathBuf>,
    /// Images of a matte (Lambertian) sphere under the same lights, in the same order, for
    /// relative intensities per colour channel (or one image list).
    #[arg(long, num_args = 1.., value_name = "IMAGES")]
    pub matte: Vec<PathBuf>,
    /// The matte sphere's mask: in the --matte images, or in the chrome images when both
    /// spheres are in one picture. Default with --matte: the list's mask, else detected.
    #[arg(long, value_name = "FILE")]
    pub matte_mask: Option<PathBuf>,
    /// A grey card's mask (in the --matte images if given, else in the chrome images): relative
    /// intensities from the card's mean brightness over n·l.
    #[arg(long, value_name = "FILE", conflicts_with = "matte_mask")]
    pub card_mask: Option<PathBuf>,
    /// The grey card's normal, x,y,z in the camera frame (x right, y up, z to the camera).
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_direction, allow_hyphen_values = true,
          default_value = "0,0,1")]
    pub card_normal: [f64; 3],
    /// Treat 8-bit images as linear (by default they are decoded as sRGB). Matters for the
    /// intensities, hardly for the directions.
    #[arg(long)]
    pub linear: bool,
    /// Stored value (0–1 after scaling integers) at or above which a sample is saturated
    /// (default: the maximum code of integer images; for float images, a maximum shared by
    /// several pixels). Saturated samples are left out of the matte ball's or card's intensity
    /// fit (as are linear values from 0.98 up), and a saturated highlight with another
    /// saturated blob beside it is ambiguous.
    #[arg(long, value_name = "LEVEL")]
    pub saturation: Option<f32>,
    /// The camera's intrinsics K, a text file of 9 numbers (three rows of three, as
    /// numpy.savetxt writes them): a perspective calibration, in which the ball's outline is
    /// fitted as the cone of rays it subtends and each of its pixels reflects its own view ray.
    /// Default: an orthographic camera.
    #[arg(long, value_name = "FILE")]
    pub camera: Option<PathBuf>,
    /// The mirror balls' radius, in the unit the light positions are wanted in (12.7 for a
    /// one-inch ball in millimetres): with two balls in the images, each light's position is
    /// where the rays it reflects off them meet, written as `position` with its uncertainty
    /// (and `direction` from the balls' midpoint). Needs --camera; a mask must then outline
    /// both balls.
    #[arg(long, value_name = "LENGTH", requires = "camera")]
    pub ball_radius: Option<f64>,
    /// Write the lights file even when some lights are in doubt (an ambiguous highlight,
    /// one at the rim, or an uncertainty above the accepted one); they keep their
    /// uncertainty and `"accepted": false` in the file. With --from-object: write the lights
    /// even when the data are not clearly rank 3.
    #[arg(long)]
    pub keep_doubtful: bool,
    /// Output lights file (JSON), written atomically.
    #[arg(long, short, value_name = "FILE")]
    pub output: PathBuf,
    /// Replace an existing output file.
    #[arg(long)]
    pub force: bool,
}

/// `sfs` options.
#[derive(Debug, Args)]
pub struct SfsArgs {
    /// The image (EXR, PNG, TIFF, JPEG or camera RAW; RGB is mixed to grey; 8-bit is decoded as sRGB).
    #[arg(value_name = "IMAGE")]
    pub image: PathBuf,
    /// Light direction x,y,z (towards the light; x right, y up, z to the camera); estimated from
    /// the image when absent.
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_direction, allow_hyphen_values = true)]
    pub light: Option<[f64; 3]>,
    /// Distant light: albedo × light intensity, the brightness of a surface facing the light;
    /// estimated when absent. Perspective: the diffuse albedo ρ alone (the intensity is
    /// --light-intensity) [default: 1].
    #[arg(long, value_name = "A")]
    pub albedo: Option<f64>,
    /// Object mask (pixels > 0); default: all but the black background touching the border.
    #[arg(long, value_name = "FILE")]
    pub mask: Option<PathBuf>,
    /// `horn` (any light in front), `tsai-shah` (oblique light), `fast-marching` (light at the
    /// viewer): a distant light and an orthographic camera; `perspective`: a point light at
    /// --light-position seen through --camera, whose fall-off makes the problem well posed
    /// [default: perspective with --light-position, horn otherwise].
    #[arg(long, value_enum)]
    pub method: Option<SfsMethodArg>,
    /// The camera's intrinsics K (9 numbers, three rows of three), for --method perspective.
    #[arg(long, value_name = "FILE")]
    pub camera: Option<PathBuf>,
    /// The point light's position x,y,z in the camera frame (x right, y up, z to the viewer;
    /// the camera centre is 0,0,0), in the units the depth is wanted in; for --method
    /// perspective.
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_position, allow_hyphen_values = true)]
    pub light_position: Option<[f64; 3]>,
    /// The point light's intensity: the brightness of a white Lambertian surface facing it at
    /// unit distance; for --method perspective [default: 1].
    #[arg(long, value_name = "PHI")]
    pub light_intensity: Option<f64>,
    /// Reflectance model of the surface: any the renderer has but the mirror. Horn and
    /// Tsai–Shah use its reflectance map; perspective needs the light at the camera centre for
    /// any but lambertian; fast marching is Lambertian only.
    #[arg(long, value_enum, default_value_t = SfsBrdfArg::Lambertian)]
    pub brdf: SfsBrdfArg,
    /// oren-nayar σ in degrees [default 20]; torrance-sparrow Beckmann m [0.3]; ward α [0.2].
    #[arg(long, value_name = "R")]
    pub roughness: Option<f64>,
    /// phong and blinn-phong exponent [default 40].
    #[arg(long, value_name = "N")]
    pub shininess: Option<f64>,
    /// Specular reflectance k_s of phong, blinn-phong, ward; torrance-sparrow's scale
    /// [default 0.5].
    #[arg(long, value_name = "KS")]
    pub specular: Option<f64>,
    /// torrance-sparrow's Fresnel reflectance at normal incidence [default 0.04].
    #[arg(long, value_name = "F0")]
    pub f0: Option<f64>,
    /// What the mask's edge is: `occluding` (the object turns away there: start convex) or
    /// `free`.
    #[arg(long, value_enum, default_value_t = BoundaryArg::Occluding)]
    pub boundary: BoundaryArg,
    /// Final smoothness weight of Horn's method.
    #[arg(long, default_value_t = photostereo::sfs::DEFAULT_SMOOTHNESS, value_name = "LAMBDA")]
    pub smoothness: f64,
    /// Distant light: relative brightness E/albedo at or below which a pixel is in shadow.
    /// Perspective: a fraction of the image's 99th percentile in the mask (the fall-off makes
    /// the brightness of a lit pixel depend on its unknown distance).
    #[arg(long, default_value_t = photostereo::sfs::DEFAULT_SHADOW_LEVEL, value_name = "F")]
    pub shadow_level: f64,
    /// Iteration limit (0: the method's default; Horn: for each resolution).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub iterations: usize,
    /// Horn: solve at full resolution only, instead of from a start solved at lower
    /// resolutions (the default when the mask keeps 3 000 pixels at half resolution).
    #[arg(long)]
    pub single_resolution: bool,
    /// Horn: when the result contradicts the occluding boundary on an image too small for a
    /// coarse-to-fine start, do not solve it again upsampled 2× (the default tries, and keeps
    /// that result only when it honours the boundary).
    #[arg(long)]
    pub no_outline_repair: bool,
    /// Horn: run the continuation in the smoothness weight once, instead of repeating it from
    /// its own result while that lowers the energy (faster, and on most shapes less accurate).
    #[arg(long)]
    pub no_restarts: bool,
    /// Horn: refine this surface instead of solving from the convex or plane start: an EXR
    /// whose channel Z holds heights towards the camera in pixels (a depth.exr of this command
    /// or of an orthographic photometric-stereo run, or a sensor's depth converted so, in the
    /// file's own pixels), NaN where unknown; a file whose photostereo:units say otherwise is
    /// refused. A file at another resolution (the same field of view) is resampled to the
    /// image's, its heights scaled with it, and its holes in the mask are filled; it is then
    /// refined at the final smoothness only, so the result is the solution nearest it.
    #[arg(long, value_name = "DEPTH.exr")]
    pub start: Option<PathBuf>,
    /// Perspective: return the swept viscosity solution without the variational refinement
    /// (a least-squares fit of the whole image from it).
    #[arg(long)]
    pub no_refine: bool,
    /// Perspective: weight of the refinement's curvature penalty (larger: smoother; default
    /// 0.01).
    #[arg(long, value_name = "LAMBDA", conflicts_with = "no_refine")]
    pub refine_smoothness: Option<f64>,
    /// Perspective: limit of the refinement's steps (0: its default).
    #[arg(
        long,
        default_value_t = 0,
        value_name = "N",
        conflicts_with = "no_refine"
    )]
    pub refine_iterations: usize,
    /// 8-bit images hold linear values (default: decoded as sRGB).
    #[arg(long)]
    pub linear: bool,
    /// Output folder (refused when it exists and is not empty, unless --force).
    #[arg(long, short, value_name = "DIR")]
    pub output: PathBuf,
    /// Write into an existing, non-empty output folder.
    #[arg(long)]
    pub force: bool,
}

/// Shape-from-shading methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SfsMethodArg {
    /// Horn 1990, height and gradient (Gauss–Newton on the height).
    Horn,
    /// Tsai–Shah 1994, linear.
    TsaiShah,
    /// Kimmel–Sethian 2001, fast marching (light at the viewer).
    FastMarching,
    /// Prados–Faugeras 2005, perspective camera and a point light with fall-off.
    Perspective,
}

/// `sfs --brdf` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SfsBrdfArg {
    /// Ideal diffuse.
    Lambertian,
    /// Rough diffuse (Oren–Nayar 1994), σ = --roughness degrees.
    OrenNayar,
    /// Phong lobe over Lambertian.
    Phong,
    /// Blinn–Phong lobe over Lambertian.
    BlinnPhong,
    /// Torrance–Sparrow microfacets over Lambertian.
    TorranceSparrow,
    /// Ward's isotropic lobe over Lambertian.
    Ward,
}

impl From<SfsMethodArg> for photostereo::sfs::SfsMethod {
    fn from(m: SfsMethodArg) -> Self {
        match m {
            SfsMethodArg::Horn => Self::Horn,
            SfsMethodArg::TsaiShah => Self::TsaiShah,
            SfsMethodArg::FastMarching => Self::FastMarching,
            SfsMethodArg::Perspective => Self::Perspective,
        }
    }
}

/// What the mask's edge is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum BoundaryArg {
    /// An occluding contour, except where the image shows it is none (brighter than a surface
    /// turning away can be: a cut end, a foot on a table), which is reported
    Occluding,
    /// No information.
    Free,
}

impl From<BoundaryArg> for photostereo::sfs::Boundary {
    fn from(b: BoundaryArg) -> Self {
        match b {
            BoundaryArg::Occluding => Self::Occluding,
            BoundaryArg::Free => Self::Free,
        }
    }
}

/// Parses `x,y,z` into a finite, non-zero direction.
fn parse_direction(s: &str) -> Result<[f64; 3]> {
    let [x, y, z] = parse_position(s)?;
    if x == 0.0 && y == 0.0 && z == 0.0 {
        bail!("{s:?}: the direction must be non-zero");
    }
    Ok([x, y, z])
}

/// Three finite numbers x,y,z.
fn parse_position(s: &str) -> Result<[f64; 3]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .with_context(|| format!("{s:?}: expected three numbers x,y,z"))?;
    let [x, y, z] = v[..] else {
        bail!("{s:?}: expected three numbers x,y,z, found {}", v.len());
    };
    if !(x.is_finite() && y.is_finite() && z.is_finite()) {
        bail!("{s:?}: the numbers must be finite");
    }
    Ok([x, y, z])
}

/// Parsing as a user types it: lists with commas or spaces alike, the usage for no arguments,
/// the image order, and `bench all` without a folder refused rather than writing into the
/// repository.
#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> std::result::Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("photostereo").chain(args.iter().copied()))
    }

    #[test]
    fn lists_take_commas_or_spaces() {
        for args in [
            &["bench", "integration", "--sizes", "256,512"][..],
            &["bench", "integration", "--sizes", "256", "512"][..],
        ] {
            match parse(args).unwrap().command {
                Some(Command::Bench(BenchCommand::Integration(a))) => {
                    assert_eq!(a.sizes, [256, 512], "{args:?}")
                }
                other => panic!("{other:?}"),
            }
        }
        for args in [
            &["bench", "scaling", "--lights", "8,16", "--sizes", "64"][..],
            &["bench", "scaling", "--lights", "8", "16", "--sizes", "64"][..],
        ] {
            match parse(args).unwrap().command {
                Some(Command::Bench(BenchCommand::Scaling(a))) => {
                    assert_eq!((a.lights, a.sizes), (vec![8, 16], vec![64]), "{args:?}")
                }
                other => panic!("{other:?}"),
            }
        }
        for args in [
            &["eval", "--diligent", "d", "--methods", "ls,threshold"][..],
            &["eval", "--diligent", "d", "--methods", "ls", "threshold"][..],
        ] {
            match parse(args).unwrap().command {
                Some(Command::Eval(a)) => assert_eq!(a.methods.len(), 2, "{args:?}"),
                other => panic!("{other:?}"),
            }
        }
    }

    #[test]
    fn no_arguments_show_the_usage() {
        let e = parse(&[]).unwrap_err();
        assert_eq!(
            e.kind(),
            clap::error::ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
        );
        assert!(e.to_string().contains("Usage:"), "{e}");
    }

    #[test]
    fn bench_outputs_go_where_the_user_says() {
        let e = parse(&["bench", "all", "--quick"]).unwrap_err();
        assert_eq!(e.kind(), clap::error::ErrorKind::MissingRequiredArgument);
        assert!(e.to_string().contains("--out"), "{e}");
        assert!(parse(&["bench", "sweep", "--quick"]).is_err());
        assert!(parse(&["bench", "all", "--quick", "--out", "/tmp/b"]).is_ok());
    }

    #[test]
    fn image_order_defaults_to_checked() {
        let cli = parse(&["a.png", "--lights", "l.txt", "-o", "o"]).unwrap();
        assert!(matches!(cli.run.image_order, ImageOrderArg::Checked));
        let cli = parse(&[
            "a.png",
            "--lights",
            "l.txt",
            "-o",
            "o",
            "--image-order",
            "natural",
        ])
        .unwrap();
        assert_eq!(
            cli.run.image_order.order(),
            photostereo::capture::ImageOrder::Natural
        );
    }
}
