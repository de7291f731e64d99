//! The library API in a few lines: write a synthetic data set, load it as a user's capture,
//! reconstruct, write the outputs, and measure the normals against the ground truth.
//!
//! `cargo run --release --example library [OUT_DIR]`

use photostereo::capture::dataset::Capture;
use photostereo::capture::stack::LoadOptions;
use photostereo::eval::metrics::angular_errors;
use photostereo::io::decode::read_normal_map;
use photostereo::progress::Silent;
use photostereo::run::pipeline::{Config, reconstruct, write_outputs};
use photostereo::synth::write::{GROUND_TRUTH_DIR, ImageFormat, write_synthetic};
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "out-library".into()),
    );
    let scene = out.join("scene");

    // A data set on disk: the built-in scene, 12 lights, noise σ = 0.005.
    let synth = photostereo::eval::demo::default_capture(0.005, 7)?;
    write_synthetic(
        &synth.rendering,
        &synth.capture.lights,
        &scene,
        ImageFormat::Exr,
    )?;

    // Load it as any capture: images, lights file, mask.
    let images: Vec<PathBuf> = (0..12)
        .map(|k| scene.join(format!("img_{k:03}.exr")))
        .collect();
    let capture = Capture::from_files(
        &images,
        &scene.join("lights.json"),
        Some(&scene.join("mask.png")),
        &LoadOptions::default(),
        &Silent,
    )?;

    // Solve, integrate, write.
    let config = Config::default();
    let mut recon = reconstruct(&capture, &config, &Silent)?;
    write_outputs(&mut recon, &capture, &config, &out, None)?;

    // Compare with the ground truth.
    let gt = read_normal_map(&scene.join(GROUND_TRUTH_DIR).join("normal_gt.exr"))?;
    let err = angular_errors(&recon.maps.normals, &gt, &capture.mask)?;
    println!(
        "mean angular error {:.3}° over {} pixels; outputs in {}",
        err.mean_deg,
        err.pixels,
        out.display()
    );
    Ok(())
}
