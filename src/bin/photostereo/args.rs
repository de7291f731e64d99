//! Command-line flags and their translation into validated library configuration.

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use photostereo::input::{ColorMode, LoadOptions, Transfer};
use photostereo::integrate::Integrator;
use photostereo::pipeline::Config;
use photostereo::solve::{DEFAULT_MAX_CONDITION, DEFAULT_SHADOW_THRESHOLD, Method, SolveOptions};
use std::path::PathBuf;

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
    /// Worker threads (default: all cores).
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
    /// Time the pipeline end to end on a DiLiGenT folder, beside the numpy peer, as JSON.
    Bench(BenchArgs),
}

/// Reconstruction of user images.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// Image files (EXR, PNG, TIFF), one per light; or one folder in the DiLiGenT layout.
    #[arg(value_name = "INPUTS")]
    pub inputs: Vec<PathBuf>,
    /// Lights file: JSON {"lights": [{"file", "direction", "intensity"}]} or `x y z` lines.
    #[arg(long, value_name = "FILE")]
    pub lights: Option<PathBuf>,
    /// Object mask (pixels > 0 are solved); default: every pixel (DiLiGenT: its mask.png).
    #[arg(long, value_name = "FILE")]
    pub mask: Option<PathBuf>,
    /// Output folder.
    #[arg(long, short, value_name = "DIR")]
    pub output: Option<PathBuf>,
    /// Solver and integration options.
    #[command(flatten)]
    pub method: MethodArgs,
    /// How images are read.
    #[command(flatten)]
    pub load: LoadArgs,
}

/// Solver options shared by the main command and the demo.
#[derive(Debug, Args, Clone)]
pub struct MethodArgs {
    /// Estimator: `threshold` (least squares over samples that pass shadow and saturation
    /// rejection), `weighted` (the same, rows weighted by intensity: diag(I)·I = diag(I)·L·g),
    /// or `ls` (plain least squares over all samples, the reference).
    #[arg(long, value_enum, default_value_t = MethodArg::Threshold)]
    pub method: MethodArg,
    /// Normal integration: `poisson` (DCT, fast), `path` (mask-aware, averaged paths), `none`.
    #[arg(long, value_enum, default_value_t = IntegrateArg::Poisson)]
    pub integrate: IntegrateArg,
    /// threshold/weighted: drop samples at or below this fraction of the pixel's brightest one.
    #[arg(long, default_value_t = DEFAULT_SHADOW_THRESHOLD, value_name = "FRACTION")]
    pub shadow_threshold: f32,
    /// Flag pixels whose usable lights have a condition number above this.
    #[arg(long, default_value_t = DEFAULT_MAX_CONDITION, value_name = "COND")]
    pub max_condition: f64,
    /// Intensities are calibrated so albedo ≤ 1: warn about pixels above it.
    #[arg(long)]
    pub albedo_normalised: bool,
}

/// Image reading options.
#[derive(Debug, Args, Clone)]
pub struct LoadArgs {
    /// Colour handling: `grey` (divide by per-channel intensity, mix with BT.601 weights) or
    /// `per-channel` (solve R, G and B separately; the normal is their common direction).
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
    /// Output folder.
    #[arg(long, short, value_name = "DIR")]
    pub output: PathBuf,
    /// Standard deviation of Gaussian image noise (images peak near 1).
    #[arg(long, default_value_t = photostereo::demo::DEFAULT_NOISE)]
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
    /// Estimated normal map (EXR with R, G, B = n_x, n_y, n_z).
    #[arg(long, value_name = "FILE")]
    pub normals: PathBuf,
    /// Ground-truth normal map, same layout.
    #[arg(long, value_name = "FILE")]
    pub gt: PathBuf,
    /// Pixels to compare (> 0); default: where both maps are defined.
    #[arg(long, value_name = "FILE")]
    pub mask: Option<PathBuf>,
}

/// `bench` options.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// DiLiGenT-layout folder to time.
    #[arg(value_name = "DIR")]
    pub dir: PathBuf,
    /// The numpy peer script to time beside it (skipped when absent).
    #[arg(
        long,
        value_name = "SCRIPT",
        default_value = "../shared/peers/numpy_ps.py"
    )]
    pub peer: PathBuf,
    /// Python interpreter for the peer.
    #[arg(long, default_value = "python3")]
    pub python: String,
    /// Repetitions; medians are reported.
    #[arg(long, default_value_t = 5)]
    pub repeat: usize,
    /// Solver and integration options.
    #[command(flatten)]
    pub method: MethodArgs,
}

/// `--method` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum MethodArg {
    /// Plain least squares.
    Ls,
    /// Least squares with shadow and saturation rejection.
    Threshold,
    /// Intensity-weighted least squares with rejection.
    Weighted,
}

/// `--integrate` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum IntegrateArg {
    /// DCT Poisson.
    Poisson,
    /// Path integration.
    Path,
    /// No depth.
    None,
}

/// `--color` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum ColorArg {
    /// BT.601 grey mix.
    Grey,
    /// Separate R, G, B solves.
    PerChannel,
}

impl MethodArgs {
    /// The library configuration these flags describe.
    pub fn config(&self) -> Result<Config> {
        let solve = SolveOptions {
            method: match self.method {
                MethodArg::Ls => Method::LeastSquares,
                MethodArg::Threshold => Method::Threshold,
                MethodArg::Weighted => Method::ShadowWeighted,
            },
            shadow_threshold: self.shadow_threshold,
            reject_saturated: true,
            max_condition: self.max_condition,
        };
        solve.validate()?;
        Ok(Config {
            solve,
            integrator: match self.integrate {
                IntegrateArg::Poisson => Some(Integrator::Poisson),
                IntegrateArg::Path => Some(Integrator::Path),
                IntegrateArg::None => None,
            },
            albedo_normalised: self.albedo_normalised,
        })
    }
}

impl LoadArgs {
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
                ColorArg::PerChannel => ColorMode::PerChannel,
            },
            transfer: if self.linear {
                Transfer::Linear
            } else {
                Transfer::Auto
            },
            saturation: self.saturation,
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
    },
}

/// A validated main-command configuration.
pub struct RunConfig {
    /// Input.
    pub source: Source,
    /// Mask file.
    pub mask: Option<PathBuf>,
    /// Output folder.
    pub output: PathBuf,
    /// Image reading.
    pub load: LoadOptions,
    /// What to compute.
    pub config: Config,
}

impl RunArgs {
    /// Validates the flags of the main command.
    pub fn validate(self) -> Result<RunConfig> {
        let output = self
            .output
            .context("no output folder: pass -o DIR (see --help)")?;
        if self.inputs.is_empty() {
            bail!(
                "no input images: give image files and --lights FILE, or a DiLiGenT folder (see --help), or run `photostereo demo -o out/`"
            );
        }
        let source = if self.inputs.len() == 1 && self.inputs[0].is_dir() {
            let dir = self.inputs[0].clone();
            if !photostereo::dataset::is_diligent_dir(&dir) {
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
            Source::Files {
                images: self.inputs,
                lights,
            }
        };
        Ok(RunConfig {
            source,
            mask: self.mask,
            output,
            load: self.load.options()?,
            config: self.method.config()?,
        })
    }
}
