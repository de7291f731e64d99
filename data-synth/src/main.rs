//! `data-synth`: renders synthetic photometric-stereo data sets with ground truth.
//!
//! A scene (a sphere, the library's built-in demo scene, or a pyramid and a Gaussian bump on a
//! ground plane) is rendered under a generated set of distant lights with
//! [`photostereo::render`], and written with [`photostereo::dataset::write_synthetic`]: one image
//! per light (`img_NNN.exr` or `img_NNN.png`), `lights.json` naming them and `mask.png`, with
//! the ground truth in `gt/`: `normal_gt.exr`, `depth_gt.exr`, `albedo_gt.exr`, and per-light
//! shadow masks `shadow_NNN.png`.
//!
//! ```text
//! cargo run -p data-synth -- --shape sphere --lights 24 --noise 0.01 -o scene/
//! photostereo scene/*.exr --lights scene/lights.json --mask scene/mask.png -o out/
//! ```
//!
//! (With `--format png16` use `scene/img_*.png`: `scene/*.png` also matches `mask.png`.)
//!
//! Flags are checked before anything is rendered or written; an invalid value prints
//! `error: ...` naming the flag and exits with status 1, leaving the output folder untouched.

use anyhow::{Context, Result, bail, ensure};
use clap::{Parser, ValueEnum};
use photostereo::dataset::{ImageFormat, write_synthetic};
use photostereo::lights::{Lights, MAX_LIGHT_CONDITION};
use photostereo::render::{RenderOptions, Rendering, render_lambertian};
use photostereo::scene::{Albedo, Primitive, Scene};
use std::path::{Path, PathBuf};

/// Smallest accepted `--size`: below this the bumps scene has no room for its shapes.
const MIN_SIZE: usize = 8;
/// Largest accepted `--size`: bigger images take very long to render (cast shadows are ray
/// marched per pixel and light) and need gigabytes per image set.
const MAX_SIZE: usize = 8192;
/// Fewest lights that determine a normal and an albedo.
const MIN_LIGHTS: usize = 3;
/// Relative amplitude of the `smooth` albedo texture: it spans value·(1 ± this).
const SMOOTH_AMPLITUDE: f32 = 0.3;
/// Ratio of the darker to the lighter square of the `checker` albedo.
const CHECKER_RATIO: f32 = 0.5;

/// Render a synthetic photometric-stereo data set (images, lights.json, mask.png and ground
/// truth) that `photostereo` reads directly:
///
///   data-synth --shape sphere --lights 24 --noise 0.01 -o scene/
///   photostereo scene/*.exr --lights scene/lights.json --mask scene/mask.png -o out/
///
/// The reflectance is Lambertian.
#[derive(Debug, Parser)]
#[command(
    name = "data-synth",
    version,
    verbatim_doc_comment,
    allow_negative_numbers = true
)]
struct Cli {
    /// Scene to render: a sphere, the built-in demo scene (fixed 320×240), or a pyramid and a
    /// Gaussian bump on a ground plane.
    #[arg(long, value_enum, default_value_t = ShapeArg::Sphere)]
    shape: ShapeArg,
    /// Image width and height in pixels (the image is N×N); ignored by --shape demo, which is
    /// fixed at 320×240.
    #[arg(long, default_value_t = 256, value_name = "N")]
    size: usize,
    /// Sphere radius in pixels (--shape sphere only) [default: 0.4 × size].
    #[arg(long, value_name = "R")]
    radius: Option<f64>,
    /// Albedo texture of the sphere or the bumps scene (the demo scene has its own textures):
    /// constant, a checkerboard of value and value/2 with squares of size/8 px, or a smooth
    /// texture value·(1 ± 0.3·sin·sin) of period size/4 px.
    #[arg(long, value_enum, default_value_t = AlbedoArg::Constant)]
    albedo: AlbedoArg,
    /// Albedo value in (0, 1] (the mean of the smooth texture, the lighter checker square);
    /// not used by --shape demo.
    #[arg(long, default_value_t = 0.7, value_name = "RHO")]
    albedo_value: f32,
    /// Number of lights, one image per light (at least 3).
    #[arg(long, default_value_t = 12, value_name = "N")]
    lights: usize,
    /// How light directions are spread: a Fibonacci spiral over the cap above --elevation, or
    /// a ring at --elevation.
    #[arg(long, value_enum, default_value_t = LightSetArg::Fibonacci)]
    light_set: LightSetArg,
    /// Light elevation above the image plane in degrees: the minimum for fibonacci (default 30,
    /// in [0, 90)), the ring's elevation for ring (default 45, in (0, 90)).
    #[arg(long, value_name = "DEG")]
    elevation: Option<f64>,
    /// Standard deviation of additive Gaussian noise, in image units (a white Lambertian
    /// surface facing the light is 1).
    #[arg(long, default_value_t = 0.0, value_name = "SIGMA")]
    noise: f32,
    /// Seed of the noise: the same seed and flags give byte-identical images.
    #[arg(long, default_value_t = 0, value_name = "S")]
    seed: u64,
    /// Do not compute cast shadows (attached shadows, n·l ≤ 0, are always present).
    #[arg(long)]
    no_cast_shadows: bool,
    /// Ambient light added as A·albedo to every pixel (0 for a dark room).
    #[arg(long, default_value_t = 0.0, value_name = "A")]
    ambient: f32,
    /// Image file format: float32 EXR, or 16-bit linear PNG (values clipped to [0, 1]).
    #[arg(long, value_enum, default_value_t = FormatArg::Exr)]
    format: FormatArg,
    /// Output folder (created if needed).
    #[arg(long, short, value_name = "DIR")]
    output: PathBuf,
}

/// `--shape` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum ShapeArg {
    /// A sphere centred in the image, no ground.
    Sphere,
    /// The library's built-in scene (320×240): hemisphere, bump, pyramid, dome on a ground.
    Demo,
    /// A pyramid and a Gaussian bump on a ground plane.
    Bumps,
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

/// `--light-set` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum LightSetArg {
    /// Near-uniform directions on a Fibonacci spiral.
    Fibonacci,
    /// Evenly spaced azimuths at one elevation.
    Ring,
}

/// `--format` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum FormatArg {
    /// Float32 EXR.
    Exr,
    /// 16-bit grey PNG.
    Png16,
}

/// Reflectance model used to render the images. Only Lambertian exists in the library today;
/// a `--brdf` flag selects among the variants once there is more than one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Brdf {
    /// Ideal diffuse reflection: albedo · max(0, n·l).
    Lambertian,
}

impl Brdf {
    /// Name for the summary line.
    fn name(self) -> &'static str {
        match self {
            Brdf::Lambertian => "Lambertian",
        }
    }

    /// Renders `scene` under `lights` with this reflectance model.
    fn render(
        self,
        scene: &Scene,
        lights: &Lights,
        options: &RenderOptions,
    ) -> photostereo::Result<Rendering> {
        match self {
            Brdf::Lambertian => render_lambertian(scene, lights, options),
        }
    }
}

/// Everything to do, validated: what `main` renders and writes.
#[derive(Debug)]
struct Plan {
    /// The scene to render.
    scene: Scene,
    /// `--shape` as given, for the summary.
    shape: ShapeArg,
    /// The lights, one per image.
    lights: Lights,
    /// `--light-set` and the elevation used, for the summary.
    light_set: (LightSetArg, f64),
    /// Reflectance model.
    brdf: Brdf,
    /// Noise, seed, shadows, ambient.
    render: RenderOptions,
    /// Image file format.
    format: ImageFormat,
    /// Output folder.
    output: PathBuf,
}

impl Cli {
    /// Checks every flag and builds the scene, the lights and the render options; fails with a
    /// message naming the flag at fault before anything is rendered or written.
    fn plan(self) -> Result<Plan> {
        ensure!(
            self.lights >= MIN_LIGHTS,
            "--lights {}: photometric stereo needs at least {MIN_LIGHTS} lights",
            self.lights
        );
        ensure!(
            (MIN_SIZE..=MAX_SIZE).contains(&self.size),
            "--size {}: must be between {MIN_SIZE} and {MAX_SIZE} pixels",
            self.size
        );
        if self.radius.is_some() && self.shape != ShapeArg::Sphere {
            bail!("--radius applies only to --shape sphere");
        }
        ensure!(
            self.albedo_value > 0.0 && self.albedo_value <= 1.0,
            "--albedo-value {}: must be in (0, 1]",
            self.albedo_value
        );
        ensure!(
            self.noise >= 0.0 && self.noise.is_finite(),
            "--noise {}: must be finite and ≥ 0",
            self.noise
        );
        ensure!(
            self.ambient >= 0.0 && self.ambient.is_finite(),
            "--ambient {}: must be finite and ≥ 0",
            self.ambient
        );
        let scene = self.scene()?;
        let (lights, elevation) = self.light_directions()?;
        check_no_stale_files(&self.output, self.lights, self.format)?;
        Ok(Plan {
            scene,
            shape: self.shape,
            lights,
            light_set: (self.light_set, elevation),
            brdf: Brdf::Lambertian,
            render: RenderOptions {
                cast_shadows: !self.no_cast_shadows,
                ambient: self.ambient,
                noise_sigma: self.noise,
                seed: self.seed,
            },
            format: self.format.image_format(),
            output: self.output,
        })
    }

    /// The albedo texture of `--albedo` and `--albedo-value`, scaled to the image size.
    fn albedo(&self) -> Result<Albedo> {
        let v = self.albedo_value;
        let size = self.size as f64;
        Ok(match self.albedo {
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

    /// The scene of `--shape`.
    fn scene(&self) -> Result<Scene> {
        let size = self.size as f64;
        Ok(match self.shape {
            ShapeArg::Sphere => {
                let radius = self.radius.unwrap_or(0.4 * size);
                // At least 1 px so that the sphere covers a pixel centre whatever the parity of
                // the size; at most size/2 so that its outline stays inside the image.
                ensure!(
                    radius >= 1.0 && radius <= size / 2.0,
                    "--radius {radius}: must be between 1 and size/2 = {} pixels so that the sphere fits in the {}×{} image",
                    size / 2.0,
                    self.size,
                    self.size
                );
                Scene::sphere(self.size, radius, self.albedo()?)
            }
            ShapeArg::Demo => Scene::default_scene(),
            ShapeArg::Bumps => bumps_scene(self.size, self.albedo()?),
        })
    }

    /// The lights of `--lights`, `--light-set` and `--elevation`, with the elevation used.
    fn light_directions(&self) -> Result<(Lights, f64)> {
        let n = self.lights;
        let (lights, elevation) = match self.light_set {
            LightSetArg::Fibonacci => {
                let e = self.elevation.unwrap_or(30.0);
                ensure!(
                    (0.0..90.0).contains(&e),
                    "--elevation {e}: the minimum elevation of --light-set fibonacci must be in [0, 90) degrees"
                );
                (Lights::fibonacci(n, e), e)
            }
            LightSetArg::Ring => {
                let e = self.elevation.unwrap_or(45.0);
                // At 90° every light of the ring is the same overhead light.
                ensure!(
                    e > 0.0 && e < 90.0,
                    "--elevation {e}: the elevation of --light-set ring must be in (0, 90) degrees"
                );
                (Lights::ring(n, e, 0.0), e)
            }
        };
        let lights = lights
            .with_context(|| format!("--lights {n} --light-set {}", self.light_set.name()))?;
        lights.check_usable(MAX_LIGHT_CONDITION).with_context(|| {
            format!(
                "--lights {n} --light-set {} --elevation {elevation}: the light set cannot determine normals",
                self.light_set.name()
            )
        })?;
        Ok((lights, elevation))
    }
}

impl LightSetArg {
    /// The flag value, as typed.
    fn name(self) -> &'static str {
        match self {
            LightSetArg::Fibonacci => "fibonacci",
            LightSetArg::Ring => "ring",
        }
    }
}

impl FormatArg {
    /// The library's image format.
    fn image_format(self) -> ImageFormat {
        match self {
            FormatArg::Exr => ImageFormat::Exr,
            FormatArg::Png16 => ImageFormat::Png16,
        }
    }
}

impl ShapeArg {
    /// The flag value, as typed.
    fn name(self) -> &'static str {
        match self {
            ShapeArg::Sphere => "sphere",
            ShapeArg::Demo => "demo",
            ShapeArg::Bumps => "bumps",
        }
    }
}

/// A `size`×`size` ground plane with a square pyramid (creases) on the left and a Gaussian bump
/// (smooth) on the right, everything with the same albedo; both cast shadows on the ground.
fn bumps_scene(size: usize, albedo: Albedo) -> Scene {
    let s = size as f64;
    Scene {
        width: size,
        height: size,
        objects: vec![
            (
                Primitive::Pyramid {
                    cx: -0.24 * s,
                    cy: 0.0,
                    half: 0.17 * s,
                    height: 0.12 * s,
                    base: 0.0,
                },
                albedo,
            ),
            (
                Primitive::Gaussian {
                    cx: 0.24 * s,
                    cy: 0.0,
                    sigma: 0.07 * s,
                    height: 0.14 * s,
                    base: 0.0,
                },
                albedo,
            ),
        ],
        ground: Some(albedo),
    }
}

/// Refuses to write into a folder holding `img_*` files that this run would not overwrite (left
/// by an earlier run with more lights or another format): the glob `DIR/img_*` would then pick
/// up images that `lights.json` does not describe.
fn check_no_stale_files(dir: &Path, lights: usize, format: FormatArg) -> Result<()> {
    if !dir.exists() {
        return Ok(());
    }
    ensure!(
        dir.is_dir(),
        "--output {}: exists and is not a folder",
        dir.display()
    );
    let ext = format.image_format().extension();
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

/// Renders and writes the data set; returns the summary line.
fn run(plan: &Plan) -> Result<String> {
    let rendering = plan
        .brdf
        .render(&plan.scene, &plan.lights, &plan.render)
        .context("rendering failed")?;
    ensure!(
        rendering.truth.mask.count() > 0,
        "the scene covers no pixel"
    );
    let clipped = if plan.format == ImageFormat::Png16 {
        rendering
            .images
            .iter()
            .flat_map(photostereo::grid::Grid::data)
            .filter(|v| **v > 1.0)
            .count()
    } else {
        0
    };
    let written = write_synthetic(&rendering, &plan.lights, &plan.output, plan.format)
        .with_context(|| format!("cannot write the data set to {}", plan.output.display()))?;
    if clipped > 0 {
        eprintln!(
            "warning: {clipped} samples above 1 were clipped to 1 in the 16-bit PNGs (and will read as saturated); lower --albedo-value or --ambient, or use --format exr"
        );
    }
    let (set, elevation) = plan.light_set;
    Ok(format!(
        "wrote {} files to {}: {} {} images {}×{} of {} ({}, {} {} lights {} {elevation}°, noise σ = {}, seed {}), lights.json, mask.png, ground truth and shadow masks",
        written.len(),
        plan.output.display(),
        plan.lights.len(),
        match plan.format {
            ImageFormat::Exr => "EXR",
            ImageFormat::Png16 => "16-bit PNG",
        },
        plan.scene.width,
        plan.scene.height,
        plan.shape.name(),
        plan.brdf.name(),
        plan.lights.len(),
        set.name(),
        match set {
            LightSetArg::Fibonacci => "above",
            LightSetArg::Ring => "at",
        },
        plan.render.noise_sigma,
        plan.render.seed,
    ))
}

/// Parses the flags, renders, writes, and prints the summary; errors print as `error: ...` with
/// exit status 1.
fn main() {
    let result = Cli::parse().plan().and_then(|plan| run(&plan));
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

    /// Parses a command line (program name added).
    fn cli(args: &[&str]) -> Cli {
        Cli::try_parse_from(std::iter::once("data-synth").chain(args.iter().copied()))
            .expect("flags parse")
    }

    /// The error message of planning `args`.
    fn plan_error(args: &[&str]) -> String {
        let mut all = args.to_vec();
        all.extend(["-o", "/nonexistent/data-synth-test"]);
        format!("{:#}", cli(&all).plan().expect_err("should be rejected"))
    }

    /// The defaults, and the per-shape and per-light-set defaults, give a valid plan.
    #[test]
    fn defaults_make_a_valid_plan() {
        let p = cli(&["-o", "/nonexistent/data-synth-test"]).plan().unwrap();
        assert_eq!((p.scene.width, p.scene.height), (256, 256));
        assert_eq!(p.lights.len(), 12);
        assert_eq!(p.light_set, (LightSetArg::Fibonacci, 30.0));
        assert_eq!(p.render, RenderOptions::default());
        assert_eq!(p.format, ImageFormat::Exr);
        let demo = cli(&[
            "--shape",
            "demo",
            "--size",
            "64",
            "-o",
            "/nonexistent/data-synth-test",
        ])
        .plan()
        .unwrap();
        assert_eq!((demo.scene.width, demo.scene.height), (320, 240));
        let ring = cli(&["--light-set", "ring", "-o", "/nonexistent/data-synth-test"])
            .plan()
            .unwrap();
        assert_eq!(ring.light_set, (LightSetArg::Ring, 45.0));
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
            (&["--albedo-value", "0"], "--albedo-value"),
            (
                &["--albedo", "smooth", "--albedo-value", "0.9"],
                "--albedo-value",
            ),
            (&["--noise", "-1"], "--noise"),
            (&["--ambient", "inf"], "--ambient"),
            (&["--elevation", "90"], "--elevation"),
            (&["--light-set", "ring", "--elevation", "90"], "--elevation"),
        ] {
            let e = plan_error(args);
            assert!(e.contains(flag), "{args:?}: {e}");
        }
    }

    /// The bumps scene covers the whole image and rises above the ground.
    #[test]
    fn bumps_scene_has_ground_and_both_shapes() {
        let hf = bumps_scene(64, Albedo::Constant(0.5)).height_field();
        assert_eq!(hf.mask.count(), 64 * 64);
        // The pyramid's apex and the bump's peak stand above the ground.
        let peak = hf.depth.data().iter().copied().fold(0.0, f32::max);
        assert!(peak > 0.1 * 64.0, "peak {peak}");
    }
}
