//! Helpers shared by the integration tests.
#![allow(dead_code)]

use photostereo::capture::dataset::Capture;
use photostereo::capture::lights::Lights;
use photostereo::capture::stack::ColorMode;
use photostereo::eval::demo::{SyntheticCapture, synthesize};
use photostereo::synth::reflectance::Material;
use photostereo::synth::render::{RenderOptions, Rendering, render};
use photostereo::synth::scene::{Albedo, Scene};
use photostereo::synth::write::{ImageFormat, write_synthetic};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The repository's top folder (the library's manifest folder; the command-line tool's tests
/// live one level down, in `cli/`).
pub fn repo() -> PathBuf {
    let m = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    if m.ends_with("cli") {
        m.parent().map(Path::to_path_buf).unwrap_or(m)
    } else {
        m
    }
}

/// `../shared/data` beside the repository, or `None` (the caller prints why it skips).
pub fn shared_data() -> Option<PathBuf> {
    let p = repo().join("../shared/data");
    p.is_dir().then_some(p)
}

/// Skips a test with a clear message when the shared data are absent.
#[macro_export]
macro_rules! require_shared {
    ($sub:expr) => {
        match common::shared_data()
            .map(|d| d.join($sub))
            .filter(|p| p.exists())
        {
            Some(p) => p,
            None => {
                eprintln!(
                    "SKIPPED: ../shared/data/{} is absent; this test needs the shared real data",
                    $sub
                );
                return;
            }
        }
    };
}

/// The photostereo binary built for these tests (the tests of the `cli/` package).
pub fn bin() -> PathBuf {
    // Set by cargo for the tests of the package that builds the binary (`cli/`) only.
    match option_env!("CARGO_BIN_EXE_photostereo") {
        Some(p) => PathBuf::from(p),
        None => panic!("the photostereo binary is built for the tests of the cli package only"),
    }
}

/// Runs the photostereo binary with `args`.
pub fn run(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(bin()).args(args).output().unwrap()
}

/// A finished run of the tool: exit code, standard output and error, wall time and peak
/// resident memory.
pub struct Measured {
    /// Exit code (`None`: killed by a signal).
    pub code: Option<i32>,
    /// Standard output.
    pub stdout: String,
    /// Standard error.
    pub stderr: String,
    /// Wall time, seconds.
    pub secs: f64,
    /// Peak resident memory, MiB.
    pub peak_mb: f64,
}

/// Runs the tool with `args` and measures it (Linux). The peak is the kernel's count of the
/// tool's resident memory (`ru_maxrss`), read by a small Python process that forks it: a
/// process started from a (large, multi-threaded) test would inherit the test's peak at `exec`.
pub fn measured(args: &[&std::ffi::OsStr]) -> Measured {
    const SHIM: &str = "import os, sys\n\
pid = os.fork()\n\
if pid == 0:\n    os.execv(sys.argv[1], sys.argv[1:])\n\
_, status, usage = os.wait4(pid, 0)\n\
print()\n\
print(usage.ru_maxrss)\n\
sys.exit(os.waitstatus_to_exitcode(status) % 256)\n";
    let start = std::time::Instant::now();
    let o = Command::new("python3")
        .arg("-c")
        .arg(SHIM)
        .arg(bin())
        .args(args)
        .output()
        .expect("python3 runs the tool");
    let stdout = String::from_utf8_lossy(&o.stdout);
    let (tool, last) = stdout
        .trim_end()
        .rsplit_once('\n')
        .unwrap_or(("", stdout.trim_end()));
    let peak_kib: f64 = last
        .trim()
        .parse()
        .expect("the peak memory on the last line");
    Measured {
        code: o.status.code(),
        stdout: tool.to_string(),
        stderr: String::from_utf8_lossy(&o.stderr).into_owned(),
        secs: start.elapsed().as_secs_f64(),
        // ru_maxrss is in KiB on Linux.
        peak_mb: peak_kib / 1024.0,
    }
}

/// An argument as an `OsStr`.
pub fn os<S: AsRef<std::ffi::OsStr> + ?Sized>(s: &S) -> &std::ffi::OsStr {
    s.as_ref()
}

/// The noise-free sphere the data sets below are rendered from: a 96² sphere with a smooth
/// albedo under 10 Fibonacci lights; returns the rendering and its lights.
pub fn sphere_synth() -> (SyntheticCapture, Lights) {
    let scene = Scene::sphere(
        96,
        40.0,
        Albedo::Smooth {
            mean: 0.6,
            amplitude: 0.2,
            period: 23.0,
        },
    );
    let lights = Lights::fibonacci(10, 30.0).unwrap();
    let synth = synthesize(scene, lights.clone(), &RenderOptions::default()).unwrap();
    (synth, lights)
}

/// A noise-free sphere data set ([`sphere_synth`]) written in `format` with `lights.json`;
/// returns the image paths in file order.
pub fn sphere_dataset(dir: &Path, format: ImageFormat) -> Vec<PathBuf> {
    let (synth, lights) = sphere_synth();
    write_synthetic(&synth.rendering, &lights, dir, format).unwrap();
    (0..10)
        .map(|k| dir.join(format!("img_{k:03}.{}", format.extension())))
        .collect()
}

/// Writes `lights` as a plain list, one `x y z` line per light, which pairs with the images
/// by position.
pub fn write_plain_lights(path: &Path, lights: &Lights) {
    let text: String = lights
        .directions()
        .iter()
        .map(|d| format!("{} {} {}\n", d.x, d.y, d.z))
        .collect();
    std::fs::write(path, text).unwrap();
}

/// The sphere set in `root/numbered`, renamed `frame.1.exr … frame.10.exr`, with a plain list
/// of lights; returns the folder, the images in numeric order and the lights file.
pub fn numbered_dataset(root: &Path) -> (PathBuf, Vec<PathBuf>, PathBuf) {
    let dir = root.join("numbered");
    let images: Vec<PathBuf> = sphere_dataset(&dir, ImageFormat::Exr)
        .into_iter()
        .enumerate()
        .map(|(k, p)| {
            let to = dir.join(format!("frame.{}.exr", k + 1));
            std::fs::rename(p, &to).unwrap();
            to
        })
        .collect();
    let text = dir.join("lights.txt");
    write_plain_lights(&text, &Lights::fibonacci(10, 30.0).unwrap());
    (dir, images, text)
}

/// The main command's arguments: `images`, `--lights lights`, the `extra` flags, `-q -o out`.
pub fn main_args(
    images: &[PathBuf],
    lights: &Path,
    extra: &[&str],
    out: &Path,
) -> Vec<std::ffi::OsString> {
    let mut a: Vec<std::ffi::OsString> =
        images.iter().map(|p| p.clone().into_os_string()).collect();
    a.extend(["--lights".into(), lights.as_os_str().to_owned()]);
    a.extend(extra.iter().map(std::ffi::OsString::from));
    a.extend(["-q".into(), "-o".into(), out.as_os_str().to_owned()]);
    a
}

/// Files in a folder (names), sorted.
pub fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|r| {
            r.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// A sphere on a ground plane beside a pyramid (attached and cast shadows) of `material`,
/// `size`² pixels, under `lights` Fibonacci lights up to 30° from the horizon's zenith, with
/// noise σ 0.005 (seed 3): the grey capture under the scene's mask, and the rendering with its
/// ground truth.
pub fn sphere_on_ground(material: Material, lights: usize, size: usize) -> (Capture, Rendering) {
    let lights = Lights::fibonacci(lights, 30.0).unwrap();
    let scene = Scene::sphere_on_ground(size, material);
    let options = RenderOptions {
        noise_sigma: 0.005,
        seed: 3,
        ..RenderOptions::default()
    };
    let r = render(&scene, &lights, &options).unwrap();
    let stack = r.to_stack(&lights, ColorMode::Grey).unwrap();
    let capture = Capture::from_stack(stack, lights, Some(r.truth.mask.clone())).unwrap();
    (capture, r)
}

/// Runs `f` in a pool of `threads` threads of its own (results that must not depend on the
/// thread count are compared across pools).
pub fn with_threads<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a thread pool")
        .install(f)
}
