//! Helpers shared by the integration tests.
#![allow(dead_code)]

use photostereo::capture::lights::Lights;
use photostereo::eval::demo::synthesize;
use photostereo::synth::render::RenderOptions;
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

/// An argument as an `OsStr`.
pub fn os<S: AsRef<std::ffi::OsStr> + ?Sized>(s: &S) -> &std::ffi::OsStr {
    s.as_ref()
}

/// A noise-free sphere data set written as EXR files with `lights.json`; returns the image
/// paths in file order.
pub fn sphere_dataset(dir: &Path, format: ImageFormat) -> Vec<PathBuf> {
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
    write_synthetic(&synth.rendering, &lights, dir, format).unwrap();
    (0..10)
        .map(|k| dir.join(format!("img_{k:03}.{}", format.extension())))
        .collect()
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
